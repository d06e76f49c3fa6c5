"""Cutting a continuous recording into trials: fixed windows, activity runs, or cycles cut at each press onset.

The fourth step of ``rigctl import`` (``--segment``, ``--align``, ``--pre-ms``; :mod:`rigctl.storage.importers`).
Every method works on one file at a time, at that file's own level:

- **Activity** (:func:`activity`): the sensor's rest level per channel is the median over the quietest fifth of
  the recording (the samples with the least sample-to-sample change, summed over channels and averaged over 0.2 s: a
  sliding contact vibrates, an unloaded sensor does not); the activity is the largest deviation of any channel from
  its rest level, moving-averaged over ``smooth_s`` (0.05 s). Its *swing* runs from its median over the quiet samples
  (rest) to its 95th percentile (pressed), so a level given as a fraction of the swing means the same on a file 5x
  weaker than the next. Limitation (measured with :mod:`rigctl.simulation.press_slide`): a static press (no
  vibration) held for 75 % of the cycle or more is as quiet as rest, the rest level can come out as the pressed one,
  and cycles are then cut at the release (trials 0.9-1.4 s off); a sliding press, or a static one under about half
  the cycle, is cut within 50 ms of its onset.
- ``fixed:SECONDS[:HOP_S]``: windows from the first sample.
- ``threshold[:LEVEL[:MIN_S[:SMOOTH_S]]]``: runs of activity above LEVEL lasting at least MIN_S (0.2 s) are trials.
  A run cut by the start or the end of the file is partial and rejected. LEVEL is a percentage of the file's own
  swing (``50%``, the default) or, as a plain number, counts of activity (the same for every file). Hysteresis: a
  run ends when the activity falls below half way between rest and LEVEL, so a vibration's zero crossings do not
  cut a trial. Relative levels and cycles refuse a file whose swing is under 10x its noise at rest (no presses).
- ``cycles[:N[:MIN_PERIOD_S[:MAX_PERIOD_S]]]`` (press-and-slide recordings): presses are runs above 50 % of the
  swing; each press's **onset** is the last sample before it where the activity is within 5 % of the swing of
  rest. The **period** starts from the highest autocorrelation peak of the activity (beyond its first zero crossing,
  or within MIN..MAX) and is checked against its harmonics and sub-harmonics (1/4 .. 4 times it) and the median
  press interval: each candidate period is scored by the cycles it explains, presses whose next press follows
  within -20 % / +25 % of it and whose activity over one period correlates >= 0.5 with the median such cycle; the
  candidate explaining the most cycles wins (ties: the shorter), and the period is the median of the intervals it
  explained. A multiple of the period explains no interval and a harmonic none either, so neither is picked
  silently. Trials start ``pre_ms`` before each onset (``--align onset``, default) and last N periods; a cycle
  whose trial would start before the file or run past its end is rejected (a partial cycle) and counted. Presses
  closer than half a period are one press (the one whose next press is nearer a period away is kept).
  ``--align none`` keeps the former rule: the autocorrelation period of the channel mean, windows from sample 0.

:func:`segment` returns a :class:`Segmentation` (sample ranges, cycle indices, period, rejected cycles); the caller
prints :func:`segment_table` and :func:`outlier_warnings` (a file whose period or trial count is under half or
over twice the import's median).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np

from rigctl.storage.recording_files import RecordingImportError

__all__ = ["SegmentSpec", "Segmentation", "Activity", "ALIGNS", "parse_segment", "activity", "segment",
           "segment_table", "outlier_warnings", "press_check", "rig_slots", "FINDER", "declared_press_period"]

#: ``--align``: cut cycles at each press onset, or from sample 0 (the former rule)
ALIGNS = ("onset", "none")
#: the quietest fraction of a recording that defines its rest level
QUIET_FRACTION = 0.2
#: window of the sample-to-sample change that finds the quiet samples, s
QUIET_WINDOW_S = 0.2
#: a press: activity above this fraction of the swing; its onset: the last sample within ONSET_FRACTION of rest
PRESS_FRACTION = 0.5
ONSET_FRACTION = 0.05
#: the press phase a cut is checked against (:func:`press_check`): presses above this fraction of the swing
PHASE_FRACTION = 0.25
#: an interval explains a period P when it lies in [INTERVAL_LO * P, INTERVAL_HI * P]
INTERVAL_LO, INTERVAL_HI = 0.8, 1.25
#: a cycle has the shape of the others when its activity correlates at least this much with the median cycle
SHAPE_MIN_CORR = 0.5
#: presses must lift the activity at least this many times the rest's noise (robust sd of the activity at rest),
#: unless the activity is clearly periodic (cycles: :data:`MIN_PERIODICITY`); ``--min-swing`` sets it per import
MIN_SWING_NOISE = 10.0
#: cycles: an activity whose autocorrelation peaks at least this high over the period range has presses, whatever its
#: swing against the noise (issue 38: a file with 42 visible cycles at 7.9x its noise was refused on amplitude)
MIN_PERIODICITY = 0.5
#: period candidates: these multiples of the autocorrelation's highest peak
HARMONICS = (0.25, 1 / 3, 0.5, 1.0, 2.0, 3.0, 4.0)
#: a file is an outlier when its period or trial count is under 1/OUTLIER_RATIO or over OUTLIER_RATIO x the median
OUTLIER_RATIO = 2.0

_USAGE = ("use fixed:SECONDS[:HOP_S], threshold[:LEVEL[%][:MIN_S[:SMOOTH_S]]] or "
          "cycles[:N[:MIN_PERIOD_S[:MAX_PERIOD_S]]]")


@dataclass(frozen=True)
class SegmentSpec:
    """How to cut a continuous recording (:func:`parse_segment`; the module docstring gives each method's rule).

    method : "fixed" | "threshold" | "cycles"
    length_s, hop_s : fixed windows, s
    level_counts / level_fraction : threshold, counts above rest or a fraction of the file's swing (one is None)
    min_s, smooth_s : threshold: shortest run, s; activity smoothing, s (cycles use ``smooth_s`` too)
    n_cycles, min_period_s, max_period_s : cycles per trial; the period's search range, s (None: automatic)
    align : "onset" (cut at each press onset) | "none" (from sample 0; cycles only)
    pre_s : margin before each onset / run start, s
    """

    method: str
    length_s: float | None = None
    hop_s: float | None = None
    level_counts: float | None = None
    level_fraction: float | None = None
    min_s: float = 0.2
    smooth_s: float = 0.05
    n_cycles: int = 1
    min_period_s: float | None = None
    max_period_s: float | None = None
    align: str = "onset"
    pre_s: float = 0.0
    min_swing: float = MIN_SWING_NOISE

    def record(self) -> dict[str, Any]:
        """The settings that apply to this method, for the session's ``segmentation`` attribute."""
        keep = {"fixed": ("length_s", "hop_s"),
                "threshold": ("level_counts", "level_fraction", "min_s", "smooth_s", "pre_s", "min_swing"),
                "cycles": ("n_cycles", "min_period_s", "max_period_s", "smooth_s", "align", "pre_s", "min_swing")
                }[self.method]
        return {"method": self.method, **{k: v for k, v in asdict(self).items() if k in keep and v is not None}}


#: what presses are counted against when the rig's press period is not known (:attr:`Segmentation.press_basis`)
FINDER = "rigctl's press finder"
#: a period found further than this fraction from the rig's declared one is named (:attr:`Segmentation.press_problem`)
RIG_PERIOD_TOLERANCE = 0.1
#: against the rig's period, a press found within this fraction of it from a slot of the rig's period is that slot's
#: press (the walk then restarts from it: a rig's cycles jitter and drift)
SLOT_TOLERANCE = 0.2

#: a trial overlapping the next one by more than this share of its length is named (:meth:`Segmentation.overlaps`)
OVERLAP_FRACTION = 0.2


@dataclass
class Segmentation:
    """One recording cut into trials.

    bounds : ``[(start, stop), ...]`` sample ranges (stop exclusive) of the trials
    cycle_index : per trial, the index of its cycle (cycles) or run (threshold) or window (fixed) in the file
    rejected : cycles or runs found but not made trials (partial cycles at the ends, runs under MIN_S)
    period_s : the file's cycle period (cycles), else None
    onsets : every press onset found (cycles with ``align="onset"``), samples
    candidates : the period candidates and the cycles each explained (cycles with ``align="onset"``)
    presses : the file's press phase checked against the trials (cycles with ``align="onset"``,
        :func:`press_check`): ``{"presses", "cut", "missed", "off_onset", "wrong_count"}``; None otherwise
    """

    bounds: list[tuple[int, int]]
    cycle_index: list[int]
    rejected: int = 0
    period_s: float | None = None
    onsets: list[int] = field(default_factory=list)
    candidates: list[dict[str, float]] = field(default_factory=list)
    presses: dict[str, int] | None = None
    #: the rig's press period, s, when known (declared with --press-period-s or a mapping, or in the file), and
    #: where it came from; the presses are then counted against it, else against :data:`FINDER`
    rig_period_s: float | None = None
    rig_period_from: str | None = None

    @property
    def press_basis(self) -> str | None:
        """What the presses were counted against: ``"the rig's period 4.00 s (--press-period-s)"``, :data:`FINDER`,
        or None (no press check: not cut into cycles)."""
        if self.presses is None:
            return None
        if self.rig_period_s is None:
            return FINDER
        return f"the rig's period {self.rig_period_s:.2f} s ({self.rig_period_from or 'declared'})"

    @property
    def press_problem(self) -> str | None:
        """One line when the trials do not follow the presses one by one (``"21 of 41 presses cut as trials press by
        press (20 missed: 20 not in the file ...; counted against the rig's period 4.00 s (--press-period-s))"``),
        else None. The line says what the presses were counted against (:attr:`press_basis`)."""
        c = self.presses
        if not c or (c["cut"] == c["presses"] and not c["off_onset"] and not c["wrong_count"]):
            return None
        absent = c.get("absent", 0)
        parts = [f"{c['missed']} missed" + (f": {absent} not in the file (no press found at its time)" if absent
                                             else "") if c["missed"] else "",
                 f"{c['off_onset']} trials start off a press onset" if c["off_onset"] else "",
                 f"{c['wrong_count']} trials hold another number of presses than asked" if c["wrong_count"] else ""]
        if self.rig_period_s and self.period_s and abs(self.period_s / self.rig_period_s - 1) > RIG_PERIOD_TOLERANCE:
            parts.append(f"the period found, {self.period_s:.2f} s, is not the rig's")
        basis = self.press_basis or FINDER
        hint = (": give the rig's press period with --press-period-s to count against it" if basis == FINDER else "")
        return (f"{c['cut']} of {c['presses']} presses cut as trials press by press (" + ", ".join(x for x in parts if x)
                + f"; counted against {basis}{hint})")

    def overlaps(self) -> tuple[int, int]:
        """``(trials, samples)``: how many trials run into the next one's start by more than
        :data:`OVERLAP_FRACTION` of their length, and the samples they share (a period longer than the spacing of
        the presses makes trials that hold the same samples twice; a few samples of a press's jitter do not count)."""
        shared = [b - a2 for (a, b), (a2, _) in zip(self.bounds, self.bounds[1:]) if b - a2 > OVERLAP_FRACTION * (b - a)]
        return len(shared), int(sum(shared))

    def row(self, file: str, rate_hz: float) -> dict[str, Any]:
        """The per-file table's row: file, period_s, trials, rejected, first_onset_s, overlapping (trials that run
        into the next one) and shared_samples."""
        first = self.bounds[0][0] / rate_hz if self.bounds else None
        overlapping, shared = self.overlaps()
        return {"file": file, "period_s": self.period_s, "trials": len(self.bounds), "rejected": self.rejected,
                "first_start_s": first, "overlapping": overlapping, "shared_samples": shared,
                "presses": None if self.presses is None else dict(self.presses),
                "presses_against": self.press_basis, "press_problem": self.press_problem}


def _number(text: str, spec: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise RecordingImportError(f"--segment {spec!r}: the values after the method must be numbers") from None
    if not (math.isfinite(value) and value >= 0):
        raise RecordingImportError(f"--segment {spec!r}: {text} is not a positive number; {_USAGE}")
    return value


def declared_press_period(value: Any, where: str, segment: SegmentSpec | None = None) -> float | None:
    """A declared press period, s (None: not declared); RecordingImportError for one that is not a number > 0, or
    (``segment`` given) for an import that does not cut cycles at their onsets (nothing to count against it)."""
    if value is None:
        return None
    try:
        period = float(value)
    except (TypeError, ValueError):
        period = math.nan
    if not (math.isfinite(period) and period > 0):
        raise RecordingImportError(f"{where} {value!r}: the rig's press period must be a number of seconds > 0")
    if segment is not None and not (segment.method == "cycles" and segment.align == "onset"):
        raise RecordingImportError(f"{where}: the rig's press period counts the presses of --segment cycles (cut at "
                                   f"each onset); this import cuts by {segment.method}")
    return period


def parse_segment(spec: str | None, *, align: str | None = None, pre_ms: float | None = None,
                  min_swing: float | None = None) -> SegmentSpec | None:
    """:func:`_parse_segment`, with ``min_swing`` (the presses' swing against the noise at rest that the threshold
    and cycles methods require, default :data:`MIN_SWING_NOISE`; > 0)."""
    out = _parse_segment(spec, align=align, pre_ms=pre_ms)
    if out is None or min_swing is None:
        return out
    if not (math.isfinite(float(min_swing)) and float(min_swing) > 0):
        raise RecordingImportError(f"--min-swing {min_swing}: must be a number > 0")
    return replace(out, min_swing=float(min_swing))


def _parse_segment(spec: str | None, *, align: str | None = None, pre_ms: float | None = None) -> SegmentSpec | None:
    """``fixed:S[:HOP]`` | ``threshold[:LEVEL[%][:MIN_S[:SMOOTH_S]]]`` | ``cycles[:N[:MIN_P[:MAX_P]]]`` ->
    :class:`SegmentSpec` (None for no spec). ``align`` (:data:`ALIGNS`, default "onset") and ``pre_ms`` (the margin
    before each onset, ms, default 0) apply to cycles and threshold runs. Raises RecordingImportError on anything
    else (the message starts with ``--segment 'SPEC':``)."""
    if not spec:
        return None
    align = align or "onset"
    if align not in ALIGNS:
        raise RecordingImportError(f"--align {align!r}: use {' | '.join(ALIGNS)}")
    pre_s = 0.0 if pre_ms is None else float(pre_ms) / 1000.0
    if not (math.isfinite(pre_s) and pre_s >= 0):
        raise RecordingImportError(f"--pre-ms {pre_ms}: must be a number >= 0")
    kind, *args = str(spec).strip().split(":")
    args = [a for a in args if a != ""]
    if kind == "fixed" and 1 <= len(args) <= 2:
        vals = [_number(a, spec) for a in args]
        if all(v > 0 for v in vals):
            return SegmentSpec("fixed", length_s=vals[0], hop_s=vals[-1])
    if kind == "threshold" and len(args) <= 3:
        level = args[0] if args else "50%"
        rest = [_number(a, spec) for a in args[1:]]
        frac = _number(level[:-1], spec) / 100.0 if level.endswith("%") else None
        counts = None if frac is not None else _number(level, spec)
        if (frac is None or 0 < frac < 1) and all(v > 0 for v in rest):
            return SegmentSpec("threshold", level_counts=counts, level_fraction=frac,
                               min_s=rest[0] if rest else 0.2, smooth_s=rest[1] if len(rest) > 1 else 0.05,
                               pre_s=pre_s)
    if kind == "cycles" and len(args) <= 3:
        vals = [_number(a, spec) for a in args]
        if all(v > 0 for v in vals) and (not vals or vals[0] == int(vals[0])):
            lo = vals[1] if len(vals) > 1 else None
            hi = vals[2] if len(vals) > 2 else None
            if lo is None or hi is None or hi > lo:
                return SegmentSpec("cycles", n_cycles=int(vals[0]) if vals else 1, min_period_s=lo, max_period_s=hi,
                                   align=align, pre_s=pre_s)
    raise RecordingImportError(f"--segment {spec!r}: {_USAGE}")


# ----------------------------------------------------------------------------------------------------- activity
@dataclass
class Activity:
    """A recording's activity (module docstring): ``values`` (n,) counts, ``rest`` and ``high`` (its level at rest
    and its 95th percentile), ``noise`` (its robust sd at rest, 1.4826 x MAD), ``rest_counts`` (n_channels,) the
    per-channel rest level."""

    values: np.ndarray
    rest: float
    high: float
    noise: float
    rest_counts: np.ndarray

    def check_presses(self, min_swing: float = MIN_SWING_NOISE, periodicity: float | None = None) -> None:
        """RecordingImportError unless the swing is at least ``min_swing`` x the rest's noise or (cycles) the
        activity's ``periodicity`` (its autocorrelation's highest peak over the period range) reaches
        :data:`MIN_PERIODICITY`."""
        if self.swing >= min_swing * max(self.noise, 0.5):
            return
        if periodicity is not None and periodicity >= MIN_PERIODICITY:
            return
        periodic = "" if periodicity is None else f", autocorrelation peak {periodicity:.2f}"
        raise RecordingImportError(
            f"no presses above the noise (activity swing {self.swing:.1f} counts = "
            f"{self.swing / max(self.noise, 0.5):.1f}x the noise at rest, {self.noise:.1f} counts{periodic}): give "
            f"--min-swing (now {min_swing:g}), --segment fixed:SECONDS or threshold:COUNTS")

    @property
    def swing(self) -> float:
        return self.high - self.rest

    def level(self, fraction: float) -> float:
        """The activity ``fraction`` of the way from rest to high."""
        return self.rest + fraction * self.swing


def activity(counts: np.ndarray, rate_hz: float, smooth_s: float = 0.05) -> Activity:
    """The activity of ``(n, n_channels)`` counts at ``rate_hz`` (module docstring). Raises RecordingImportError
    for fewer than 3 samples."""
    # here, not at the top: scipy.ndimage costs ~0.15 CPU-s to import, and `rigctl import` segments only when asked
    from scipy.ndimage import uniform_filter1d

    x = np.asarray(counts, dtype=np.float64)
    if x.shape[0] < 3:
        raise RecordingImportError("too few samples to segment")
    change = np.abs(np.diff(x, axis=0)).sum(axis=1)
    change = uniform_filter1d(np.concatenate((change[:1], change)), max(2, round(QUIET_WINDOW_S * rate_hz)),
                              mode="nearest")
    quiet = change <= np.quantile(change, QUIET_FRACTION)
    rest_counts = np.median(x[quiet], axis=0)
    dev = np.abs(x - rest_counts).max(axis=1)
    values = uniform_filter1d(dev, max(1, round(smooth_s * rate_hz)), mode="nearest")
    at_rest = values[quiet]
    rest = float(np.median(at_rest))
    noise = 1.4826 * float(np.median(np.abs(at_rest - rest)))
    return Activity(values, rest, float(np.quantile(values, 0.95)), noise, rest_counts)


def _runs(a: np.ndarray, on: float, off: float) -> list[tuple[int, int]]:
    """``[(start, stop), ...]`` where ``a`` rises above ``on`` until it falls below ``off`` (hysteresis)."""
    n = a.size
    event = np.where(a > on, 1, np.where(a < off, -1, 0))
    last = np.maximum.accumulate(np.where(event != 0, np.arange(n), -1))
    state = (last >= 0) & (event[np.maximum(last, 0)] == 1)
    edges = np.flatnonzero(np.diff(np.concatenate(([0], state.astype(np.int8), [0]))))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist()))


