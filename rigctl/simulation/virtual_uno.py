"""The simulated taxel streamer (Arduino Uno) on a pty: ready banner, S/P/I commands, frames at the sensor's rate.

Implements ``docs/wire-protocol.md`` section 1 from the board's side, for any sensor: ``VirtualUno(layout=...)``
announces the layout's channel count, rate and bits in its banner and identify reply (``ch=``, ``rate_hz=``,
``bits=``, ``layout=RxCxL``) and sends frames of ``7 + 2 * ch`` bytes; the default is the Uno firmware's 18 channels
at 1 kHz, 10 bits, with the firmware's exact banner. The board is passive: whoever owns the simulation clock
(:class:`rigctl.simulation.rig.SimulatedRig`'s physics thread, or :meth:`VirtualUno.run_paced` /
:meth:`VirtualUno.run_on_clock` for a standalone board) calls :meth:`VirtualUno.tick` with the samples of every
elapsed sample period, so frame k of a stream goes out no earlier than ``t0 + k / rate`` (of the clock's time) and the
long-run rate is exactly the layout's rate. Framing reuses :func:`rigctl.devices.frames.encode_frames`.
"""

from __future__ import annotations

import logging
import os
import select
import threading
import time
from collections.abc import Callable

import numpy as np

from rigctl.core.sensor import PAPER_SENSOR, SensorLayout
from rigctl.core.shared_clock import SharedClock, host_stamp, on_a_kernel_hop, port_keys
from rigctl.devices import wire
from rigctl.devices.frames import encode_frames, encode_stream_frames
from rigctl.simulation.priority import board_thread
from rigctl.simulation.pty import PtyEndpoint
from rigctl.simulation.world_loop import WorldLoop

log = logging.getLogger(__name__)

#: how far an unpaced world may run ahead of its host's taxel reader, s of frames written and not read: a wire at
#: 1 kHz holds about this much in its USB-serial chip and the host's tty buffer (an FTDI bridge's 16 ms latency
#: timer); further, the world waits for the reader, a part of the host (unpaced, an `acquire --replay` whose reader
#: fell 3.3 s behind started a trial 3,336 samples late, and a trial's frames came in seconds after the drum angle
#: predicted their index). Paced, the world keeps to the wall clock up to :data:`READER_LEAD_PACED_S`
READER_LEAD_S = 0.05
#: how far a paced world may run ahead of its host's taxel reader, s of frames written and not read: a reader that
#: gets no CPU while its process's heartbeat still grants the world the wall's time (one thread of a host starved,
#: another not) would otherwise see the board's output queue run over and lose bytes in the middle of a frame (beside
#: two CPU hogs the README's quick check recorded a CRC error); a reader never falls this far behind on a machine that
#: lets it run, and a world held so catches up a live source once it reads again (WorldLoop's ``keep_wall``). At most
#: the world loop's BUSY_MAX_S of wall time: a reader gone for good (a face killed) lets the world run on
READER_LEAD_PACED_S = 1.0


def board_info(layout: SensorLayout = PAPER_SENSOR) -> str:
    """The fields of the banner / identify reply for a board streaming ``layout``:
    ``fw=1.0 ch=18 rate_hz=1000 bits=10 baud=1000000`` for the paper's sensor (the firmware's text, spec section
    1.3), with ``layout=RxCxL`` appended for any other sensor whose layers share one grid."""
    text = "fw={}.{} ch={} rate_hz={:g} bits={} baud={}".format(
        *wire.UNO_FIRMWARE_VERSION, layout.n_channels, layout.sample_rate_hz, layout.adc_bits, wire.TAXEL_BAUD)
    if layout.layers != PAPER_SENSOR.layers and "+" not in layout.shape_text:
        text += f" layout={layout.shape_text}"
    return text


