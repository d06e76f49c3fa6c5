"""The HIL rig's live taxel signal: the Uno firmware streams readings rendered from the Mega firmware's drum
travel and contact force (rigctl.simulation.hil live mode)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from rigctl.devices.drum import DrumClient
from rigctl.devices.taxel_stream import TaxelStream
from rigctl.rigs import WATCHDOG_MS, drum_answer_timeout_s

from .conftest import home

pytestmark = pytest.mark.hil

#: captures tried: one whose swaps all came in time is judged (a starved feeder's late swap may jump)
CAPTURES = 3


def test_live_taxel_signal_follows_the_drum_without_seams(hil_rig):
    """Live mode: the readings are rendered from the Mega's drum travel and force; waveform swaps (every 0.5 s)
    continue the texture's phase and amplitude, so the stream has no seams. Judged on a capture during which every
    swap came in time, as the feeder measured it (:attr:`HilRig.live_swaps`): a swap that skipped past the rows
    continuing the old waveform, or found it run out (a starved feeder), may jump, and the capture is taken again."""
    rig = hil_rig
    # the drum's waits on the Mega's simulated clock (simavr runs slower than real time on a starved machine)
    # the answer timeout and host watchdog of the firmware under simavr, as open_rig("hil") sets them (paced to the
    # wall clock: late on a loaded machine)
    with DrumClient(rig.drum_port, clock=rig.clock, timeout_s=drum_answer_timeout_s("hil"),
                    watchdog_ms=WATCHDOG_MS["hil"]) as drum, \
            TaxelStream(rig.taxel_port) as stream:
        rig.set_texture("B")  # circular ridges
        home(drum)
        drum.set_force(500)
        drum.set_speed(40)
        drum.run()
        stream.start()
        drum.wait_force_settled(timeout_s=10.0)
        tries = []
        for _ in range(CAPTURES):
            t0 = time.monotonic()
            stream.begin_capture()
            while not stream.wait_capture(2500, timeout_s=0.2):
                drum.read_status()  # keep the watchdog fed
            cap = stream.end_capture()
            t1 = time.monotonic()
            with rig._render_lock:  # a swap under way has been measured
                late = [s for s in tuple(rig.live_swaps) if s.loaded_s < t1 and s.done_s > t0 and s.late]
            tries.append([s.delay_rows for s in late])
            if not late:
                break
        drum.stop()
    assert not late, f"every capture had a late swap (rows skipped; None: the waveform had run out): {tries}"
    x = cap.samples.astype(float)
    assert x.std(axis=0).mean() > 20  # the ridges pass under the taxels
    worst, step = _worst_step(x)
    # the model's own largest 1 ms step for this motion (steep ridge edges + noise), ~30 counts: a seam (a jump
    # of the texture's phase or shape at a waveform swap) is a step well beyond it
    own = _worst_step(_model_signal(rig, speed_mm_s=40.0, force_g=500.0))[1]
    assert 10 < own < 60
    assert step < 1.5 * own, f"a seam of {step:.0f} counts (model's own max step {own:.0f}) at sample {worst} of {len(x)}"


def _worst_step(x: np.ndarray) -> tuple[int, float]:
    steps = np.abs(np.diff(np.asarray(x, dtype=float), axis=0)).max(axis=1)
    worst = int(np.argmax(steps))
    return worst, float(steps[worst])


def _model_signal(rig, speed_mm_s: float, force_g: float, seconds: float = 10.0) -> np.ndarray:
    from rigctl.simulation.model import SensorModel

    position = np.arange(int(seconds * 1000)) / 1000.0 * speed_mm_s
    return SensorModel(rig.config.sensor).render("B", position, force_g, np.random.default_rng(1))


def test_seam_check_detects_a_phase_jump(hil_rig):
    """The seam check fails on the model's own signal with a 1 mm phase jump spliced in (a seam)."""
    x = _model_signal(hil_rig, 40.0, 500.0, seconds=3.0).astype(float)
    own = _worst_step(_model_signal(hil_rig, 40.0, 500.0))[1]
    assert _worst_step(x)[1] < 1.5 * own
    y = np.concatenate([x[:1500], x[1525:]])  # 25 ms = 1 mm of travel missing
    assert _worst_step(y)[1] >= 1.5 * own
