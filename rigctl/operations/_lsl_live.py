"""The live part of a run published on LSL: :class:`LiveLslFeed`, a worker thread that pushes the taxel stream and
its SA/RA spikes to :class:`rigctl.acquisition.lsl.LslOutlets` as the reader receives them, for as long as the rig is
open (between trials too: the sensor streams), and the drum state at every status poll.

Every ``poll_s`` (25 ms) it reads the taxel source's live ring (:class:`rigctl.devices.ring.RingBuffer`, its own
cursor: nothing the run stores changes), feeds the frames to its own online clock fit
(:class:`rigctl.core.clocksync.DeviceClockFit`: the board's sequence numbers against the host receive times) and
pushes them in one chunk with their fitted times on the LSL clock; the same chunk goes through the streaming
Izhikevich encoder (:class:`rigctl.encoding.izhikevich.StreamingEncoder`, paper eqs. 3-5, the live encoder's kernel:
the spikes of the whole stream equal :func:`~rigctl.encoding.izhikevich.encode_sa` / ``encode_ra`` on it), each
spike timestamped at its sample. The drum state comes from the drum client's status polls
(``DrumClient.status_listeners``: whoever polls, the run at ~50 Hz during a trial, its waits between trials).
"""

from __future__ import annotations

import math
import threading
from typing import Any

import numpy as np

from rigctl.acquisition.lsl import LslOutlets
from rigctl.core.clocksync import DeviceClockFit
from rigctl.core.errors import describe_error
from rigctl.core.normalisation import TaxelRange
from rigctl.operations._live import live_ring

__all__ = ["LiveLslFeed", "LIVE_PUSH_S"]

#: how often the feed pushes what the reader received, s (a chunk of ~25 frames at 1 kHz)
LIVE_PUSH_S = 0.025


