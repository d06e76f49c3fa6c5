"""The Uno encoder image (uno_encoder: the taxel streamer with the integer SA encoder) under simavr, against the host's
integer kernel on the samples the board's ADC converted (docs/firmware.md "The encoder in the Uno image",
docs/wire-protocol.md 1.5).

The harness plays simulated handheld scans to the ADC in a loop and reports the row of each encoded scan's first sample
(the image's marker pin); the host runs each scan through its client (:class:`rigctl.devices.encoder_stream
.OnboardEncoder`: calibrate, encode, one speed per 100 ms window as the board's samples arrive, stop, finish) and
encodes the same rows with :class:`rigctl.encoding.fixed_sa.FixedSAEncoder`, scaled with the speeds the board applied:
every spike on the same sample, every window count and the 180 features equal (those of the live
``ScanEncoder(kernel="fixed")`` too), no sample dropped, the CPU's load per 1 ms tick (the harness's ``LOAD`` lines)
under the tick and the stack clear of the static RAM. A window the board held (scaled with the last speed) is judged
on the board's clock and the host's own: its SPEED reached the board only after the board needed it (the harness's
``RX`` times), and the host sent it measurably late; a speed that arrived in time is never held. Then START on the
same image: its taxel frames exact.
"""

from __future__ import annotations

import re
import subprocess
import time

import numpy as np
import pytest
import serial

from rigctl.core.normalisation import TaxelRange
from rigctl.devices import wire
from rigctl.devices.encoder_stream import STOP_BURST, OnboardEncoder, held_windows, speed_command, spike_raster
from rigctl.devices.taxel_stream import TaxelStream
from rigctl.encoding.features import counted_realtime_features
from rigctl.encoding.fixed_sa import FixedSAEncoder
from rigctl.encoding.params import EncodeParams
from rigctl.encoding.realtime import ScanEncoder
from rigctl.encoding.speed import incremental_scale
from rigctl.simulation import hil
from rigctl.simulation.hil_finger import NotingPort

pytestmark = pytest.mark.hil

N_TAXELS = wire.ENC_N_TAXELS
TICK_CYCLES = 16_000
#: samples per real-time window; the host sends a window's SPEED once it has this many of the next window's samples
WINDOW = 100
SEND_AFTER = 50
#: the board holds window w when it starts window w + HOLD_AFTER without w's speed (sa_step: 2 windows may wait)
HOLD_AFTER = 2
#: a host's send is measurably late: it had already received this many samples past the one that triggered it (a
#: window: twice its 50 ms read timeout), or it wrote the SPEED this long (s) after the read that triggered it returned
LATE_SAMPLES = WINDOW
LATE_WRITE_S = 0.05
#: the two harnesses' clock lock: one runs at most this far ahead of the other (rigctl_simavr.c LOCK_LEAD_S), ms
LOCK_LEAD_MS = 2.0


@pytest.fixture(scope="module")
def scans(handheld_scans):
    return handheld_scans


@pytest.fixture(scope="module")
def enc_rig(fw_build, scans):
    """Both boards under simavr, the Uno running the encoder image and playing the scans in a loop (top layer and,
    for the bottom layer, the same counts)."""
    x = np.concatenate([s[0] for s in scans])
    with hil.HilRig(uno_image="uno_encoder", live=False) as rig:
        rig.play_waveform(np.concatenate([x, x], axis=1))
        rig.log_uno_requests()  # when each host command reaches the board (its clock)
        yield rig