# ----------------------------------------------------------------------------------------------------- period
def _autocorrelation(sig: np.ndarray) -> np.ndarray:
    """Unbiased, normalised autocorrelation of ``sig`` (mean removed) at lags 0 .. n-1 (FFT)."""
    sig = sig - sig.mean()
    n = sig.size
    nfft = 1 << int(math.ceil(math.log2(2 * n)))
    spec = np.fft.rfft(sig, nfft)
    ac = np.fft.irfft(spec * np.conj(spec), nfft)[:n]
    if ac[0] <= 0:
        raise RecordingImportError("cycles: the recording is constant, no cycle to detect")
    out: np.ndarray = ac / ac[0] * n / (n - np.arange(n))
    return out


def _lag_range(ac: np.ndarray, rate_hz: float, min_p: float | None, max_p: float | None) -> tuple[int, int]:
    n = ac.size
    hi = min(n // 2, int(round(max_p * rate_hz)) if max_p else n // 2)
    lo = max(1, int(round((min_p or 0.0) * rate_hz)))
    if min_p is None:  # start after the first zero crossing (the central lobe is not a period)
        neg = np.flatnonzero(ac[1:hi] < 0)
        if not neg.size:
            raise RecordingImportError("cycles: no periodic structure found (give cycles:N:MIN_PERIOD_S:MAX_PERIOD_S)")
        lo = int(neg[0]) + 1
    if hi <= lo + 1:
        raise RecordingImportError("cycles: the recording is too short for the period range")
    return lo, hi


def _acf_period(x: np.ndarray, rate_hz: float, min_p: float | None, max_p: float | None) -> int:
    """The former rule (``--align none``): the shortest autocorrelation peak of the channel mean reaching 90 % of the
    highest, samples."""
    ac = _autocorrelation(x.astype(np.float64).mean(axis=1))
    lo, hi = _lag_range(ac, rate_hz, min_p, max_p)
    seg = ac[lo:hi]
    peaks = np.flatnonzero((seg[1:-1] >= seg[:-2]) & (seg[1:-1] >= seg[2:])) + 1
    good = peaks[seg[peaks] >= 0.9 * float(seg.max())] if peaks.size else np.array([int(np.argmax(seg))])
    return lo + int(good[0] if good.size else np.argmax(seg))


def _periodicity(a: np.ndarray, rate_hz: float, spec: SegmentSpec) -> float:
    """The highest autocorrelation of the activity ``a`` over the period range (0 when none can be found)."""
    try:
        ac = _autocorrelation(a)
        lo, hi = _lag_range(ac, rate_hz, spec.min_period_s, spec.max_period_s)
    except RecordingImportError:
        return 0.0
    return float(ac[lo:hi].max())


def _explained(a: np.ndarray, onsets: np.ndarray, period: int) -> np.ndarray:
    """Indices ``i`` of the onsets whose next onset follows within [INTERVAL_LO, INTERVAL_HI] x ``period`` and whose
    activity over one period correlates >= SHAPE_MIN_CORR with the median of those cycles."""
    if onsets.size < 2 or period < 2:
        return np.empty(0, dtype=np.int64)
    intervals = np.diff(onsets)
    idx = np.flatnonzero((intervals >= INTERVAL_LO * period) & (intervals <= INTERVAL_HI * period)
                         & (onsets[:-1] + period <= a.size))
    if idx.size == 0:
        return idx
    cycles = np.stack([a[o:o + period] for o in onsets[idx]])
    cycles = cycles - cycles.mean(axis=1, keepdims=True)
    template = np.median(cycles, axis=0)
    norm = np.linalg.norm(cycles, axis=1) * np.linalg.norm(template)
    corr = np.divide(cycles @ template, norm, out=np.zeros(len(idx)), where=norm > 0)
    kept: np.ndarray = idx[corr >= SHAPE_MIN_CORR]
    return kept


def _checked_period(a: np.ndarray, onsets: np.ndarray, rate_hz: float, spec: SegmentSpec
                    ) -> tuple[int, list[dict[str, float]]]:
    """The period (samples) that explains the most cycles among the autocorrelation peak's harmonics and
    sub-harmonics and the median press interval (module docstring), and every candidate's score."""
    ac = _autocorrelation(a)
    lo, hi = _lag_range(ac, rate_hz, spec.min_period_s, spec.max_period_s)
    peak = lo + int(np.argmax(ac[lo:hi]))
    raw = [peak * h for h in HARMONICS]
    if onsets.size >= 2:
        raw.append(float(np.median(np.diff(onsets))))
    candidates = set()
    for lag in raw:
        a0, b0 = max(lo, int(0.9 * lag)), min(hi, int(math.ceil(1.1 * lag)) + 1)
        if b0 > a0:
            candidates.add(a0 + int(np.argmax(ac[a0:b0])))
    scored = []
    for p in sorted(candidates):
        idx = _explained(a, onsets, p)
        scored.append((len(idx), -p, idx))
    report = [{"period_s": -q / rate_hz, "cycles": float(k)} for k, q, _ in sorted(scored, key=lambda s: -s[1])]
    best = max(scored, key=lambda s: (s[0], s[1])) if scored else None
    if best is None or best[0] == 0:
        raise RecordingImportError(
            f"cycles: no repeated presses found ({onsets.size} press onsets; autocorrelation peak "
            f"{peak / rate_hz:.2f} s): give cycles:N:MIN_PERIOD_S:MAX_PERIOD_S, --segment threshold or fixed")
    return int(round(float(np.median(np.diff(onsets)[best[2]])))), report


def _merge_presses(onsets: np.ndarray, period: int) -> np.ndarray:
    """Onsets closer than half a period are one press: of two, the one whose next onset is nearer a period away."""
    kept: list[int] = []
    for i, o in enumerate(onsets.tolist()):
        if kept and o - kept[-1] < period / 2:
            nxt = onsets[i + 1] if i + 1 < onsets.size else None
            if nxt is not None and abs(nxt - o - period) < abs(nxt - kept[-1] - period):
                kept[-1] = o
            continue
        kept.append(o)
    return np.asarray(kept, dtype=np.int64)


# ----------------------------------------------------------------------------------------------------- methods
def _fixed(n: int, rate_hz: float, spec: SegmentSpec) -> Segmentation:
    assert spec.length_s is not None and spec.hop_s is not None
    length, hop = int(round(spec.length_s * rate_hz)), int(round(spec.hop_s * rate_hz))
    if length < 1 or hop < 1:
        raise RecordingImportError(f"segment length {spec.length_s} s is under one sample at {rate_hz:g} Hz")
    bounds = [(s, s + length) for s in range(0, n - length + 1, hop)]
    return Segmentation(bounds, list(range(len(bounds))))


def _threshold(counts: np.ndarray, rate_hz: float, spec: SegmentSpec) -> Segmentation:
    act = activity(counts, rate_hz, spec.smooth_s)
    if spec.level_fraction is not None:
        act.check_presses(spec.min_swing)
    on = act.level(spec.level_fraction) if spec.level_fraction is not None else float(spec.level_counts or 0.0)
    off = act.rest + (on - act.rest) / 2 if on > act.rest else on
    runs = _runs(act.values, on, off)
    min_n, pre = max(1, int(round(spec.min_s * rate_hz))), int(round(spec.pre_s * rate_hz))
    bounds, index = [], []
    for i, (a, b) in enumerate(runs):
        if b - a >= min_n and a - pre >= 0 and a > 0 and b < act.values.size:  # not cut by the file's ends
            bounds.append((a - pre, b))
            index.append(i)
    return Segmentation(bounds, index, rejected=len(runs) - len(bounds))


def _cycles(counts: np.ndarray, rate_hz: float, spec: SegmentSpec, rig_period: int | None = None) -> Segmentation:
    n = counts.shape[0]
    if spec.align == "none":
        period = _acf_period(counts, rate_hz, spec.min_period_s, spec.max_period_s)
        length = period * spec.n_cycles
        bounds = [(s, s + length) for s in range(0, n - length + 1, length)]
        return Segmentation(bounds, [i * spec.n_cycles for i in range(len(bounds))], period_s=period / rate_hz)
    act = activity(counts, rate_hz, spec.smooth_s)
    act.check_presses(spec.min_swing, _periodicity(act.values, rate_hz, spec))
    a = act.values
    low = np.flatnonzero(a <= act.level(ONSET_FRACTION))
    onsets, inside = [], 0
    for start, _ in _runs(a, act.level(PRESS_FRACTION), act.level(PRESS_FRACTION / 2)):
        k = int(np.searchsorted(low, start)) - 1
        if k < 0:
            inside += 1  # the file starts inside a press: no onset to cut at
        else:
            onsets.append(int(low[k]) + 1)
    raw = np.asarray(onsets, dtype=np.int64)
    period, candidates = _checked_period(a, raw, rate_hz, spec)
    kept = _merge_presses(raw, period)
    length, pre = period * spec.n_cycles, int(round(spec.pre_s * rate_hz))
    bounds, index = [], []
    for i in range(0, kept.size, spec.n_cycles):
        start = int(kept[i]) - pre
        if start >= 0 and start + length <= n:
            bounds.append((start, start + length))
            index.append(i)
    rejected = inside + len(range(0, kept.size, spec.n_cycles)) - len(bounds)
    # the press phase the trials are checked against: presses found at half the cutting level, so that weaker
    # presses the cut passed over are counted as missed, not as absent
    phase = [int(low[k]) + 1 for start, _ in _runs(a, act.level(PHASE_FRACTION), act.level(PHASE_FRACTION / 2))
             if (k := int(np.searchsorted(low, start)) - 1) >= 0]
    phase = _merge_presses(np.asarray(sorted(set(phase)), dtype=np.int64), int(0.5 * period)).tolist()
    return Segmentation(bounds, index, rejected=rejected, period_s=period / rate_hz, onsets=kept.tolist(),
                        candidates=candidates,
                        presses=press_check(phase, bounds, n, pre=pre, n_cycles=spec.n_cycles, period=rig_period))


#: a trial starts at a press onset when its start (plus the margin) is within this fraction of the median press
#: interval of an onset (or 2 samples)
ONSET_TOLERANCE = 0.05


def press_check(onsets: Sequence[int], bounds: Sequence[tuple[int, int]], n: int, *, pre: int, n_cycles: int,
                period: int | None = None) -> dict[str, int]:
    """The trials checked against the file's press phase, press by press.

    ``onsets``: every press onset found (before any merging), samples; ``bounds``: the trials; ``n``: the file's
    samples; ``pre``: the margin before each onset; ``n_cycles``: presses a trial should hold; ``period``: the rig's
    press period, samples, when known (None: the presses are the onsets rigctl found).

    Without ``period`` the presses are the onsets found (rigctl's press finder: a press it did not find is not
    counted, a bump it took for one is). With it they are the rig's: one every ``period`` from the first press found
    to the last (:func:`rig_slots`), whether or not a press was found there (``absent``: none was), and an onset
    found off every slot is not a press. A press can be cut when its whole cycle (the median press interval, or
    ``period``) lies in the file after the margin. A trial is right when its start plus ``pre`` lies within
    :data:`ONSET_TOLERANCE` of the interval of a press and it holds ``n_cycles`` presses; the presses it starts are
    then cut right. Returns ``{"presses": cuttable presses, "cut": presses cut right, "missed": cuttable presses in
    no right trial, "off_onset": trials starting off every press, "wrong_count": trials holding another number of
    presses, "absent": cuttable presses of the rig with no press found at their time (0 without ``period``)}``."""
    on = np.asarray(sorted(onsets), dtype=np.int64)
    absent = np.zeros(on.size, dtype=bool)
    if period is not None and period >= 2 and on.size:
        on, found = rig_slots(on, period)
        absent = ~found
    if on.size < 2 and period is None:
        return {"presses": int(on.size), "cut": 0, "missed": int(on.size), "off_onset": len(bounds),
                "wrong_count": 0, "absent": 0}
    interval = float(period) if period is not None else float(np.median(np.diff(on)))
    tol = max(2.0, ONSET_TOLERANCE * interval)
    cuttable = (on - pre >= 0) & (on + interval <= n)
    right = np.zeros(on.size, dtype=bool)
    off_onset = wrong_count = 0
    for a, b in bounds:
        start = a + pre
        k = int(np.argmin(np.abs(on - start)))
        if abs(on[k] - start) > tol or absent[k]:
            off_onset += 1
            continue
        held = np.flatnonzero((on >= on[k]) & (on < b - tol))
        if held.size != n_cycles:
            wrong_count += 1
            continue
        right[held] = True
    cut = int((right & cuttable).sum())
    return {"presses": int(cuttable.sum()), "cut": cut, "missed": int(cuttable.sum()) - cut, "off_onset": off_onset,
            "wrong_count": wrong_count, "absent": int((absent & cuttable).sum())}


def rig_slots(onsets: np.ndarray, period: int) -> tuple[np.ndarray, np.ndarray]:
    """The rig's presses at its ``period`` (samples) among the sorted press ``onsets`` found: ``(slots, found)``,
    the sample of each press of the rig from the first press found to the last, and whether a press was found there.

    A walk from one found onset steps ``period`` both ways; a found onset within :data:`SLOT_TOLERANCE` x
    ``period`` of the next step is that press (the walk goes on from it: cycles jitter and drift), else the press
    is missing at the step's time. The walk starts from the onset whose walk finds the most presses (a bump taken
    for a press, off the rig's phase, is then no press), ties the earliest."""
    tol = SLOT_TOLERANCE * period
    best: tuple[int, np.ndarray, np.ndarray] | None = None
    for start in onsets.tolist():
        slots, found = [start], [True]
        for step in (period, -period):
            t = start
            while onsets[0] - tol <= t + step <= onsets[-1] + tol:
                t += step
                k = int(np.argmin(np.abs(onsets - t)))
                hit = abs(int(onsets[k]) - t) <= tol
                t = int(onsets[k]) if hit else t
                slots.append(t)
                found.append(hit)
        order = np.argsort(slots, kind="stable")
        got = (int(np.sum(found)), np.asarray(slots, dtype=np.int64)[order], np.asarray(found, dtype=bool)[order])
        if best is None or got[0] > best[0]:
            best = got
    assert best is not None
    return best[1], best[2]


def segment(counts: np.ndarray, rate_hz: float, spec: SegmentSpec | None, *, rig_period_s: float | None = None,
            rig_period_from: str = "--press-period-s") -> Segmentation:
    """Cut a continuous ``(n, n_channels)`` recording at ``rate_hz`` into trials by ``spec`` (module docstring);
    None: the whole recording is one trial. ``rig_period_s``: the rig's press period, s, when known (and
    ``rig_period_from``, where it was declared): cycles' presses are then counted against it (:func:`press_check`),
    else against rigctl's own press finder. Raises RecordingImportError when no cycle can be found."""
    n = counts.shape[0]
    if spec is None:
        return Segmentation([(0, n)], [0])
    if spec.method == "fixed":
        return _fixed(n, rate_hz, spec)
    if spec.method == "threshold":
        return _threshold(counts, rate_hz, spec)
    cut = _cycles(counts, rate_hz, spec, None if rig_period_s is None else int(round(rig_period_s * rate_hz)))
    if rig_period_s is not None and cut.presses is not None:
        cut.rig_period_s, cut.rig_period_from = float(rig_period_s), rig_period_from
    return cut


# ----------------------------------------------------------------------------------------------------- reporting
def _presses_cell(row: Mapping[str, Any]) -> str:
    c = row.get("presses")
    if not c:
        return "-"
    return f"{c['cut']}/{c['presses']}" + (" FLAGGED" if row.get("press_problem") else "")


def segment_table(rows: Sequence[Mapping[str, Any]]) -> str:
    """The per-file table (file, period, trials, rejected, first trial's start, presses cut press by press of the
    presses that could be: ``41/41``, or ``21/41 FLAGGED``) as aligned text lines, and a last line saying what the
    presses were counted against (the rig's period, or rigctl's press finder) when a row has presses."""
    head = ("file", "period s", "trials", "rejected", "first at s", "presses cut")
    body = [(str(r["file"]), "-" if r.get("period_s") is None else f"{r['period_s']:.2f}", str(r["trials"]),
             str(r["rejected"]), "-" if r.get("first_start_s") is None else f"{r['first_start_s']:.2f}",
             _presses_cell(r)) for r in rows]
    widths = [max(len(row[i]) for row in [head, *body]) for i in range(len(head))]
    lines = ["  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths)))
             for row in [head, *body]]
    bases = list(dict.fromkeys(str(r["presses_against"]) for r in rows if r.get("presses_against")))
    if bases:  # what "presses" means in the last column: the rig's presses, or those rigctl found
        finder = ("; give the rig's press period with --press-period-s to count against it" if FINDER in bases
                  else "")
        lines.append(f"presses cut: counted against {' / '.join(bases)}{finder}")
    return "\n".join(lines)


def outlier_warnings(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """One line per file whose trials do not follow its presses one by one (:func:`press_check`), per file whose
    trials overlap (any number of files), and per file whose period or trial count is
    at or under half, or at or over twice, the import's median (three files or more: a period exactly twice the
    median is a cycle counted as two)."""
    out = [f"{r['file']}: {r['press_problem']}: check its trials (rigctl info), give its period with "
           "cycles:N:MIN_PERIOD_S:MAX_PERIOD_S, or leave it out with --skip-bad" for r in rows if r.get("press_problem")]
    out += [f"{r['file']}: {r['overlapping']} trials run into the next one ({r['shared_samples']} samples in two "
           "trials): its period is likely wrong; check its trials (rigctl info) or give its period with "
           "cycles:N:MIN_PERIOD_S:MAX_PERIOD_S" for r in rows if r.get("overlapping")]
    if len(rows) < 3:
        return out
    for key, what in (("period_s", "period"), ("trials", "trial count")):
        values = [float(r[key]) for r in rows if r.get(key) is not None]
        if len(values) < 3:
            continue
        med = float(np.median(values))
        for r in rows:
            v = r.get(key)
            if v is not None and med > 0 and not (med / OUTLIER_RATIO < float(v) < med * OUTLIER_RATIO):
                shown = f"{float(v):.2f} s" if key == "period_s" else str(v)
                median = f"{med:.2f} s" if key == "period_s" else f"{med:g}"
                out.append(f"{r['file']}: {what} {shown} is an outlier (the import's median is {median}); check "
                           "its trials (rigctl info) or give its period with cycles:N:MIN_PERIOD_S:MAX_PERIOD_S")
    return out