class VirtualUno:
    """Virtual Uno on a :class:`PtyEndpoint`.

    Parameters
    ----------
    link : path or None
        Stable path the client opens (a symlink to the pty slave).
    reset_delay_s : float
        Boot time after a client opens the port (the DTR reset of a real Uno) before the ready banner is sent.
    seed : int
        Seed of the fault-injection random generator.
    layout : SensorLayout or None
        The sensor streamed (channel count, rate, bits), announced in the banner; default the paper's 3x3x2 at
        1 kHz, 10 bits (the Uno firmware).

    Notes
    -----
    Fault injection (for tests): :meth:`inject_garbage`, :meth:`corrupt_frames`, :meth:`drop_frames`,
    :meth:`drop_sync_frames`, :meth:`stall`.
    """

    #: the board's clock for its boot wait and stalls, s: the wall clock, or the simulated rig's shared clock
    #: (:meth:`use_clock`)
    _now: Callable[[], float] = staticmethod(time.monotonic)

    def __init__(self, link=None, *, reset_delay_s: float = 0.25, seed: int = 0, layout: SensorLayout | None = None):
        self.layout = layout or PAPER_SENSOR
        info = board_info(self.layout)
        self.banner = f"{wire.UNO_BANNER_PREFIX} {info}\n".encode()
        self.identity = f"{wire.UNO_IDENTITY_PREFIX} {info}\n".encode()
        self.frame_size = wire.frame_size(self.layout.n_channels)
        # compile/load the numba CRC kernel of the framing now, not in the first tick of a stream: that first call
        # takes 1-4 s, during which the board's clock thread (the simulated rig's physics) would stand still
        encode_frames(np.zeros(1), 0, np.zeros((1, self.layout.n_channels)))
        encode_stream_frames(0, np.zeros(1, bool), True, np.zeros((1, self.layout.n_channels), np.uint16), 1)
        self.port = PtyEndpoint(link)
        self.reset_delay_s = reset_delay_s
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()
        self.streaming = False
        self.seq = 0
        self._first = False
        self._booting_until: float | None = self._now()  # power-up: banner right away
        self._garbage = bytearray()
        self._corrupt_left = 0
        self._corrupt_bits = 1
        self._drop_left = 0
        self._drop_sync_left = 0
        self._stalled_until: float | None = None
        self.frames_sent = 0
        self.frames_dropped = 0
        #: samples handed to :meth:`tick` so far, and their count when the last START took effect: the frame with
        #: sequence number k of that stream carries sample ``stream_start_sample + k`` of the source
        self.samples_ticked = 0
        self.stream_start_sample: int | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        #: the board's own shared clock when it runs on one (:meth:`run_on_clock`), else None
        self.clock: SharedClock | None = None
        #: when a tick last began the read that took the host's bytes from the port (time.monotonic)
        self._taken_at = 0.0
        #: when the board last wrote to its port (time.monotonic): :meth:`output_on_its_way`
        self._wrote_at = 0.0
        #: the clock a host of this process stamps its finds on (SharedClock.note_read: the rig's, or
        #: :meth:`run_on_clock`'s own), and when a host of another process last found bytes here (the rig's clock file)
        self.host_clock: SharedClock | None = None
        self.remote_stamp: Callable[[bool], float] | None = None

    def use_clock(self, now: Callable[[], float]) -> None:
        """Time the boot wait and stalls on ``now()`` (s; the simulated rig's shared clock), from now on."""
        with self._lock:
            self._now = now
            if self._booting_until is not None:
                self._booting_until = now()
            self._stalled_until = None

    @property
    def path(self) -> str:
        """The path a client opens with pyserial."""
        return self.port.path

    def frames_unread(self) -> float:
        """How many frames' worth of bytes the board has written that its host has not read yet (queued by the board
        or in the pty). Lock-free."""
        return self.port.unread_by_board() / self.frame_size

    # ------------------------------------------------------------------ fault injection
    def inject_garbage(self, data: bytes) -> None:
        """Send ``data`` between the next two frames (while streaming)."""
        with self._lock:
            self._garbage += data

    def corrupt_frames(self, n: int, bits: int = 1) -> None:
        """Flip ``bits`` random bits (outside the sync bytes) in each of the next ``n`` frames sent."""
        with self._lock:
            self._corrupt_left += int(n)
            self._corrupt_bits = int(bits)

    def drop_frames(self, n: int) -> None:
        """Do not send the next ``n`` frames (their sequence numbers are used up: the host sees a gap)."""
        with self._lock:
            self._drop_left += int(n)

    def drop_sync_frames(self, n: int = 1) -> None:
        """Do not send the next ``n`` frames flagged SYNC_IN (the drum's index pulse); a gap where each was."""
        with self._lock:
            self._drop_sync_left += int(n)

    def stall(self, seconds: float) -> None:
        """The board hangs for ``seconds`` (a firmware lock-up, a USB hub that stops forwarding): nothing is sampled
        or sent and nothing is read, while the port stays open; then it carries on streaming where it was (its
        sequence numbers continue: the host sees silence, not a sequence gap)."""
        with self._lock:
            self._stalled_until = self._now() + float(seconds)

    # ------------------------------------------------------------------ unplug / replug
    def unplug(self) -> None:
        """The USB cable is pulled: the port vanishes, the board stops streaming."""
        with self._lock:
            self.port.unplug()
            self.streaming = False

    def replug(self) -> None:
        """The cable is plugged back: the port reappears and the board boots (banner after ``reset_delay_s``)."""
        with self._lock:
            self.port.replug()
            self.streaming = False
            self._booting_until = self._now() + self.reset_delay_s

    # ------------------------------------------------------------------ the board's loop
    def tick(self, samples: np.ndarray | int, sync_in: np.ndarray | None = None, unsent: int = 0) -> None:
        """Advance the board by ``len(samples)`` sample periods (ms at 1 kHz).

        Parameters
        ----------
        samples : (n, layout.n_channels) uint16 ADC counts 0..layout.adc_max, one row per elapsed sample period; or
            the number n of periods elapsed without samples, when the board did not stream as the tick began
            (:attr:`streaming` False: the caller rendered none): a START read in this tick then takes effect with the
            next tick's first period (as if its byte had come just after this tick's read).
        sync_in : (n,) bool, the drum index pulse seen in each period (sets the SYNC_IN flag), or None.
        unsent : the last ``unsent`` periods had no sample (a live source behind the board's clock): no frame is
            sent for them, the sequence counter still steps over them (the host counts them as lost; counted in
            :attr:`frames_dropped`).
        """
        if isinstance(samples, (int, np.integer)):
            rendered, n = False, int(samples)
        else:
            rendered, n = True, len(samples)
        with self._lock:
            base = self.samples_ticked
            self.samples_ticked += n
            port = self.port
            if not port.plugged:
                return
            now = self._now()
            if self._stalled_until is not None:
                if now < self._stalled_until:
                    return
                self._stalled_until = None
            if port.client_opened():  # DTR reset on open
                self.streaming = False
                port.discard_output()
                self._booting_until = now + self.reset_delay_s
            taken_at = time.monotonic()
            if self._booting_until is not None:
                if port.read(4096):  # the bootloader ignores what the host sends
                    self._taken_at = taken_at
                if now >= self._booting_until:
                    self._booting_until = None
                    self._write(self.banner)
                port.flush()
                return
            commands = port.read(4096)
            if commands:
                self._taken_at = taken_at
            # commands are applied at the start of this tick (the Uno checks its UART between ticks)
            for byte in commands:
                c = bytes([byte])
                if c == wire.UnoCommand.START.value:
                    self.stream_start_sample = base if rendered else base + n
                    self.streaming = True
                    self.seq = 0
                    self._first = True
                elif c == wire.UnoCommand.STOP.value:
                    self.streaming = False
                elif c == wire.UnoCommand.IDENTIFY.value:
                    self.streaming = False
                    self._write(self.identity)
            if self.streaming and n and rendered:
                self._send_frames(samples, sync_in, unsent)
            port.flush()

    def _write(self, data: bytes) -> None:
        self._wrote_at = time.monotonic()
        self.port.write(data)

    def output_on_its_way(self) -> bool:
        """Bytes the board wrote after the host last found bytes on the port (or opened it: ``note_read`` on
        :attr:`host_clock`, or :attr:`remote_stamp`), none waiting on the host's side now: in the kernel's hands
        (a pty hands them to the reader through a kernel worker, which a loaded machine holds for seconds; a banner
        held so failed a 3 s banner wait beside two CPU hogs), for at most ``KERNEL_HOP_MAX_S``. False while no host
        stamps its finds. Lock-free."""
        read_at = host_stamp(self.host_clock, self.path, self.remote_stamp, False)
        if read_at <= 0.0 or not on_a_kernel_hop(self._wrote_at, read_at):
            return False
        return not self.port.unread_by_board()

    def answer_in_flight(self, path: str) -> bool:
        """Whether ``path`` is this board's port and its output is on its way to the host
        (:meth:`output_on_its_way`): a host clock's ``in_flight`` (the banner and identify waits,
        :func:`rigctl.core.shared_clock.on_its_way_until`). Lock-free."""
        return bool(port_keys(path) & port_keys(self.path)) and self.output_on_its_way()

    def _send_frames(self, samples, sync_in, unsent: int = 0) -> None:
        n = len(samples)
        if not (unsent > 0 or self._drop_left or self._drop_sync_left or self._corrupt_left or self._garbage) and \
                getattr(samples, "dtype", None) == np.uint16:  # the common tick: every period's frame, as it is
            first, seq0 = self._first, self.seq
            self._first = False
            self.seq = (seq0 + n) & 0xFFFF
            sync = np.zeros(n, bool) if sync_in is None else np.ascontiguousarray(sync_in, dtype=bool)
            self._write(encode_stream_frames(seq0, sync, first, np.ascontiguousarray(samples), self.layout.adc_max))
            self.frames_sent += n
            return
        seq = (self.seq + np.arange(n)) & 0xFFFF
        flags = np.zeros(n, np.uint8)
        if sync_in is not None:
            flags |= np.asarray(sync_in, bool).astype(np.uint8) * np.uint8(wire.FrameFlag.SYNC_IN)
        if self._first:
            flags[0] |= wire.FrameFlag.STREAMING_START
            self._first = False
        self.seq = (self.seq + n) & 0xFFFF
        samples = np.asarray(samples)
        if unsent > 0:  # periods without a sample: numbered, never sent
            k = min(int(unsent), n)
            self.frames_dropped += k
            seq, flags, samples = seq[:n - k], flags[:n - k], samples[:n - k]
            n -= k
        if self._drop_left or self._drop_sync_left:  # fault injection: frames the link loses
            keep = np.ones(n, bool)
            if self._drop_left:
                k = min(self._drop_left, n)
                keep[:k] = False
                self._drop_left -= k
                self.frames_dropped += k
            if self._drop_sync_left:
                idx = np.flatnonzero(keep & ((flags & wire.FrameFlag.SYNC_IN) != 0))[:self._drop_sync_left]
                keep[idx] = False
                self._drop_sync_left -= len(idx)
                self.frames_dropped += len(idx)
            seq, flags, samples = seq[keep], flags[keep], samples[keep]
        if not len(samples):
            return
        data = encode_frames(seq, flags, samples, adc_max=self.layout.adc_max)
        if self._corrupt_left:
            flipped = bytearray(data)
            k = min(self._corrupt_left, len(samples))
            self._corrupt_left -= k
            for i in range(k):
                for _ in range(self._corrupt_bits):
                    pos = i * self.frame_size + int(self._rng.integers(2, self.frame_size))
                    flipped[pos] ^= 1 << int(self._rng.integers(0, 8))
            data = bytes(flipped)
        if self._garbage:
            data = bytes(self._garbage) + data
            self._garbage.clear()
        self._write(data)
        self.frames_sent += len(samples)

    # ------------------------------------------------------------------ standalone pacing
    def run_paced(self, source, *, tick_s: float = 0.003) -> None:
        """Run the board on its own real-time clock in a thread at ``layout.sample_rate_hz``:
        ``source(n) -> (samples (n, ch), sync_in (n,) or None)`` with n the sample periods elapsed.

        For a board without the rig's physics thread (e.g. tests, replay). Stop with :meth:`close`.
        """
        if self._thread is not None:
            raise RuntimeError("already running")
        self._stop.clear()
        self._thread = threading.Thread(target=board_thread(paced_loop), args=(self._stop, tick_s, lambda n: self.tick(*source(n))),
                                        kwargs={"rate_hz": self.layout.sample_rate_hz}, name="virtual-uno",
                                        daemon=True)
        self._thread.start()

    def run_on_clock(self, source, *, paced: bool = False, tick_s: float = 0.003) -> SharedClock:
        """Run the board in a thread on a clock of its own shared with the host of this process, as a simulated
        rig's physics thread runs it (docs/architecture.md "Time on a simulated rig"): a :class:`TaxelStream` of
        this process that opens :attr:`path` finds the clock by the port and times its banner wait, receive stamps
        and waits on it; the board's boot wait and stalls judge it too; a starved host pauses the board. Unpaced
        (the default), the board runs as fast as the host's grants allow, no further than
        :data:`READER_LEAD_S` of frames ahead of the host's reader, and not while a command of the host is on its way
        (:meth:`command_on_its_way`); paced, no faster than the wall clock either.
        ``source(n) -> (samples (n, ch), sync_in (n,) or None)`` as for :meth:`run_paced`; ``tick_s``: the
        steps, s (of simulated time unpaced). For a board at 1 kHz (the clock counts the board's milliseconds).
        Returns the clock (:attr:`clock`); stop with :meth:`close`.

        Raises ValueError for a layout not at 1 kHz, RuntimeError if the board already runs."""
        if self.layout.sample_rate_hz != 1000.0:
            raise ValueError(f"run_on_clock steps a 1 kHz board, not {self.layout.sample_rate_hz:g} Hz")
        if self._thread is not None:
            raise RuntimeError("already running")
        ticks = [0]  # the board's milliseconds

        def step(n: int) -> None:
            self.tick(*source(n))
            ticks[0] += n

        self.clock = self.host_clock = SharedClock(lambda: ticks[0] / 1000.0, world_notifies=True).start()
        self.clock.in_flight = self.answer_in_flight  # a banner or reply the kernel holds is waited for
        self.clock.own_port(self.path)
        self.use_clock(self.clock.now)
        lead = READER_LEAD_S * self.layout.sample_rate_hz

        def busy() -> bool:  # unpaced: the host's reader behind, or a write of the host on its way
            return (self.streaming and self.frames_unread() > lead) or self.command_on_its_way()

        loop = WorldLoop(self.clock, lambda: ticks[0], step, paced=paced, tick_s=tick_s,
                         board_busy=None if paced else busy)
        self._stop.clear()
        self._thread = threading.Thread(target=board_thread(loop.run), args=(self._stop,), name="virtual-uno",
                                        daemon=True)
        self._thread.start()
        return self.clock

    def command_on_its_way(self) -> bool:
        """A write of the host to the port (a START, STOP or IDENTIFY: stamped on :attr:`clock`,
        :meth:`~rigctl.core.shared_clock.SharedClock.note_write`) that no tick has taken from the port yet: in the
        kernel's hands, which a loaded machine holds for hundreds of ms (no longer than ``KERNEL_HOP_MAX_S``), where a
        wire carries a byte in about a millisecond: a world on the shared clock waits for it. Lock-free."""
        clock = self.clock
        if clock is None or not self.port.plugged:
            return False
        return on_a_kernel_hop(clock.written_at(self.path), self._taken_at)

    def close(self) -> None:
        """Stop the board's thread (if any), its clock (:meth:`run_on_clock`) and close the pty."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2)
            self._thread = None
        if self.clock is not None:
            self.clock.close()
            self.clock.release_ports()
        with self._lock:
            self.port.close()


def paced_loop(stop: threading.Event, tick_s: float, step, *, rate_hz: float = 1000.0,
               idle: Callable[[], bool] | None = None, idle_tick_s: float | None = None,
               wake_fd: int | None = None) -> None:
    """Call ``step(n)`` about every ``tick_s`` with the periods of ``rate_hz`` elapsed since the last call (the
    milliseconds at the default 1 kHz). Exact long-run rate: period k is handed out no earlier than
    ``t0 + k / rate_hz``. With ``idle`` and ``idle_tick_s``: after a call for which ``idle()`` is True the next comes
    about ``idle_tick_s`` later instead (a clock with nothing to send wakes less often; the same periods are handed out,
    in longer steps). ``wake_fd``: the read end of a pipe; a byte written to it ends the wait, and the next call comes
    at the next period (a command the step must act on now). Ends within one such wait of ``stop`` being set (a plain
    sleep or select: an ``Event.wait`` with a timeout costs several times its CPU, hundreds of times a second)."""
    rate = float(rate_hz)
    monotonic, sleep, stopped = time.monotonic, time.sleep, stop.is_set
    t0 = monotonic()
    done = 0
    busy_ahead = ahead = max(1, int(tick_s * rate))
    idle_ahead = busy_ahead if idle is None or idle_tick_s is None else max(busy_ahead, int(idle_tick_s * rate))
    woken = False
    while not stopped():
        due = int((monotonic() - t0) * rate)
        n = due - done
        if n > 0:
            try:
                step(n)
            except Exception:  # keep the clock alive; the error is logged
                log.exception("simulation step failed")
            done = due
            woken = False
            if idle is not None:
                ahead = idle_ahead if idle() else busy_ahead
        wait = t0 + (done + (1 if woken else ahead)) / rate - monotonic()
        if wait > 0.0:
            if wake_fd is None:
                sleep(wait)
            elif select.select([wake_fd], [], [], wait)[0]:
                os.read(wake_fd, 4096)
                woken = True