def _encode_scan(rig: hil.HilRig, port: NotingPort, n_samples: int, lo: np.ndarray, hi: np.ndarray,
                 speeds_mm_s: np.ndarray):
    """One scan on the board through the host's client (:class:`OnboardEncoder`): a SPEED per window once half of
    the next window's samples are encoded (window w's speed is ``speeds_mm_s[w % len]``), stop after
    ``n_samples``. Returns (the scan, the spike frames, the harness's LOAD reports of the seconds while the board
    encoded, after the first 2 s, the SPEEDs written: (window, :meth:`NotingPort.sent` of its write), the windows
    given a speed, the board's time as the host began each SPEED write)."""
    enc = OnboardEncoder(port)
    port.samples = lambda: enc.samples
    speeds0 = len(port.sent(wire.EncoderCommand.SPEED.value))
    enc.start(lo, hi, 100)
    loads0 = len(rig.loads)
    last = time.monotonic()
    while enc.samples < n_samples:
        n = enc.poll()
        if n:
            last = time.monotonic()
        assert time.monotonic() - last < 10.0, "the board stopped sending"
        while len(enc.speeds_sent) * WINDOW + SEND_AFTER <= n:
            enc.send_speed(float(speeds_mm_s[len(enc.speeds_sent) % len(speeds_mm_s)]))
    rest = [float(speeds_mm_s[(len(enc.speeds_sent) + i) % len(speeds_mm_s)]) for i in range(5)]
    stops0 = len(port.sent(wire.UnoCommand.STOP.value))
    scan = enc.finish(rest, quiet_s=0.5)
    stops = len(port.sent(wire.UnoCommand.STOP.value)) - stops0
    print(f"scan of {n_samples} samples: STOP sent {stops} time(s)")  # more than once: the board went on streaming
    speeds = list(zip(enc.speed_windows, port.sent(wire.EncoderCommand.SPEED.value)[speeds0:], strict=True))
    written_s = port.sent_board_s(wire.EncoderCommand.SPEED.value)[speeds0:]
    # the reports of the seconds while it encoded, after its first 2 s (every one: a loop starved beside CPU hogs that
    # looked at the latest only saw fewer than ten of a 14 s scan's); the first may cover the second before ENCODE
    loads = rig.loads[loads0:]
    t_first = loads[0]["t"] if loads else 0.0
    loads = [r for r in loads if r["t"] >= t_first + 2.0]
    return scan, enc.parser, loads[1:], speeds, len(enc.speeds_sent), written_s


def _arrivals(rig: hil.HilRig, port: NotingPort, offsets: list[int]) -> np.ndarray:
    """The board's simulated time (s) at which the byte at each offset of the host's writes reached it (the harness's
    ``RX`` chunks, in order); waits for the harness's reports of every byte written."""
    deadline = time.monotonic() + 30.0
    while sum(n for _, n in tuple(rig.uno_requests)) < port.written:
        assert time.monotonic() < deadline, "the harness did not report every host byte's arrival"
        time.sleep(0.05)
    chunks = list(rig.uno_requests)
    ends = np.cumsum([n for _, n in chunks])
    return np.array([chunks[i][0] for i in np.searchsorted(ends, offsets)])


def _judge_held(held: list[int], speeds: list[tuple[int, tuple[int, int, float]]], n_given: int,
                arrived_s: np.ndarray, start_s: float, samples: int, queue_max: int, written_s: list[float]) -> None:
    """The board held exactly the windows whose SPEED reached it after it needed it (it starts window w + 2: sample
    WINDOW * (w + 2); its main loop encodes a sample and reads a command up to ``queue_max`` ticks after they come,
    so a speed within that many ms of the sample's tick may go either way), and each was the host's lateness: sent
    measurably late by the host's own count (:data:`LATE_SAMPLES`, :data:`LATE_WRITE_S`), or on the board's clock
    (``written_s``: the rig's time as the host began the write, already past the need: the host had the board's
    samples late, its own threads or the kernel holding them on the way), or not sent at all (of the ``n_given``
    windows given a speed): the host had the board's sample WINDOW * (w + 2) already, 150 samples past its trigger,
    and knew the board had held it. A speed written in time that reached the board late was held on its way: the
    clock lock's failure (test_fw_clock_lock)."""
    written = [w for w, _ in speeds]
    assert set(range(n_given)) - set(written) <= set(held), "a window's SPEED was not sent, though not held"
    for (w, (_, seen, write_s)), t, t_write in zip(speeds, arrived_s, written_s, strict=True):
        need = WINDOW * (w + HOLD_AFTER)  # the sample at which the board needs window w's speed
        if need >= samples:
            continue  # stopped before: the board never needed it
        due_ms = (t - start_s) * 1000.0 - need  # arrival after the tick of that sample, ms of the board's clock
        # the host's write after the need, ms of the board's clock: the rig's clock is the slower board's, at most
        # LOCK_LEAD_MS behind the Uno's
        write_due_ms = (t_write - start_s) * 1000.0 - need + LOCK_LEAD_MS
        late = f"window {w}: speed arrived {due_ms:+.1f} ms after the board needed it, host sent it with {seen} " \
               f"samples received (trigger {WINDOW * w + SEND_AFTER}), {1e3 * write_s:.0f} ms after its read, " \
               f"{write_due_ms:+.1f} ms after the need on the board's clock"
        if w in held:
            assert due_ms > -(queue_max + 1.0), "held, though its speed arrived in time: " + late
            assert (seen - (WINDOW * w + SEND_AFTER) >= LATE_SAMPLES or write_s >= LATE_WRITE_S
                    or write_due_ms > -(queue_max + 1.0)), "held, though the host sent its speed in time: " + late
        else:
            assert due_ms < queue_max + 1.0, "not held, though its speed arrived after it was needed: " + late