class LiveLslFeed(threading.Thread):
    """Pushes ``stream``'s frames (its ``ring``) and spikes to ``outlets`` every ``poll_s`` (module docstring).

    ``stream`` : the rig's taxel source with a live ``ring`` (an in-process source is asked for one:
    ``enable_ring``); ``drum`` : the drum client (its ``status_listeners`` get :meth:`on_status`);
    ``normaliser`` : the encoder's per-taxel range. :meth:`stop` pushes what is left and ends the thread.

    Attributes: ``frames`` / ``spikes`` / ``drum_samples`` pushed so far; ``error`` the last failure in words (the
    feed goes on: a live view never stops a run).
    """

    def __init__(self, outlets: LslOutlets, stream: Any, drum: Any, normaliser: TaxelRange, *,
                 poll_s: float = LIVE_PUSH_S) -> None:
        super().__init__(name="lsl-live", daemon=True)
        self.outlets, self.stream, self.drum = outlets, stream, drum
        self.layout = outlets.layout
        self.normaliser = normaliser
        self.poll_s = float(poll_s)
        self.frames = self.spikes = self.drum_samples = 0
        self.error: str | None = None
        self._halt = threading.Event()
        self._push_lock = threading.Lock()
        self._fit = DeviceClockFit(self.layout.sample_rate_hz)
        self._segment_origin: tuple[int, float] | None = None  # (count, host time) of a segment's first frame
        self._last_time = -math.inf
        self._ring = live_ring(stream)
        self._cursor = self._ring.total if self._ring is not None else 0
        # the encoder is made (its kernels compiled: ~1 s the first time) in a thread of its own, so that the taxels
        # go out live meanwhile; their spikes follow once it is ready (the chunks wait in the backlog)
        self._encoder: Any = None
        self._encoder_ready = threading.Event()
        self._compiler = threading.Thread(target=self._make_encoder, name="lsl-live-encoder", daemon=True)
        self._backlog: list[tuple[np.ndarray, np.ndarray]] = []
        self._encoded = 0  # samples encoded (the encoder's time 0 = the first frame pushed)
        self._times = np.zeros(0)  # fitted host times of the samples encoded, kept for spikes the encoder
        self._times_from = 0  # gives later than their sample (a resampled stream); index of _times[0]
        listeners = getattr(drum, "status_listeners", None)
        if listeners is not None:
            listeners.append(self.on_status)

    # ----------------------------------------------------------------------------------------------- the drum
    def on_status(self, host_time_s: float, status: Any) -> None:
        """One status poll (``DrumClient.status_listeners``): speed, force, actuator position on the drum stream.
        Never raises: it runs inside the poller's ``read_status`` (the run's, the GUI's)."""
        try:
            self.outlets.push_drum(np.array([host_time_s]), np.array([status.speed_mm_s]),
                                   np.array([status.force_g]), np.array([status.actuator_mm]))
        except Exception as exc:  # noqa: BLE001 - e.g. the outlets closed under a poll in another thread
            self.error = f"drum stream: {describe_error(exc)}"
            return
        self.drum_samples += 1

    # ----------------------------------------------------------------------------------------------- the taxels
    def fitted_times(self, seq: np.ndarray, host_time_s: np.ndarray) -> np.ndarray:
        """The fitted host times (s) of frames just received (fed to the online fit); before the fit has two
        blocks (~2 s), the nominal rate from the segment's first frame's receive time."""
        segment = self._fit.segment
        counts = self._fit.add(seq, host_time_s)
        if self._segment_origin is None or self._fit.segment != segment:
            self._segment_origin = (int(counts[0]), float(host_time_s[0]))
        m = self._fit.mapping()
        if m is not None:
            times = m.host_time(counts)
        else:
            c0, t0 = self._segment_origin
            times = t0 + (counts - c0) / self._fit.nominal_rate_hz
        # a refit never sends a stream back in time (LSL inlets expect increasing stamps)
        return np.maximum(times, self._last_time + 1e-9)

    def push_pending(self) -> int:
        """Push the frames received since the last push (and their spikes); returns how many frames."""
        with self._push_lock:
            ring = getattr(self.stream, "ring", None)
            if ring is None:
                return 0
            if ring is not self._ring:  # the stream was reopened: a new ring
                self._ring, self._cursor = ring, 0
            self._cursor, samples, seq, host_t = ring.read_since(self._cursor)
            if not len(seq):
                return 0
            times = self.fitted_times(seq, host_t)
            self._last_time = float(times[-1])
            self.outlets.push_taxels(samples, seq, times)
            self.frames += len(seq)
            self._backlog.append((samples, times))
            if self._encoder_ready.is_set():
                for chunk in self._backlog:
                    self._push_spikes(*chunk)
                self._backlog.clear()
            return len(seq)

    def _make_encoder(self) -> None:
        try:
            from rigctl.encoding.izhikevich import StreamingEncoder

            enc = StreamingEncoder(self.layout.n_channels, normalise=self.normaliser, fs=self.layout.sample_rate_hz)
            enc.process(np.zeros((1, self.layout.n_channels), np.uint16))  # compile
            enc.reset()
            self._encoder = enc
        except Exception as exc:  # noqa: BLE001 - the taxels go on; said in error
            self.error = f"spike encoder: {describe_error(exc)}"
        finally:
            self._encoder_ready.set()

    def _push_spikes(self, samples: np.ndarray, times: np.ndarray) -> None:
        if self._encoder is None:  # it failed to build: said in error
            return
        self._encoded += len(samples)
        self._times = np.concatenate([self._times, times])
        try:
            chunk = self._encoder.process(samples)
        except Exception as exc:  # noqa: BLE001 - the taxels go on; said in error
            self.error = f"spike encoder: {describe_error(exc)}"
            return
        rate = self.layout.sample_rate_hz
        trains, at = [], []
        for kind, which in enumerate(("sa", "ra")):
            t, ch = chunk.events(which)
            idx = np.clip(np.round(np.asarray(t) * rate).astype(np.int64) - self._times_from, 0,
                          len(self._times) - 1)
            trains.append(kind * self.layout.n_channels + np.asarray(ch, dtype=np.int64))
            at.append(self._times[idx])
        train = np.concatenate(trains)
        self.outlets.push_spikes(train, np.concatenate(at))
        self.spikes += len(train)
        drop = len(self._times) - int(rate)  # a second of history for spikes found late (a resampled stream)
        if drop > 0:
            self._times = self._times[drop:]
            self._times_from += drop

    # ----------------------------------------------------------------------------------------------- the thread
    def run(self) -> None:
        self._compiler.start()
        while not self._halt.wait(self.poll_s):
            try:
                self.push_pending()
            except Exception as exc:  # noqa: BLE001 - a live stream never stops the run; said in error
                self.error = describe_error(exc)

    def stop(self, timeout_s: float = 5.0) -> None:
        """Push what is left, end the thread, stop listening to the drum's polls."""
        self._halt.set()
        if self.is_alive():
            self.join(timeout_s)
        if self._compiler.is_alive():
            self._compiler.join(max(timeout_s, 60.0))
        elif not self._encoder_ready.is_set():  # never started
            self._make_encoder()
        listeners = getattr(self.drum, "status_listeners", None)
        if listeners is not None and self.on_status in listeners:
            listeners.remove(self.on_status)
        self.push_pending()
