"""The live encoder: the taxel stream encoded into SA and RA spike trains as it arrives, in a worker thread.

:class:`LiveEncoder` reads the taxel source's ring buffer with its own cursor and runs the streaming Izhikevich
encoder (:class:`rigctl.encoding.izhikevich.StreamingEncoder`, paper eqs. 3-5) on it; the spikes go into two
fixed-size :class:`SpikeRing` s that a live view reads at its own pace (the GUI's raster). No Qt: any face (the GUI,
a script, a server) can show them.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np

from rigctl.core.encoding_model import MODEL_RATE_HZ
from rigctl.core.errors import describe_error
from rigctl.core.normalisation import TaxelRange
from rigctl.core.sensor import PAPER_SENSOR, SensorLayout

__all__ = ["LIVE_WINDOW_MAX_S", "LiveEncoder", "SpikeRing", "spike_capacity", "live_ring"]


def live_ring(taxels: Any) -> Any:
    """The live ring buffer (:class:`rigctl.devices.ring.RingBuffer`) of a taxel source, for a live consumer (the
    live encoder, a live view, the LSL feed): a serial stream always keeps one; the in-process rig keeps one only once
    asked (``enable_ring()``: its tests pay nothing for it), which this does. None for a source that has neither."""
    ring = getattr(taxels, "ring", None)
    enable = getattr(taxels, "enable_ring", None)
    return enable() if ring is None and enable is not None else ring


class SpikeRing:
    """The most recent spikes of one population (e.g. the 18 SA trains): fixed-size arrays of time and channel.

    ``capacity`` spikes are kept; older ones are overwritten (the raster only shows the last few seconds).
    """

    def __init__(self, capacity: int = 40_000) -> None:
        self.t = np.zeros(capacity)
        self.ch = np.zeros(capacity, dtype=np.int16)
        self._n = 0
        self._lock = threading.Lock()

    def extend(self, t: np.ndarray, ch: np.ndarray) -> None:
        k = len(t)
        if k == 0:
            return
        cap = len(self.t)
        with self._lock:
            if k >= cap:
                t, ch, k = t[-cap:], ch[-cap:], cap
            i = self._n % cap
            first = min(k, cap - i)
            self.t[i : i + first] = t[:first]
            self.ch[i : i + first] = ch[:first]
            if first < k:
                self.t[: k - first] = t[first:]
                self.ch[: k - first] = ch[first:]
            self._n += k

    def since(self, t0: float) -> tuple[np.ndarray, np.ndarray]:
        """Spikes with time >= ``t0`` (s), unordered copies ``(t, channel)``."""
        with self._lock:
            n = min(self._n, len(self.t))
            t, ch = self.t[:n], self.ch[:n]
            keep = t >= t0
            return t[keep], ch[keep]

    def clear(self) -> None:
        with self._lock:
            self._n = 0

    @property
    def total(self) -> int:
        return self._n


#: the longest window the live view shows (s); the spike rings hold at least this much at the model's top rate
LIVE_WINDOW_MAX_S = 10.0
#: after a pause longer than a live view's longest window, the encoder starts afresh (its neurons at rest) this much
#: stream before that window, s: by the oldest spike shown its trains fire as the never-paused encoder's (spike counts
#: within 2 % over the window, test_gui_layouts.py; from 0.5 s before, a train near threshold fired 20 spikes the
#: never-paused one did not)
RESUME_WARM_UP_S = 2.0


def spike_capacity(layout: SensorLayout, seconds: float = LIVE_WINDOW_MAX_S, max_rate_hz: float = MODEL_RATE_HZ) -> int:
    """Spikes one population can produce in ``seconds``: ``layout.n_channels`` trains at ``max_rate_hz`` (one spike
    per 1 ms model step, the streaming encoder's ceiling), so a :class:`SpikeRing` of this size never drops a spike
    of the last ``seconds``."""
    return int(np.ceil(seconds * max_rate_hz * layout.n_channels))


class LiveEncoder(threading.Thread):
    """Streaming SA + RA encoding of the live taxel stream in a worker thread
    (:class:`rigctl.encoding.izhikevich.StreamingEncoder`, paper eqs. 3-5).

    Reads the taxel stream's ring buffer with its own cursor every ``poll_s`` and puts the spikes into
    :attr:`sa` and :attr:`ra` (:class:`SpikeRing`, times in s of stream time =
    frame number in the ring / ``layout.sample_rate_hz``; one model step per sample).
    ``layout`` is the stream's sensor (default ``taxels.layout``, else the paper's 3x3x2 at 1 kHz): one SA and one RA
    train per channel. ``normaliser`` is a :class:`rigctl.core.normalisation.TaxelRange` (per-taxel min/max, from the
    calibration); without one the full ADC range 0-``layout.adc_max`` is used.

    ``active=False`` (or :meth:`set_active`): paused, for a face that shows no spikes now (the GUI's live view
    hidden): the thread sleeps without reading the stream. On resuming it encodes the frames it missed, as if never
    paused, when they are at most :data:`LIVE_WINDOW_MAX_S` + :data:`RESUME_WARM_UP_S` of stream (and the ring still
    holds them); after a longer pause it starts afresh (neurons at rest) that much before the newest frame, so a live
    view's longest window is filled again (the spikes older than that window are never shown, and are not computed).
    """

    def __init__(self, taxels: Any, *, normaliser: TaxelRange | None = None, poll_s: float = 0.04,
                 layout: SensorLayout | None = None, active: bool = True) -> None:
        super().__init__(name="live-encoder", daemon=True)
        self.taxels = taxels
        self.layout = layout or getattr(taxels, "layout", None) or PAPER_SENSOR
        self.poll_s = poll_s
        self.normaliser = normaliser or self.full_range()
        self.n_samples = 0  # frames encoded since start
        # room for every spike of the live view's longest window even if every train fired at every model step
        # (1 ms): the raster never loses its oldest spikes to the ring's size
        cap = spike_capacity(self.layout)
        self.sa = SpikeRing(cap)
        self.ra = SpikeRing(cap)
        self.encoder_error: str | None = None
        self.ready = False  # the encoder's kernels are compiled and it is keeping up
        self._halt = threading.Event()
        self._reset_request = threading.Event()
        self._active = threading.Event()
        self._wake = threading.Event()  # set by set_active(True) and stop(): ends a pause's wait
        if active:
            self._active.set()

    def full_range(self) -> TaxelRange:
        """The full ADC range of every channel (no calibration yet)."""
        n = self.layout.n_channels
        return TaxelRange(np.zeros(n), np.full(n, float(self.layout.adc_max)))

    @property
    def stream_time_s(self) -> float:
        return self.n_samples / self.layout.sample_rate_hz

    def stop(self) -> None:
        self._halt.set()
        self._wake.set()

    @property
    def active(self) -> bool:
        """True while encoding; False while paused (:meth:`set_active`)."""
        return self._active.is_set()

    def set_active(self, on: bool) -> None:
        """Encode the stream (True) or pause (False; see the class's docstring). Returns at once."""
        if on:
            self._active.set()
            self._wake.set()
        else:
            self._active.clear()

    def _resume_start(self, ring: Any, cursor: int | None) -> int | None:
        """Where a resumed encoder goes on: None to go on from ``cursor`` with its state (the frames missed are
        few enough and still in the ring), else the frame to start afresh from."""
        total = ring.total
        keep = int(round((LIVE_WINDOW_MAX_S + RESUME_WARM_UP_S) * self.layout.sample_rate_hz))
        keep = min(keep, int(getattr(ring, "capacity", keep)))
        if cursor is not None and total - cursor <= keep:
            return None
        return max(0, total - keep)

    def set_normaliser(self, taxel_range: TaxelRange | None) -> None:
        """Use a new per-taxel range (a calibration) and start the encoder afresh."""
        self.normaliser = taxel_range or self.full_range()
        self._reset_request.set()

    def _make_encoder(self) -> Any:
        from rigctl.encoding.izhikevich import StreamingEncoder

        return StreamingEncoder(self.layout.n_channels, normalise=self.normaliser, fs=self.layout.sample_rate_hz)

    def run(self) -> None:
        ring = live_ring(self.taxels)
        encoder = None
        cursor = start = 0
        resume_from: int | None = None  # after a long pause: the frame a fresh encoder starts from
        while not self._halt.is_set():
            if not self._active.is_set():
                self._wake.wait()
                self._wake.clear()
                if self._active.is_set() and not self._halt.is_set():
                    resume_from = self._resume_start(ring, cursor if encoder is not None else None)
                    if resume_from is not None:
                        self._reset_request.set()
                continue
            if encoder is None or self._reset_request.is_set():
                self._reset_request.clear()
                try:
                    encoder = self._make_encoder()
                    encoder.process(np.zeros((1, self.layout.n_channels), np.uint16))  # compile before going live
                    encoder.reset()
                except Exception as exc:  # noqa: BLE001 - shown in the live view; traces keep going
                    self.encoder_error = describe_error(exc)
                    self._halt.wait(1.0)
                    encoder = None
                    continue
                cursor = start = ring.total if resume_from is None else resume_from
                resume_from = None
                self.ready = True
            cursor, samples, _seq, _t = ring.read_since(cursor)
            if len(samples):
                try:
                    chunk = encoder.process(samples)  # raw ADC counts; the encoder normalises
                except Exception as exc:  # noqa: BLE001
                    self.encoder_error = describe_error(exc)
                else:
                    off = start / self.layout.sample_rate_hz
                    t, ch = chunk.events("sa")
                    self.sa.extend(t + off, ch)
                    t, ch = chunk.events("ra")
                    self.ra.extend(t + off, ch)
                    self.encoder_error = None
                self.n_samples += len(samples)
            self._halt.wait(self.poll_s)