def test_the_board_encodes_every_sample_as_the_host_does(enc_rig, scans, fw_build):
    x_all = np.concatenate([s[0] for s in scans])
    lo, hi = x_all.min(axis=0), x_all.max(axis=0)
    speeds = np.concatenate([s[1] for s in scans])
    rng = TaxelRange(lo.astype(np.float64), hi.astype(np.float64))
    results = []
    with serial.Serial(enc_rig.taxel_port, timeout=0.05) as raw:
        port = NotingPort(raw, board_s=enc_rig.clock.now)
        banner = b""
        t0 = time.monotonic()
        while b"\n" not in banner:
            banner += raw.read(256)
            assert time.monotonic() - t0 < 30, "no banner"
        assert wire.UNO_ENCODER_FIELD.encode() in banner
        arrivals = []
        for n in (14_000, 3_000):  # a long scan (14 s: ten LOAD reports while encoding), then a handheld scan's length
            results.append(_encode_scan(enc_rig, port, n, lo, hi, speeds))
            arrivals.append(_arrivals(enc_rig, port, [end for _, (end, _, _) in results[-1][3]]))
    assert len(enc_rig.encoder_start_rows) == 2
    total_spikes = 0
    for (scan, parser, _, sent, n_given, written_s), row0, start_s, arrived_s in zip(
            results, enc_rig.encoder_start_rows, enc_rig.encoder_start_times_s, arrivals):
        assert parser.crc_errors == 0 and not parser.seq  # spike frames instead of taxel frames
        counts, raster, held, applied = scan.counts, scan.raster, scan.held, scan.speeds_mm_s
        n = raster.shape[0]
        # every sample of the scan encoded, none dropped; a window whose speed reached the board too late (a starved
        # host: > 150 ms) is scaled with the last speed, flagged, and the host's reference does the same
        assert n >= 3_000 and counts.samples == n and counts.dropped == 0 and counts.held == len(held)
        _judge_held(held, sent, n_given, arrived_s, start_s, n, counts.queue_max, written_s)
        assert not any(f.flags & ~wire.SpikeFlag.HELD for f in parser.spikes)
        assert row0 >= 0
        x = x_all[(row0 + np.arange(n)) % len(x_all)]  # the harness's rows: what the board's ADC converted
        host = FixedSAEncoder(rng, k_sa=100.0).process(x)
        host_raster = np.zeros_like(raster)
        for i in range(N_TAXELS):
            host_raster[np.rint(host.train(0, i) * 1000.0).astype(np.int64), i] = 1
        total_spikes += int(host_raster.sum())
        assert host_raster.sum() > 1000 * n / 30_000
        same = int((raster & host_raster).sum())
        print(f"scan of {n} samples: {int(host_raster.sum())} host spikes, {int(raster.sum())} board spikes, "
              f"{same} on the same sample; queue depth max {counts.queue_max}, windows held {len(held)}")
        assert np.array_equal(raster, host_raster), "a spike differs from the host's integer kernel"
        scaled, _ = incremental_scale(host, [applied])
        host_counts = scaled.window_counts(0.1, wire.ENC_N_WINDOWS)[0]
        assert host_counts.sum() > 200
        assert np.array_equal(counts.counts, host_counts)
        # the classifier's features: the board's counts as the handheld real-time path's encoder (ScanEncoder, the
        # integer kernel) computes them live from the same samples and a velocity trace of the same window speeds
        live = ScanEncoder(rng, EncodeParams(), taxels=list(range(N_TAXELS)), kernel="fixed")
        live.feed(x)
        edges = np.arange(applied.size) * 0.1
        live.feed_speed(np.stack([edges + 1e-6, edges + 0.1 - 1e-6], axis=1).ravel(), np.repeat(applied, 2))
        assert np.array_equal(counted_realtime_features(counts.counts, applied),
                              live.features()["realtime_speed_scaled"])
    long_loads = results[0][2]
    assert len(long_loads) >= 10, "the harness reported no load while the board encoded"
    busy = np.array([r["busy_cycles_per_tick"] for r in long_loads])
    busy_max = max(r["busy_max_per_tick"] for r in long_loads)
    print(f"Uno encoder image while encoding, CPU cycles per 1 ms tick over {busy.size} s: mean {busy.mean():.0f} "
          f"(seconds {busy.min():.0f}-{busy.max():.0f}), largest tick {busy_max:.0f}")
    assert total_spikes > 0
    # the stack's high-water mark above the static RAM (the ATmega328P's RAM starts at 0x100)
    size = subprocess.run(["avr-size", "-A", str(fw_build / "uno_encoder.elf")], capture_output=True, text=True,
                          check=True).stdout
    sec = {m.group(1): int(m.group(2)) for m in re.finditer(r"^(\.\w+)\s+(\d+)", size, re.M)}
    static_end = 0x100 + sec.get(".data", 0) + sec.get(".bss", 0)
    headroom = int(long_loads[-1]["sp_min"]) - static_end
    print(f"static RAM {static_end - 0x100} B, stack high-water {0x8FF - int(long_loads[-1]['sp_min'])} B, "
          f"{headroom} B never touched")
    assert headroom > 100
    # the tick's interrupts and the encoder leave the CPU idle part of every tick on average (the queue absorbs a
    # tick that scales a window: none dropped above)
    assert 0.3 * TICK_CYCLES < busy.max() < 0.9 * TICK_CYCLES


