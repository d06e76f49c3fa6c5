"""The real-time encoding of one scan, fed as it arrives (the paper's microcontroller; Methods, "Real-time Texture
Classification - Speed Invariance Module" and "Feature Extraction").

:class:`ScanEncoder` takes a scan's taxel readings chunk by chunk and the tracker's velocity samples as they come,
encodes the SA spike trains of the real-time taxels with the streaming Izhikevich encoder
(:class:`rigctl.encoding.izhikevich.StreamingEncoder`, identical to the batch encoding), and scales each 100 ms window
of "real time" as soon as it is complete and its velocity is known (eq. 2 applied to the gaps between the window's
spikes with that window's mean velocity, reference 100 mm/s: the piecewise map of
:func:`rigctl.encoding.speed.incremental_scale`, built window by window). :meth:`ScanEncoder.features` gives the
paper's two 180-feature vectors at the scan's end: the speed-scaled SR of the 20 scaled-time windows normalised by
each window's real-time duration (:func:`rigctl.encoding.features.realtime_features`), and the original SR of the last
20 real-time windows, or all of them zero-padded (:func:`rigctl.encoding.features.realtime_features_unscaled`).

The same functions compute the offline encoding of a recorded session (``rigctl encode``: variants
``realtime_original`` and ``realtime_speed_scaled``), so a scan encoded live gives the features the file holds for it
(``tests/encoding/test_realtime_scan.py`` holds them equal on a recorded handheld session).
"""

from __future__ import annotations

import numpy as np

from rigctl.core.normalisation import TaxelRange
from rigctl.encoding.features import realtime_features, realtime_features_unscaled
from rigctl.encoding.fixed_sa import FixedSAEncoder
from rigctl.encoding.izhikevich import StreamingEncoder
from rigctl.encoding.params import EncodeParams
from rigctl.encoding.speed import floor_speeds, window_speeds
from rigctl.encoding.spikes import SpikeTrains

__all__ = ["KERNELS", "ScanEncoder"]

#: the SA kernels a scan can be encoded with: "float" (the fused kernel in ``params.kernel_dtype``, float32 by
#: default) or "fixed" (the integer kernel the on-board encoder runs, :mod:`rigctl.encoding.fixed_sa`)
KERNELS = ("float", "fixed")


