"""A scan older than its cue is refused, never recorded (issue 56, "Done when"): a tracker's stamps on another clock
than the one they are read on (every pass then looks newer than every cue: the same pass recorded for every trial),
or a pass that arrived before the operator was cued."""

from __future__ import annotations

import re
import threading
import time
import uuid

import numpy as np
import pytest

from rigctl.core.handheld import MARGIN_S, STAMP_AHEAD_S, ScanError, refuse_older_than_cue, wait_for_pass

PASS = ([0.0, 0.3, 3.0, 3.2, 4.0], [15.0, 15.0, 285.0, 15.0, 15.0])  # rest, 100 mm/s over the plate, back, rest


def _pass_at(t: np.ndarray, start: float) -> np.ndarray:
    return np.interp(t - start, *PASS)


class _Recorded:
    """A tracker whose samples are all there already: one pass stamped ``ahead_s`` after the arrival of each."""

    name, channels = "fake", (0,)

    def __init__(self, arrived: np.ndarray, ahead_s: float) -> None:
        self.arrived = arrived
        self.t = arrived + ahead_s
        self.x = _pass_at(arrived, float(arrived[0]))[:, None]

    def since_received(self, t0: float):
        sel = self.t >= t0
        return self.t[sel], self.x[sel], self.arrived[sel]

    def since(self, t0: float):
        return self.since_received(t0)[:2]


def test_a_pass_stamped_after_it_arrived_is_refused():
    """Samples stamped an hour after they arrived (a bridge stamping another clock than LSL's): the pass, which arrived
    before the cue, looks newer than it; refused with the reason (old main returned it: every trial the same pass)."""
    now = time.monotonic()
    tracker = _Recorded(now - 4.5 + np.arange(0, 4.0, 1 / 120), 3600.0)
    with pytest.raises(ScanError, match="stamped 3600.0.. s after they arrived"):
        wait_for_pass(tracker, lambda x: x[:, 0], now, timeout_s=1.0)


def test_a_pass_that_arrived_before_its_cue_is_refused_and_one_after_it_is_taken():
    t = np.arange(0, 4.0, 1 / 120)
    stamped = 0.8 * STAMP_AHEAD_S  # within the stamps' tolerance
    x = _pass_at(t, 0.0)
    entry = int(np.flatnonzero(x >= 50.0)[0])
    # the entry arrived MARGIN_S + 0.05 s before the cue: older than its cue
    cue = float(t[entry]) + MARGIN_S + 0.05
    with pytest.raises(ScanError, match="a scan older than its cue"):
        refuse_older_than_cue(t + stamped, t, entry, cue)
    refuse_older_than_cue(t + stamped, t, entry, float(t[entry]) + MARGIN_S - 0.05)  # a hand that went on the cue
    refuse_older_than_cue(t, t, entry, float(t[entry]) - 1.0)  # after its cue
    with pytest.raises(ScanError, match="stamped 0.150 s after"):
        refuse_older_than_cue(t + 0.15, t, entry, float(t[entry]) - 1.0)


PROTO = """
name = "hh_bridge"
rig = "handheld"
textures = ["L"]
forces_g = [500]
trials_per_condition = 1
travel_mm = 200
speeds_mm_s = [100]
retries = 1
"""


class _BridgeOnAnotherClock:
    """An LSL tracker (one channel, 120 Hz) that stamps its samples with a clock an hour ahead of liblsl's (a bridge
    stamping its own clock: liblsl's time correction, 0 on one machine, cannot see it), a pass every 4 s."""

    def __init__(self, pylsl, name: str) -> None:
        info = pylsl.StreamInfo(name, "Position", 1, 120.0, pylsl.cf_float32, f"bridge-{name}")
        self.outlet = pylsl.StreamOutlet(info)
        self.pylsl, self.halt = pylsl, threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        t0, k = self.pylsl.local_clock(), 0
        while not self.halt.is_set():
            while t0 + k / 120 <= self.pylsl.local_clock():
                x = float(np.interp((k / 120) % 4.0, *PASS))
                self.outlet.push_sample([x], t0 + k / 120 + 3600.0)
                k += 1
            time.sleep(0.005)

    def close(self) -> None:
        self.halt.set()
        self.thread.join(2)


# wall: an LSL stream (timestamps of LSL's local_clock, the wall)
@pytest.mark.realtime
def test_a_tracker_stamping_another_clock_records_nothing(lsl, tmp_path):
    """Each cue's pass is refused (stamped an hour after it arrived) and the trial fails with that reason after its
    retries: nothing recorded (old main recorded the tracker's oldest buffered pass for every cue, 3,600 s off)."""
    from rigctl.acquisition.protocol import parse_protocol
    from rigctl.acquisition.runner import run_protocol
    from rigctl.rigs import open_rig
    from rigctl.storage.session import open_session

    name = f"bridge-{uuid.uuid4().hex[:8]}"
    bridge = _BridgeOnAnotherClock(lsl, name)
    try:
        with open_rig("handheld", motion=f"lsl:{name}@0", host_config_path=tmp_path / "rig.json",
                      resolve_s=30.0, timeout_s=30.0) as rig:
            summary = run_protocol(parse_protocol(PROTO), tmp_path / "s.h5",
                                   rig=rig)
    finally:
        bridge.close()
    assert not summary.ok
    assert any(re.search(r"stamped 3[56]\d\d\.\d+ s after they arrived", str(f)) and "refused, not recorded" in str(f)
               for f in summary.failures), \
        summary.failures
    with open_session(tmp_path / "s.h5") as s:
        assert s.completed_ids() == []


def test_the_boards_encoder_path_refuses_a_tracker_stamped_ahead_before_the_board_starts():
    """--onboard-encoder: the host refuses the pass before it sends the board ENCODE (nothing written to the port)."""
    from rigctl.core.trial import PlannedTrial
    from rigctl.devices.onboard_finger import BoardRange, OnboardFingerScans

    class Port:
        written = b""

        def write(self, data: bytes) -> None:
            self.written += bytes(data)

        def read(self, n: int = 1) -> bytes:
            return b""

        in_waiting = 0

    now = time.monotonic()
    tracker = _Recorded(now - 4.5 + np.arange(0, 4.0, 1 / 120), 3600.0)
    port = Port()
    board = BoardRange.of(np.full(9, 100.0), np.full(9, 900.0), 100)
    scans = OnboardFingerScans(port, "fake", tracker, None, board, timeout_s=2.0)
    with pytest.raises(ScanError, match="stamped 3600.0.. s after they arrived"):
        scans.scan(PlannedTrial(0, "L", 100.0, 500.0, 2.0, "medium"))
    assert port.written == b""
