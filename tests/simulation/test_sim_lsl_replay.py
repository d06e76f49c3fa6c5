"""LSL replay (issue 27 item 1's inlet): a lab's own taxel device publishes on LSL (an outlet in this process, paced to
the wall clock) and the simulated rig's taxel board streams it (`open_rig("replay", source="lsl:NAME")`, i.e.
`rigctl acquire --replay lsl:NAME`): a recorded trial holds consecutive samples of the stream, none repeated or lost.
The pty rig (paced to the wall clock, as the device is): `realtime`. The source's own logic (a stream that falls
behind) is judged on a device that pushes when told, not on the wall clock. Loopback only (LSLAPICFG:
tests/conftest.py)."""

from __future__ import annotations

import threading
import time
import uuid

import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.acquisition.protocol import parse_protocol
from rigctl.acquisition.runner import run_protocol
from rigctl.cli import main
from rigctl.rigs import open_rig
from rigctl.storage.session import open_session

N_CH = 6
RATE_HZ = 1000.0


def _sample(i: np.ndarray) -> np.ndarray:
    """Sample i of the device: channel 0 = i mod 1000, channel 1 = i // 1000 mod 1000, then fixed offsets."""
    i = np.asarray(i, dtype=np.int64)
    cols = [i % 1000, (i // 1000) % 1000] + [(i + 37 * k) % 1000 for k in range(2, N_CH)]
    return np.stack(cols, axis=1).astype(np.int32)


def _index(rows: np.ndarray) -> np.ndarray:
    return rows[:, 0].astype(np.int64) + 1000 * rows[:, 1].astype(np.int64)


def _outlet(pylsl, name):
    """The device's outlet: N_CH int32 channels at RATE_HZ, 10-bit readings."""
    info = pylsl.StreamInfo(name, "Tactile", N_CH, RATE_HZ, pylsl.cf_int32, f"{name}-src")
    info.desc().append_child_value("adc_bits", "10")
    return pylsl.StreamOutlet(info)


class Device(threading.Thread):
    """An LSL taxel device: N_CH int32 channels at 1 kHz, pushed every 10 ms as the wall clock says."""

    def __init__(self, pylsl, name):
        super().__init__(daemon=True)
        self.outlet = _outlet(pylsl, name)
        self.halt = threading.Event()
        self.hold = threading.Event()  # set: nothing is pushed (a starved device), the samples due pile up
        self.sent = 0

    def run(self):
        t0 = time.monotonic()
        while not self.halt.is_set():
            due = int((time.monotonic() - t0) * RATE_HZ)
            if due > self.sent and not self.hold.is_set():
                self.outlet.push_chunk(_sample(np.arange(self.sent, due)))
                self.sent = due
            time.sleep(0.01)


@pytest.mark.lsl
# wall: an LSL stream (timestamps of LSL's local_clock, the wall)
@pytest.mark.realtime
def test_a_live_lsl_stream_is_recorded_through_the_simulated_board(lsl, tmp_path):
    name = f"fingertip-{uuid.uuid4().hex[:8]}"
    device = Device(lsl, name)
    device.start()
    try:
        proto = parse_protocol('name = "lsl_replay"\ntextures = ["A"]\nspeeds_mm_s = [120]\nforces_g = [300]\n'
                               'trials_per_condition = 2\nduration_s = 1.0\n')
        with open_rig("replay", source=f"lsl:{name}", host_config_path=tmp_path / "rig.json") as rig:
            assert rig.layout.n_channels == N_CH and rig.layout.sample_rate_hz == RATE_HZ
            summary = run_protocol(proto, tmp_path / "s.h5", rig=rig)
            underruns = rig.backend.sim.source.underrun_samples
    finally:
        device.halt.set()
        device.join(5)
    assert summary.ok, summary.lines()
    with open_session(tmp_path / "s.h5") as s:
        for tid in s.completed_ids():
            t = s.trial(tid)
            idx = _index(t.taxels)
            assert t.taxels.shape == (1000, N_CH)
            assert np.array_equal(np.diff(idx), np.ones(999, dtype=np.int64)), (tid, underruns)  # consecutive
            assert np.array_equal(t.taxels, _sample(idx))
    print(f"{device.sent} samples sent; {underruns} periods the board had no sample for while the stream lagged")


class Pushed:
    """An LSL taxel device like :class:`Device` whose samples are pushed when the test says, not as the wall clock
    goes: what the source has received is then known exactly (:func:`_arrived`), whatever the machine's load."""

    def __init__(self, pylsl, name):
        self.outlet = _outlet(pylsl, name)
        self.sent = 0

    def push(self, n: int) -> None:
        self.outlet.push_chunk(_sample(np.arange(self.sent, self.sent + n)))
        self.sent += n

    def push_once_consumed(self, n: int) -> threading.Thread:
        """Push ``n`` samples as soon as an inlet has opened the stream (in a thread: the source's constructor waits
        for its prebuffer meanwhile)."""

        def run():
            assert self.outlet.wait_for_consumers(HANG_S), "no inlet opened the stream"
            self.push(n)

        t = threading.Thread(target=run, daemon=True)
        t.start()
        return t


#: a bound on a wait for samples already pushed: only a hang reaches it (the machine may be loaded 3x)
HANG_S = 30.0


def _arrived(src, n: int) -> None:
    """Wait until the source holds ``n`` samples not yet read (everything pushed has arrived)."""
    deadline = time.monotonic() + HANG_S
    while src._n_pending < n:
        assert time.monotonic() < deadline, f"{src._n_pending} of {n} pushed samples arrived in {HANG_S:g} s"
        time.sleep(0.005)
    assert src._n_pending == n


@pytest.mark.lsl
def test_a_stream_that_falls_behind_is_never_filled_in(lsl):
    """A stream held up longer than the prebuffer: the board gets fewer samples than are due (it sends no frame for
    the others: the host counts them lost, the trial is recorded again), never a repeated one; then none until the
    prebuffer is full again (else every later chunk would come just too late), even with some samples in; every
    sample it gets is the stream's next, none lost. The device pushes when told (the samples in known), not paced by
    the wall clock: a starved pacing thread once pushed a late backlog into the source mid-test."""
    from rigctl.simulation.lsl_replay import LslReplay

    name = f"fingertip-{uuid.uuid4().hex[:8]}"
    device = Pushed(lsl, name)
    first = device.push_once_consumed(300)
    src = LslReplay(name, prebuffer_s=0.25)  # returns once 250 samples (the prebuffer) are in
    try:
        first.join(HANG_S)
        _arrived(src, 300)
        got, asked = [], 0
        while not got or len(got[-1]) == 50:  # the stream stalls: nothing more is pushed
            got.append(src.read(50))
            asked += 50
            assert len(got) < 1000
        short = sum(len(g) for g in got)
        assert short == 300 and asked == 350 and src.underrun_samples == asked - short
        device.push(100)  # fewer than the prebuffer's 250: held back
        _arrived(src, 100)
        assert len(src.read(50)) == 0 and src.underrun_samples == 100
        device.push(300)
        _arrived(src, 400)
        got.append(src.read(50))
        assert len(got[-1]) == 50  # buffered again
        while len(part := src.read(50)) == 50:  # the stream stalls again
            got.append(part)
        got.append(part)
        assert len(src.read(50)) == 0  # behind again: nothing until the prebuffer is full
        assert src.underrun_samples == 100 + 50 + 50
    finally:
        src.close()
    idx = _index(np.concatenate(got))
    assert np.array_equal(idx, np.arange(device.sent))  # the stream's own, in order, none lost or repeated


def test_the_command_takes_lsl_names_and_refuses_a_missing_stream(tmp_path, monkeypatch):
    monkeypatch.setitem(__import__("sys").modules, "pylsl", None)
    monkeypatch.setenv("RIGCTL_CONFIG", str(tmp_path / "none.json"))
    res = CliRunner().invoke(main, ["acquire", "quick_check", "--out", str(tmp_path / "s.h5"), "--replay", "lsl:",
                                    "--quiet"])
    assert res.exit_code == 2 and "lsl:NAME" in res.output
    res = CliRunner().invoke(main, ["acquire", "quick_check", "--out", str(tmp_path / "s.h5"), "--replay",
                                    "lsl:nobody", "--quiet"])
    assert res.exit_code == 1 and res.output.startswith("Error: LSL streaming needs pylsl"), res.output
    assert not (tmp_path / "s.h5").exists()
