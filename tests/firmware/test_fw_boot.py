"""The boards' real bootloaders under simavr (stk500v2 on the Mega, optiboot on the Uno), each reset when a host
opens its port (the DTR auto-reset): the host must connect every time and never trap the Mega's bootloader."""

from __future__ import annotations

import os
import threading
import time

import numpy as np
import pytest

from rigctl.devices import wire
from rigctl.devices.drum import MEGA_BOOT_WINDOW_S, DrumClient
from rigctl.devices.errors import DrumError, DrumTimeout
from rigctl.devices.ports import is_exclusive
from rigctl.devices.taxel_stream import TaxelStream
from rigctl.rigs import drum_answer_timeout_s
from rigctl.simulation import hil

pytestmark = pytest.mark.hil


@pytest.fixture(scope="module")
def mega_boot_rig(fw_build):
    """The Mega alone with its bootloader, for the Mega's tests: no Uno core simulated beside it (~0.2 of a CPU core
    for the ~80 s they take) and none to keep its clock in lock step with."""
    with hil.HilRig(bootloaders=True, live=False, with_uno=False) as rig:
        yield rig


@pytest.fixture(scope="module")
def boot_rig(fw_build):
    """Both boards with their bootloaders; a fixed waveform (no live rendering: the CPU goes to the cores)."""
    with hil.HilRig(bootloaders=True, live=False) as rig:
        yield rig


def _client(rig: hil.HilRig, **kw) -> DrumClient:
    kw.setdefault("boot_wait_s", rig.drum_boot_wait_s)
    kw.setdefault("boot_quiet_s", rig.drum_boot_quiet_s)
    return DrumClient(rig.drum_port, timeout_s=drum_answer_timeout_s("hil"), clock=rig.clock, **kw)


def _first_answer_s(rig: hil.HilRig, drum: DrumClient, t0: float) -> float:
    drum.read_status()
    return rig.clock.now() - t0


@pytest.mark.timeout(900)  # 5 s of programming-mode timeout; a starved machine simulates slower than real time
def test_the_stk500v2_window_is_measured_and_a_host_sending_at_once_is_trapped(mega_boot_rig):
    """Today's host (sends at once, retries every 0.5 s): the Mega's bootloader takes the first request for a
    programmer and every retry keeps it there, so it never answers."""
    rig = mega_boot_rig
    for _attempt in range(TRAP_ATTEMPTS):
        first_write_s = _world_at_first_write(rig)
        t_open = rig.clock.now()
        drum = _client(rig, boot_wait_s=0.0, boot_quiet_s=0.0, retries=4)
        try:
            with drum:
                drum.read_status()
        except DrumTimeout:
            assert first_write_s[0] - t_open <= MEGA_BOOT_WINDOW_S  # trapped by a request sent within the window
            break
        # answered: only a host whose first request left after the window may be (the sketch had started); the
        # window is of the world's time, and the world runs on wall-time grants while a starved client's thread
        # waits for the CPU between its open and its write (CI run 2 at e99a99e): not "a host sending at once"
        sent_after_s = first_write_s[0] - t_open
        assert sent_after_s > MEGA_BOOT_WINDOW_S, (
            f"a request sent {sent_after_s:.3f} s after the open (the window: {MEGA_BOOT_WINDOW_S} s) was answered")
        rig.clock.sleep(6.0)  # the bootloader's programming-mode timeout, should a retry have trapped it
    else:
        pytest.fail(f"in {TRAP_ATTEMPTS} opens the client never sent within the bootloader's window of its open")
    # the sketch did start once the host went quiet (the bootloader's 5 s programming-mode timeout)
    n = len(rig.boot_times_s)
    deadline = rig.clock.now() + 10.0
    while len(rig.boot_times_s) == n:
        assert rig.clock.now() < deadline, "the bootloader never started the sketch after the host went quiet"
        rig.clock.sleep(0.05)
    assert rig.boot_times_s[-1] > 4.0  # trapped for the programming-mode timeout, not the 0.83 s window
    # a quiet open: the window alone, as measured on the bootloader's own loop
    with _client(rig) as drum:
        drum.read_status()
    rig.next_telemetry()  # the harness's lines up to now read: this boot's APP among them, however late
    assert abs(rig.boot_times_s[-1] - MEGA_BOOT_WINDOW_S) < 0.05