class ScanEncoder:
    """One scan's SA spikes, incremental speed scaling and real-time features (module docstring).

    Parameters
    ----------
    normalisation : the per-taxel range the readings are normalised with (an encoded file's ``normalisation``: the
        same as the offline encoding's).
    params : the encoding's constants (an encoded file's ``EncodeParams.from_dict(f.parameters)``): ``k_sa``,
        ``window_s``, ``n_windows_realtime``, ``realtime_reference_speed_mm_s``, ``realtime_taxels``, ``fs_hz``.
    taxels : the channels encoded (default ``params.realtime_taxels``, else every channel).
    kernel : "float" (default: the fused float kernel in ``params.kernel_dtype``) or "fixed" (the on-board
        encoder's integer kernel, :class:`rigctl.encoding.fixed_sa.FixedSAEncoder`: the board's spikes exactly;
        needs an integer range and an integer ``k_sa`` <= 255).

    Raises
    ------
    ValueError
        The stream is not at the model's rate (``params.fs_hz``: resample first), the range has no taxels, an
        unknown kernel, or a range or k the integer kernel cannot take.
    """

    def __init__(self, normalisation: TaxelRange, params: EncodeParams | None = None, *,
                 taxels: list[int] | None = None, kernel: str = "float") -> None:
        self.params = p = params or EncodeParams()
        n_ch = normalisation.n_taxels
        if n_ch == 0:
            raise ValueError("the normalisation has no taxels")
        self.taxels = list(taxels if taxels is not None else (p.realtime_taxels or range(n_ch)))
        if kernel not in KERNELS:
            raise ValueError(f"kernel must be one of {KERNELS}, got {kernel!r}")
        self.kernel = kernel
        rng = TaxelRange(normalisation.taxel_min[self.taxels], normalisation.taxel_max[self.taxels])
        self._encoder: StreamingEncoder | FixedSAEncoder
        if kernel == "fixed":
            self._encoder = FixedSAEncoder(rng, k_sa=p.k_sa, fs=p.fs_hz)
        else:
            self._encoder = StreamingEncoder(len(self.taxels), normalise=rng, k_sa=p.k_sa, fs=p.fs_hz,
                                             dtype=np.dtype(p.kernel_dtype), ra=False)  # SA spikes only
        self.reset()

    def reset(self) -> None:
        """Start a new scan."""
        self._encoder.reset()
        self.n_samples = 0
        self._pending: list[np.ndarray] = []  # readings fed but not yet run through the encoder (see :meth:`feed`)
        self._real: list[list[np.ndarray]] = [[] for _ in self.taxels]  # real-time spike times per taxel, s
        self._n_scaled = [0] * len(self.taxels)  # of which this many are scaled
        self._scaled: list[list[np.ndarray]] = [[] for _ in self.taxels]  # scaled-time spike times, s
        self._trace_t: list[np.ndarray] = []
        self._trace_v: list[np.ndarray] = []
        self._n_trace = 0  # velocity samples so far
        self._trace_end_s = 0.0  # the latest one's time, s (NaN if a time was NaN)
        self._factors: list[float] = []  # v_w / v_ref of each scaled real-time window so far
        self._edges = [0.0]  # scaled time of each real-time window edge

    @property
    def windows_scaled(self) -> int:
        """Real-time windows scaled so far (each once complete and its velocity known)."""
        return len(self._factors)

    # ------------------------------------------------------------------------------------------------- feeding
    def feed(self, readings: np.ndarray) -> None:
        """The next ``(n, n_channels)`` raw readings (ADC counts) of the scan, at ``params.fs_hz``.

        The encoder runs on the readings when their spikes are needed (a window to scale, the features): the
        spikes of a stream do not depend on how it is cut into chunks (:class:`rigctl.encoding.izhikevich.
        StreamingEncoder`, :class:`rigctl.encoding.fixed_sa.FixedSAEncoder`), so one call per 100 ms window gives
        those of one call per chunk, without the per-call cost of every 20 ms block."""
        x = np.asarray(readings)[:, self.taxels]
        self._pending.append(x)
        self.n_samples += x.shape[0]
        self._scale_ready()

    def _encode_pending(self) -> None:
        """Run the encoder on the readings fed since its last run; their spikes join each taxel's real-time train."""
        if not self._pending:
            return
        x = self._pending[0] if len(self._pending) == 1 else np.concatenate(self._pending)
        self._pending = []
        enc = self._encoder
        sa = enc.process(x) if isinstance(enc, FixedSAEncoder) else enc.process(x).sa
        for i in range(len(self.taxels)):
            self._real[i].append(sa.train(0, i))

    def feed_speed(self, time_s: np.ndarray, speed_mm_s: np.ndarray) -> None:
        """The tracker's velocity samples that arrived: times (s from the scan's first sample, increasing) and
        mm/s."""
        t = np.asarray(time_s, np.float64).reshape(-1)
        self._trace_t.append(t)
        self._trace_v.append(np.asarray(speed_mm_s, np.float64).reshape(-1))
        if t.size:
            end = t.max()
            self._trace_end_s = float(end if self._n_trace == 0 else np.maximum(self._trace_end_s, end))
            self._n_trace += t.size
        self._scale_ready()

    def _trace(self) -> tuple[np.ndarray, np.ndarray]:
        """The velocity samples so far, as one (times s, mm/s) pair (the pieces joined once)."""
        if len(self._trace_t) > 1:
            self._trace_t, self._trace_v = [np.concatenate(self._trace_t)], [np.concatenate(self._trace_v)]
        t = self._trace_t[0] if self._trace_t else np.zeros(0)
        v = self._trace_v[0] if self._trace_v else np.zeros(0)
        return t, v

    def _scale_ready(self, final: bool = False) -> None:
        """Scale every window that is complete (its samples in, a velocity sample at or past its end), or, at the
        scan's end (``final``), every window left (the last partial one too; the velocity held past the trace)."""
        p = self.params
        if self._n_trace == 0:
            return
        w_s = p.window_s
        per = max(1, int(round(w_s * p.fs_hz)))
        n_done = len(self._factors)
        if not final:
            n_ready = min(self.n_samples // per, int(np.floor(self._trace_end_s / w_s)))
            if n_ready <= n_done:
                return
        t, v = self._trace()
        if final:
            n_ready = max(1, -(-self.n_samples // per))  # ceil: as the offline encoding's windows
            speeds = window_speeds(t, v, self.n_samples / p.fs_hz, w_s)
        else:
            speeds = window_speeds(t, v, n_ready * w_s, w_s)  # window w depends on the samples around it only
        speeds = floor_speeds(speeds)  # a window the hand stood still or slipped back in: 0 mm/s, as the board
        for w in range(n_done, n_ready):
            f = float(speeds[w]) / p.realtime_reference_speed_mm_s
            self._factors.append(f)
            self._edges.append(self._edges[-1] + f * w_s)
        self._encode_pending()
        self._scale_spikes(final)

    def _scale_spikes(self, final: bool) -> None:
        """Scale the spikes of the windows scaled so far (every spike at the end: those past the last window with
        its factor, as :func:`rigctl.encoding.speed.incremental_scale`)."""
        w_s = self.params.window_s
        n_win = len(self._factors)
        factor = np.asarray(self._factors)
        edges = np.asarray(self._edges)
        limit = np.inf if final else n_win * w_s
        for i in range(len(self.taxels)):
            if len(self._real[i]) > 1:
                self._real[i] = [np.concatenate(self._real[i])]
            x = self._real[i][0][self._n_scaled[i]:] if self._real[i] else np.zeros(0)
            x = x[x < limit]
            if x.size:
                w = np.clip(np.floor(x / w_s).astype(np.int64), 0, n_win - 1)
                self._scaled[i].append(edges[w] + (x - w * w_s) * factor[w])
                self._n_scaled[i] += x.size

    # ------------------------------------------------------------------------------------------------- the end
    def features(self) -> dict[str, np.ndarray]:
        """At the scan's end: ``{"realtime_original": (n_taxels * 20,), "realtime_speed_scaled": (n_taxels * 20,)}``
        float32 spikes/s (the second only with velocity samples). Call once per scan (then :meth:`reset`)."""
        p = self.params
        duration = self.n_samples / p.fs_hz
        self._encode_pending()
        real = SpikeTrains.from_lists([[np.concatenate(self._real[i] + [np.zeros(0)])
                                         for i in range(len(self.taxels))]])
        out = {"realtime_original": realtime_features_unscaled(real, duration, n_windows=p.n_windows_realtime,
                                                               window_s=p.window_s)[0]}
        if self._n_trace:
            self._scale_ready(final=True)
            trains = SpikeTrains.from_lists([[np.concatenate(self._scaled[i] + [np.zeros(0)])
                                              for i in range(len(self.taxels))]])
            out["realtime_speed_scaled"] = realtime_features(trains, [np.asarray(self._edges)],
                                                             n_windows=p.n_windows_realtime, window_s=p.window_s)[0]
        return out
