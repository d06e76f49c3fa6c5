"""The one trial validator: which complete trials of a session may be used, and why the others may not.

``rigctl info``, ``encode``, ``analyze`` (through the encoder), ``export nwb`` and the GUI all take their trials from
:func:`usable_trials`, so a damaged trial is excluded everywhere with the same reason and counted in each summary.
:class:`rigctl.storage.session.Session` checks the *shape* of a trial when it is read (datasets, types, the
``n_samples`` attribute); this module adds what needs the data or the whole session:

- **sequence gaps** are counted from the ``seq`` column (uint16 frame counter, wrapping at 65,536: wire spec
  section 1), not trusted from the ``dropped_frames`` attribute; a trial whose column shows more missing frames
  than its attribute says contradicts itself and is excluded;
- **length**: the samples recorded plus the frames missing must be between half and twice the plan's
  ``round(duration_s x rate)`` (+-2): a 10-sample trial of a 2 s plan is not a 2 s trial. (The recorder captures
  exactly the planned count and the importers plan what they read, so any difference is suspect; the bounds are
  loose so that hand-made sessions whose plan only roughly says the length still pass.)
- **ADC range**: counts outside ``0 .. 2**adc_bits - 1`` (negative counts of a signed dataset included);
- **impossible attributes**: a plan duration that is not finite, <= 0 or over :data:`MAX_TRIAL_S`; a counter
  (``dropped_frames``, ``crc_errors``) above :func:`max_count` (16 per frame slot of the trial + 1024: more frames
  than the link could have carried); a sensor sample rate above :data:`MAX_RATE_HZ` (every trial excluded);
- **duplicates**: a trial whose taxels are a byte copy of an earlier trial's (trials of equal length and Adler-32
  are compared by SHA-256 of the counts; constant trials, e.g. a silent sensor, are not compared).

The reasons are one line each; :attr:`TrialReport.excluded` maps trial id -> reason.
"""

from __future__ import annotations

import functools
import hashlib
import math
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rigctl.storage.session_format import SessionError, TrialStatus, trial_group_name
from rigctl.storage.session_reader import SessionReader as Session  # checked here; session.Session calls us
from rigctl.storage.session_recording import read_rows

__all__ = ["MAX_RATE_HZ", "MAX_TRIAL_S", "TrialReport", "TrialsExcluded", "block_seq_gaps", "max_count", "seq_gaps",
           "usable_trials"]

#: no taxel sensor samples faster (1 MHz; the paper's runs at 1 kHz): a faster rate is a damaged header
MAX_RATE_HZ = 1e6
#: the longest plausible trial, s (a day; the paper's are 2-6 s)
MAX_TRIAL_S = 86_400.0


class TrialsExcluded(UserWarning):
    """Warned by the commands that use a session's trials when the validator excluded some (one line:
    :meth:`TrialReport.summary`)."""


def max_count(slots: int) -> int:
    """The largest plausible ``dropped_frames`` / ``crc_errors`` of a trial of ``slots`` frame slots."""
    return 16 * max(0, int(slots)) + 1024


def seq_gaps(seq: np.ndarray) -> int:
    """Frames missing inside a trial by its uint16 ``seq`` column (wrapping at 65,536): the sum of the jumps beyond
    one."""
    if seq.size < 2:
        return 0
    d = np.mod(np.diff(seq.astype(np.int64)), 65536)
    return int(np.sum(d[d > 1] - 1))