#: opens tried until one sends its first request within the bootloader's window (a saturated CPU can hold a client's
#: thread between its open and its write while the world runs on)
TRAP_ATTEMPTS = 4


def _world_at_first_write(rig: hil.HilRig) -> list[float]:
    """A one-element list that gets the world's time (s) at the next stamped write of a host of this process (inf until
    then): the clock's ``on_stamp`` wrapped, then restored at that write."""
    clock = rig.clock
    inner = clock.on_stamp
    seen = [float("inf")]

    def stamp(path: str, written: bool, n_bytes: int) -> None:
        if written and n_bytes > 0 and seen[0] == float("inf"):
            seen[0] = clock.now()
            clock.on_stamp = inner
        if inner is not None:
            inner(path, written, n_bytes)

    clock.on_stamp = stamp
    return seen


def _stratified(rng: np.random.Generator, n: int, low_s: float, high_s: float) -> np.ndarray:
    """``n`` delays (s), one at a random moment in each of ``n`` equal slices of ``[low_s, high_s)``, in random order:
    the range is covered evenly (no slice wider than ``(high_s - low_s) / n`` left out, which 30 uniform draws did
    not promise either)."""
    edges = np.linspace(low_s, high_s, n + 1)
    return rng.permutation(edges[:-1] + rng.uniform(0.0, 1.0, n) * np.diff(edges))


#: openings by a new client after the last close, and openings under a polling host
N_NEW_CLIENT, N_UNDER_POLLER = 10, 5


@pytest.mark.timeout(900)  # ~18 s of the Mega's simulated time; a starved machine simulates slower than real time
def test_openings_at_random_moments_all_connect(mega_boot_rig):
    """15 openings of the Mega's port: 10 by a new client at a random moment after the last close (one in each
    0.12 s slice of 0-1.2 s), 5 while a host polls (its port fails under it, it reopens: the board resets under the
    poller; one in each 0.16 s slice of 0.2-1.0 s). Every one gets answers; the time to the first answer is
    reported."""
    rig = mega_boot_rig
    rng = np.random.default_rng(22)
    first_s: list[float] = []
    rig.next_telemetry()
    boots0 = len(rig.boot_times_s)
    for delay_s in _stratified(rng, N_NEW_CLIENT, 0.0, 1.2):
        time.sleep(float(delay_s))
        t0 = rig.clock.now()
        with _client(rig) as drum:
            first_s.append(_first_answer_s(rig, drum, t0))
    with _client(rig) as drum:
        polled: dict = {"error": None}
        answers: list[int] = []  # drum.boot_waits (opens waited out so far) at each answer
        stop = threading.Event()

        def poll():
            try:
                while not stop.is_set():
                    drum.read_status()
                    answers.append(drum.boot_waits)
            except Exception as exc:  # noqa: BLE001 - reported below
                polled["error"] = exc

        poller = threading.Thread(target=poll, daemon=True)
        poller.start()
        try:
            for delay_s in _stratified(rng, N_UNDER_POLLER, 0.2, 1.0):
                time.sleep(float(delay_s))
                with drum._lock:  # the USB link drops under the poller: its next request reopens the port
                    drum._client.close()
                    opens = drum.boot_waits
                t0 = rig.clock.now()
                # the first answer after the reopen (one with more opens waited out than before the close)
                while not (answers and answers[-1] > opens) and polled["error"] is None and poller.is_alive():
                    time.sleep(0.01)
                first_s.append(rig.clock.now() - t0)
        finally:
            stop.set()
            poller.join(timeout=60)
    assert polled["error"] is None, f"the polling host failed: {polled['error']!r}"
    first = np.array(first_s)
    rig.next_telemetry()
    boots = np.array(list(rig.boot_times_s)[boots0:])
    print(f"{len(first)}/{N_NEW_CLIENT + N_UNDER_POLLER} openings connected; time to the first answer (Mega's "
          f"simulated time): median {np.median(first):.2f}"
          f" s, min {first.min():.2f} s, max {first.max():.2f} s; {len(boots)} boot windows {boots.min():.3f}-"
          f"{boots.max():.3f} s; load {open('/proc/loadavg').read().split()[0]}")
    print("  per opening (s): " + " ".join(f"{v:.2f}" for v in first))
    assert len(first) == N_NEW_CLIENT + N_UNDER_POLLER
    # never trapped: no opening took the bootloader's 5 s programming-mode timeout
    assert len(boots) >= N_NEW_CLIENT + N_UNDER_POLLER and boots.max() < 1.0
    assert first.max() < 5.0