def test_the_encoder_image_still_streams_exact_taxel_frames(enc_rig, scans, wait_frames):
    """START on the encoder image: the taxel stream of the plain streamer (docs/wire-protocol.md 1.1), every frame in
    order with the harness's values (the waveform above: top layer and its copy)."""
    x_all = np.concatenate([s[0] for s in scans])
    wave = np.concatenate([x_all, x_all], axis=1)
    with TaxelStream(enc_rig.taxel_port, start_timeout_s=10.0) as stream:
        assert stream.banner["firmware"] == wire.UNO_FIRMWARE_VERSION
        stream.start()
        stream.begin_capture()
        assert wait_frames(stream, 3000), f"only {stream.stats.frames} frames"
        cap = stream.end_capture()
        stream.stop()
    assert cap.crc_errors == 0 and cap.dropped == 0
    assert np.all(np.diff(cap.seq.astype(np.int64)) % 65536 == 1)
    assert not np.any(cap.flags & (wire.FrameFlag.ADC_OVERRUN | wire.FrameFlag.TX_OVERRUN))
    # the row of the first frame: the one whose next 200 rows are the next 200 frames (a scan repeats rows where the
    # finger rests)
    n_fit = 200
    fits = [k for k in np.flatnonzero((wave == cap.samples[0]).all(axis=1))
            if np.array_equal(wave[(k + np.arange(n_fit)) % len(wave)], cap.samples[:n_fit])]
    assert fits, "the first frames are no rows of the waveform"
    k0 = int(fits[0])
    np.testing.assert_array_equal(cap.samples, wave[(k0 + np.arange(len(cap.seq))) % len(wave)])