def block_seq_gaps(seq: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """:func:`seq_gaps` of every trial of a block stored back to back: trial ``i`` is ``seq[pos[i]:pos[i + 1]]``
    (``pos`` (n_trials + 1,) non-decreasing, from 0 to ``seq.size``); (n_trials,) int64. Only the jumps are
    gathered (a recording has few): a block of a million rows costs one difference and one comparison."""
    pos = np.asarray(pos, dtype=np.int64)
    gaps = np.zeros(max(pos.size - 1, 0), dtype=np.int64)
    # uint16 differences wrap at 65,536 by themselves
    d = np.diff(seq) if seq.dtype == np.uint16 else np.mod(np.diff(seq.astype(np.int64)), 65536)
    k = np.flatnonzero(d > 1)  # a jump between samples k and k + 1
    if k.size == 0 or gaps.size == 0:
        return gaps
    trial = np.searchsorted(pos, k, side="right") - 1  # the trial holding sample k ...
    inside = (trial >= 0) & (trial < gaps.size)
    inside[inside] &= k[inside] + 1 < pos[trial[inside] + 1]  # ... and sample k + 1 (not the next trial's first)
    np.add.at(gaps, trial[inside], d[k[inside]].astype(np.int64) - 1)
    return gaps


@dataclass
class TrialReport:
    """What :func:`usable_trials` found.

    ids : usable complete trials, plan order. excluded : trial id -> one-line reason (complete trials only).
    dropped_frames : usable trial id -> frames missing by its ``seq`` column (or its attribute, if larger).
    """

    ids: list[int] = field(default_factory=list)
    excluded: dict[int, str] = field(default_factory=dict)
    dropped_frames: dict[int, int] = field(default_factory=dict)

    def summary(self) -> str:
        """One line: how many complete trials are usable and which were excluded (first three reasons)."""
        n = len(self.ids) + len(self.excluded)
        if not self.excluded:
            return f"{len(self.ids)} of {n} complete trials usable"
        shown = "; ".join(f"trial {t}: {why}" for t, why in list(self.excluded.items())[:3])
        more = f"; +{len(self.excluded) - 3} more" if len(self.excluded) > 3 else ""
        return f"{len(self.ids)} of {n} complete trials usable, {len(self.excluded)} excluded ({shown}{more})"


def usable_trials(session: Session) -> TrialReport:
    """Check every complete trial of ``session`` (module docstring); the report is computed once per open
    session and cached on it."""
    cached = getattr(session, "_trial_report", None)
    if isinstance(cached, TrialReport):
        return cached
    report = TrialReport()
    rate = float(session.layout.sample_rate_hz)
    plan = {int(r["trial_id"]): r for r in session.plan}
    session_problem = None
    if not (math.isfinite(rate) and 0 < rate <= MAX_RATE_HZ):
        session_problem = f"the sensor's sample rate {rate:g} Hz is impossible (above {MAX_RATE_HZ:g} Hz)"
    copies = _Copies()
    if session_problem is not None:
        report.excluded = dict.fromkeys(session.completed_ids(), session_problem)
    elif session._flat:  # schema 4: the recording arrays, in blocks
        _check_recorded(session, session.completed_ids(), plan, rate, report)
    else:
        for tid in session.completed_ids():
            try:
                why, dropped = _check_trial(session, tid, plan[tid], rate, copies)
            except (SessionError, KeyError) as exc:
                why, dropped = _reason(exc, tid), 0
            _record(report, tid, why, dropped)
    for tid, why in report.excluded.items():
        session._problem(f"{session.path}: trial {tid} is damaged: {why}; its data are not used (excluded)")
    session._trial_report = report  # type: ignore[attr-defined]
    return report


def _reason(exc: BaseException, tid: int) -> str:
    """The part of a SessionError that says what is wrong with the trial."""
    text = str(exc.args[0]) if isinstance(exc, KeyError) and exc.args else str(exc)
    marker = f"trial {tid} is damaged: "
    if marker in text:
        text = text.split(marker, 1)[1]
    return text.replace("; its data are not used", "")


def _count(attrs: dict[str, Any], name: str) -> int:
    try:
        return int(attrs.get(name, 0))
    except (TypeError, ValueError, OverflowError):
        return -1


def _check_trial(session: Session, tid: int, row: Any, rate: float, copies: "_Copies") -> tuple[str | None, int]:
    """(reason or None, frames missing by the seq column) for one complete trial of a file with one group of
    datasets per trial (schema 1-3)."""
    why = _check_duration(row)
    if why:
        return why, 0
    attrs = session.trial_attrs(tid)  # shape checks (SessionError names the problem)
    n = int(attrs.get("n_samples", -1))
    g = session._f[trial_group_name(tid)]
    taxels = g["taxels"]
    if n < 0:
        n = int(taxels.shape[0])
    return _check_data(session, tid, float(row["duration_s"]), rate, n, seq_gaps(np.asarray(g["seq"][()])),
                       _count(attrs, "dropped_frames"), _count(attrs, "crc_errors"), lambda: np.asarray(taxels[()]),
                       copies)


def _check_duration(row: Any) -> str | None:
    duration = float(row["duration_s"])
    if not (math.isfinite(duration) and 0 < duration <= MAX_TRIAL_S):
        return f"its plan duration {duration:g} s is impossible (not in 0..{MAX_TRIAL_S:g} s)"
    return None


def _check_data(session: Session, tid: int, duration: float, rate: float, n: int, gaps: int, said: int,
                crc: int, taxels: Callable[[], np.ndarray], copies: "_Copies", in_range: bool = False,
                reload: Callable[[], np.ndarray] | None = None) -> tuple[str | None, int]:
    """(reason or None, frames missing) from a trial's plan duration (s), the sensor's rate (Hz), its sample count,
    counters, frames missing by its ``seq`` column (:func:`seq_gaps`) and taxels (read by ``taxels()`` only when the
    other checks pass; ``in_range``: known to be inside the ADC range; ``reload()`` reads them again later, default
    ``taxels``)."""
    planned = int(round(duration * rate))
    for name, value in (("dropped_frames", said), ("crc_errors", crc)):
        if value > max_count(planned + n):
            return f"its {name} attribute {value} is impossible for {planned + n} frame slots", 0
    if gaps > said:
        return (f"its seq column shows {gaps} missing frames, its dropped_frames attribute says {said}"), gaps
    if not planned / 2 - 2 <= n + gaps <= 2 * planned + 2:
        return (f"it holds {n} samples ({gaps} missing), its plan asks {duration:g} s = {planned} at "
                f"{rate:g} Hz"), gaps
    why = _check_counts(session, taxels(), tid, copies, reload or taxels, in_range)
    return why, max(gaps, said)


#: rows of the recording arrays checked at once (schema 4): 36 MB of the paper's taxels
_BLOCK_ROWS = 1 << 20


def _check_recorded(session: Session, ids: list[int], plan: dict[int, Any], rate: float,
                    report: TrialReport) -> None:
    """The checks of :func:`_check_trial` for a schema-4 file, from ``/recording/index`` and the recording arrays
    read in blocks of about :data:`_BLOCK_ROWS` rows (no group opened per trial; memory bounded by the block)."""
    from rigctl.storage.session_recording import GROUP

    copies = _Copies()
    todo: list[tuple[int, np.void]] = []
    index, n_rows = session.recording_index(), session._recorded_rows()
    for tid in ids:
        row = index.get(tid)
        why = _check_duration(plan[tid]) or session.index_problem(row, n_rows)
        if why is None and row is not None:
            todo.append((tid, row))
        else:
            report.excluded[tid] = str(why)
    rec = session._f[GROUP]
    taxels_ds = rec["taxels"]
    k = 0
    while k < len(todo):
        j, rows = k, 0
        while j < len(todo) and (j == k or rows + int(todo[j][1]["n_samples"]) <= _BLOCK_ROWS):
            rows += int(todo[j][1]["n_samples"])
            j += 1
        block = todo[k:j]
        starts = np.array([int(r["sample_start"]) for _, r in block], dtype=np.int64)
        lengths = np.array([int(r["n_samples"]) for _, r in block], dtype=np.int64)
        pos = np.concatenate([[0], np.cumsum(lengths)])
        seq = np.empty(int(pos[-1]), dtype=np.uint16)
        tax = np.empty((int(pos[-1]), taxels_ds.shape[1]), dtype=np.uint16)
        read_rows(rec["seq"], starts, lengths, seq)
        read_rows(taxels_ds, starts, lengths, tax)
        gaps = block_seq_gaps(seq, pos)
        in_range = bool(tax.size == 0 or int(tax.max()) <= session.layout.adc_max)  # uint16: never below 0
        for i, (tid, r) in enumerate(block):
            a, b = int(pos[i]), int(pos[i + 1])
            why, dropped = _check_data(session, tid, float(plan[tid]["duration_s"]), rate, b - a, int(gaps[i]),
                                       int(r["dropped_frames"]), int(r["crc_errors"]),
                                       functools.partial(_rows, tax, a, b), copies, in_range,
                                       functools.partial(_read_trial, taxels_ds, int(starts[i]), b - a))
            _record(report, tid, why, dropped)
        k = j
    order = {t: i for i, t in enumerate(ids)}  # the report in plan order, as for older files
    report.ids.sort(key=order.__getitem__)
    report.excluded = dict(sorted(report.excluded.items(), key=lambda kv: order[kv[0]]))


def _rows(arr: np.ndarray, a: int, b: int) -> np.ndarray:
    return arr[a:b]


def _read_trial(ds: Any, start: int, n: int) -> np.ndarray:
    return np.asarray(ds[start:start + n])


def _record(report: TrialReport, tid: int, why: str | None, dropped: int) -> None:
    if why:
        report.excluded[tid] = why
    else:
        report.ids.append(tid)
        report.dropped_frames[tid] = dropped


def _check_counts(session: Session, data: np.ndarray, tid: int, copies: "_Copies",
                  load: Callable[[], np.ndarray], in_range: bool = False) -> str | None:
    """ADC range and byte copies of the trial's taxel counts (``load()`` reads them again; ``in_range``: known to
    be inside the ADC range)."""
    adc_max = session.layout.adc_max
    if data.size == 0:
        return None
    if not in_range:
        lo, hi = int(data.min()), int(data.max())
        if lo < 0 or hi > adc_max:  # worded as Session.trial words it
            row = int(np.flatnonzero(((data < 0) | (data > adc_max)).any(axis=1))[0])
            return (f"taxels hold {hi if hi > adc_max else lo} (sample {row}), outside the sensor's "
                    f"{session.layout.adc_bits}-bit range 0..{adc_max}")
    earlier = copies.copy_of(tid, data, load)
    return None if earlier is None else f"its taxels are a byte copy of trial {earlier}'s"


#: rows of a trial's counts in its fingerprint (:meth:`_Copies.fingerprint`)
_PRINT_ROWS = 256


class _Copies:
    """Byte copies among the trials' taxel counts, in the order the trials are checked: every non-constant trial is
    remembered by its fingerprint (dtype, shape, Adler-32 of about :data:`_PRINT_ROWS` rows spread over the trial: a copy
    always has its original's; hashing every byte cost as much as reading them); trials equal in that are compared
    by SHA-256 of all their counts (computed only then, re-reading an earlier trial's counts if needed). A constant
    trial (a silent sensor) is no evidence of a copy."""

    @staticmethod
    def fingerprint(data: np.ndarray) -> tuple[Any, ...]:
        """(dtype, shape, Adler-32 of every ``len // _PRINT_ROWS``-th row and the last): ``(n, ch)`` counts."""
        step = max(1, data.shape[0] // _PRINT_ROWS)
        crc = zlib.adler32(np.ascontiguousarray(data[::step]).data.cast("B"))
        return data.dtype.str, data.shape, zlib.adler32(np.ascontiguousarray(data[-1]).data.cast("B"), crc)

    def __init__(self) -> None:
        self._seen: dict[tuple[Any, ...], list[list[Any]]] = {}  # key -> [[tid, sha256 or None, load], ...]

    @staticmethod
    def _sha(data: np.ndarray) -> bytes:
        return hashlib.sha256(np.ascontiguousarray(data).data.cast("B")).digest()

    def copy_of(self, tid: int, data: np.ndarray, load: Callable[[], np.ndarray]) -> int | None:
        """The earlier trial whose counts ``data`` copies, or None (then ``tid`` is remembered; ``load()`` reads its
        counts again)."""
        data = np.ascontiguousarray(data)
        key = self.fingerprint(data)
        same = self._seen.setdefault(key, [])
        if same:
            if int(data.min()) == int(data.max()):
                return None
            mine = self._sha(data)
            for entry in same:
                if entry[1] is None:
                    entry[1] = self._sha(entry[2]())
                if entry[1] == mine:
                    return int(entry[0])
            same.append([tid, mine, load])
        else:
            same.append([tid, None, load])
        return None


def status_of(session: Session, tid: int) -> str:
    """A trial's status for listings: the plan's (``complete`` / ``pending`` / ``failed``), or ``excluded`` for a
    complete trial :func:`usable_trials` refused."""
    row = session.plan[session.plan["trial_id"] == tid]
    status = TrialStatus(int(row["status"][0])).name.lower() if row.size else "unknown"
    if status == "complete" and tid in usable_trials(session).excluded:
        return "excluded"
    return status