def test_a_second_program_cannot_open_the_port_and_reset_the_board_under_a_polling_host(mega_boot_rig):
    """The host holds its port in the tty's exclusive mode (TIOCEXCL): another program's open() fails in the kernel
    before DTR is raised, so it cannot reset the board (root bypasses TIOCEXCL: then only the advisory lock refuses
    the second client, after its open has reset the board, and the reset is not checked)."""
    rig = mega_boot_rig
    with _client(rig) as drum:
        drum.read_status()
        assert is_exclusive(drum._client.socket)
        rig.next_telemetry()  # this client's boot's APP read
        n = len(rig.boot_times_s)
        with pytest.raises(DrumError):
            _client(rig).open()
        if os.geteuid() != 0:
            with pytest.raises(OSError):
                os.close(os.open(rig.drum_port, os.O_RDWR | os.O_NOCTTY))
        for _ in range(3):
            drum.read_status()
        if os.geteuid() != 0:
            rig.next_telemetry()
            assert len(rig.boot_times_s) == n  # no reset


@pytest.mark.timeout(900)
def test_the_uno_stream_opens_through_optiboot_every_time(boot_rig, wait_frames):
    rig = boot_rig
    rig.play_waveform(np.full((10, wire.N_TAXELS), 512, dtype=np.uint16))
    for _ in range(3):  # each open resets the Uno into optiboot again
        t0 = time.monotonic()
        # the banner comes 1 s of the Uno's simulated time after the open; a starved machine simulates slower than
        # real time, so the wait is for the banner, not for 3 s of host time
        with TaxelStream(rig.taxel_port, banner_timeout_s=60.0) as stream:
            banner_s = time.monotonic() - t0
            stream.start()
            stream.begin_capture()
            assert wait_frames(stream, 200)
            cap = stream.end_capture()
        assert np.all(cap.samples == 512)
        print(f"Uno: banner {banner_s:.2f} s (host time) after the open; optiboot held the Uno "
              f"{rig.uno_boot_times_s[-1]:.3f} s (simulated)")


def _capture(rig: hil.HilRig, wait_frames, n: int) -> np.ndarray:
    """The stream's frames from its very first (the capture begins before START)."""
    with TaxelStream(rig.taxel_port, banner_timeout_s=60.0) as stream:
        stream.begin_capture()
        stream.start()
        assert wait_frames(stream, n)
        return stream.end_capture().samples


def test_a_waveform_loaded_while_the_uno_sits_in_optiboot_plays_from_its_first_scan(boot_rig, wait_frames):
    """A waveform loaded while the Uno runs no scans (a host's open has just reset it into optiboot) has no row
    boundary to wait for: the stream's first frame, the first scan after the reset, already plays it (CI once saw
    that first frame play the harness's default pattern instead)."""
    rig = boot_rig
    rig.play_waveform(np.full((10, wire.N_TAXELS), 100, dtype=np.uint16))
    assert np.all(_capture(rig, wait_frames, 50) == 100)
    new_rows = (300 + np.arange(10, dtype=np.uint16))[:, None].repeat(wire.N_TAXELS, axis=1)
    new_rows = new_rows[:7]
    fd = os.open(rig.taxel_port, os.O_RDWR | os.O_NOCTTY)  # the DTR reset: optiboot holds the Uno ~1 s
    try:
        time.sleep(0.05)  # the harness has seen the open and reset the Uno
        rig.play_waveform(new_rows)
        scans, _ = rig._scan()
        assert scans == 0, "the Uno scanned before the waveform was loaded: not the window this test is about"
        assert rig.last_wave_playing
    finally:
        os.close(fd)
    samples = _capture(rig, wait_frames, 50)
    assert np.all(np.isin(samples, new_rows[:, 0])), f"first frame {samples[0].tolist()}"