def _burst_while_scaling(raw: serial.Serial, burst_speeds: int) -> tuple[OnboardEncoder, int, bool]:
    """One scan: once the board has completed window 2 (and half of 3), window 2's SPEED, ``burst_speeds`` SPEEDs of
    window 0 and STOP in one write; read until 0.5 s without bytes (5 s at most). Tried again (5 times) while window 2
    came out held: the host stalled there and its SPEED came too late. Returns (the host's client with the spike
    frames, the window, whether the stream stopped)."""
    lo, hi = np.full(N_TAXELS, 300), np.full(N_TAXELS, 900)
    for _ in range(5):  # tries
        enc = OnboardEncoder(raw)
        enc.start(lo, hi, 100)
        deadline = time.monotonic() + 30.0
        while enc.poll() < 340:  # window 2 complete, half of window 3: the board waits for window 2's speed
            assert time.monotonic() < deadline, "the board sent no spike frames"
        w = enc.samples // WINDOW - 1
        raw.write(speed_command(w, 50.0) + speed_command(0, 50.0) * burst_speeds + wire.UnoCommand.STOP.value)
        quiet = sent = time.monotonic()
        while time.monotonic() - quiet < 0.5 and time.monotonic() - sent < 5.0:
            chunk = raw.read(4096)
            if chunk:
                enc.parser.feed(chunk)
                quiet = time.monotonic()
        stopped = time.monotonic() - quiet >= 0.5
        if not stopped:
            raw.write(STOP_BURST)  # leave the board stopped
            break
        if w not in held_windows(enc.parser.spikes):  # else the host stalled here: its SPEED came too late
            break
    return enc, w, stopped


def test_a_burst_of_speeds_longer_than_the_ring_loses_no_byte_while_the_board_scales_a_window(enc_rig):
    """A host that stalled catches up with every window's SPEED at once, then STOP, in one write (a 10 s stall: 100
    SPEEDs, 708 bytes, ~8 ms at the line rate). The first is the speed of the window the board has just completed,
    which it scales (~0.6 ms in loop()) while the rest arrive; the rest are for windows it held long ago (dropped at
    once). The board takes every byte: the one STOP at the end stops the stream (a 64-byte receive ring lost the burst's
    tail and the STOP with it, and the stream never stopped: the CI run that hung in the test above) and the scaled
    window is not held. A burst of 50 (358 bytes, 1.4 times the ring) costs no sample either.

    Not the 100's: loop() keeps pace with bytes at the line rate but encodes no sample while they come, so its sample
    queue (7 deep) grows ~1 sample a ms of burst (700 bytes alone: 6-7), and with the window's scaling in it a loaded
    CI run saw one dropped (flagged DROPPED): docs/wire-protocol.md 1.5, what a host may send (bursts of 255 bytes)."""
    with serial.Serial(enc_rig.taxel_port, timeout=0.05) as raw:
        banner = b""
        t0 = time.monotonic()
        while b"\n" not in banner:  # the board restarts when a host opens its port
            banner += raw.read(256)
            assert time.monotonic() - t0 < 30, "no banner"
        for burst_speeds in (100, 50):
            enc, w, stopped = _burst_while_scaling(raw, burst_speeds)
            assert stopped, f"the board kept streaming 5 s after a {burst_speeds}-SPEED burst and one STOP (bytes lost)"
            assert w not in held_windows(enc.parser.spikes), f"window {w}'s SPEED never reached the board in time (5 " \
                "tries: a starved host), so the burst never came while the board scaled it"
            assert spike_raster(enc.parser.spikes).shape[0] >= 340
    assert not any(f.flags & wire.SpikeFlag.DROPPED for f in enc.parser.spikes), "a sample dropped in a 50-SPEED burst"
