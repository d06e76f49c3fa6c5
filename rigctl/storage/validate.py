"""The one trial validator: which complete trials of a session may be used, and why the others may not.

``rigctl info``, ``encode``, ``analyze`` (through the encoder), ``export nwb``, the replay rig and the GUI all take
their trials from :func:`usable_trials`, so a damaged trial is excluded everywhere with the same reason and counted
in each summary, and a damaged trial never takes the others down. Checked, per complete trial, in this order (the
first problem found is the reason):

- **the plan**: a duration that is not finite, <= 0 or over :data:`MAX_TRIAL_S`;
- **where its data are** (schema 4): its ``/recording/index`` row missing, listed more than once (which rows are
  its is ambiguous), or pointing outside the recording arrays (samples or traces);
- **declared sizes**, against the file's real size before anything is read: a trial declaring more samples than
  the file can hold (a dataset declared (2**34, 18) with nothing written) is excluded, never allocated;
- **its group**: it must open; ``n_samples``, ``dropped_frames``, ``crc_errors`` must be counts agreeing with the
  data (schema 4, 5: with the index); ``taxels`` must be ``(n, channels)`` integers (schema 4: the view, the one
  the documented plain-h5py reading uses; the other views are not opened: rigctl reads the recording arrays; schema
  5 has no views). Schema 1-3: every dataset's shape and type (:meth:`Session.trial_attrs`);
- **counters**: ``dropped_frames``, ``crc_errors`` above :func:`max_count` (16 per frame slot of the trial + 1024:
  more frames than the link could have carried);
- **sequence gaps** are counted from the ``seq`` column (uint16 frame counter, wrapping at 65,536: wire spec
  section 1), not trusted from the ``dropped_frames`` attribute; a trial whose column shows more missing frames
  than its attribute says contradicts itself and is excluded;
- **length**: the samples recorded plus the frames missing must be between half and twice the plan's
  ``round(duration_s x rate)`` (+-2): a 10-sample trial of a 2 s plan is not a 2 s trial. (The recorder captures
  exactly the planned count and the importers plan what they read, so any difference is suspect; the bounds are
  loose so that hand-made sessions whose plan only roughly says the length still pass.) A trial encoded on the
  board (the handheld rig's ``--onboard-encoder``: no taxel frames, marked ``encoded_on_board`` with a whole
  ``onboard`` record, :mod:`rigctl.storage.onboard_group`) is measured by the samples the board encoded; marked
  with a record that is not whole, it is excluded with that reason; 0 frames without the mark stay 0 frames;
- **ADC range**: counts outside ``0 .. 2**adc_bits - 1`` (negative counts of a signed dataset included);
- **duplicates**: a trial whose taxels are a byte copy of an earlier trial's (trials of equal length and Adler-32
  are compared by SHA-256 of the counts; constant trials, e.g. a silent sensor, are not compared);
- **finite readings**: NaN or inf in the force or speed trace or their times: excluded (the reason ends with
  :data:`KEEP_HINT`) unless the caller keeps them (``keep_nonfinite``, the commands' ``--keep-nonfinite``), then
  usable and listed in :attr:`TrialReport.nonfinite`.

A sensor sample rate above :data:`MAX_RATE_HZ`, or recording arrays of another type or shape than the documented
ones, excludes every trial.

Schema 4 files written by this rigctl hold the trial facts (:mod:`rigctl.storage.trial_facts`): while the file is
sealed (nobody wrote to it after rigctl's last commit), a trial with facts is judged on them (sequence gaps, ADC
range, byte copies, non-finite readings) and its group is not opened; a trial whose facts show counts outside the
ADC range is read, for the reason. The verdicts and reasons are those of reading the samples; an edited, copied or
older file is read as before.

The reasons are one line each; :attr:`TrialReport.excluded` maps trial id -> reason.
"""

from __future__ import annotations

import functools
import math
import os
import pickle
import subprocess
import sys
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import h5py
import numpy as np

from rigctl.core.buffers import zeroed
from rigctl.core.progress import ProgressCallback, Stage
from rigctl.core.trial import repeated_samples
from rigctl.storage.onboard_group import onboard_samples
from rigctl.storage.outputs import size_text
from rigctl.storage.session_format import SessionError, TrialStatus, trial_group_name
from rigctl.storage.session_reader import (
    SessionReader as Session,  # checked here; session.Session calls us
    TaxelBlock,
    as_count,
)
from rigctl.storage.session_recording import GROUP
from rigctl.storage.trial_blocks import Block, Entry, Sums, block_seq_gaps, block_sums, read_entries
from rigctl.storage.trial_facts import (
    TRACE_NAMES as _TRACE_NAMES,
    aligned,
    facts_nonfinite_text,
    nonfinite_text,
    seq_gaps,
    sha256,
    taxels_print,
)
from rigctl.storage.trial_seal import describes, foreign_problem, plan_digest, read_seal

__all__ = ["BESIDE_BYTES", "KEEP_HINT", "MAX_RATE_HZ", "MAX_TRIAL_S", "Beside", "KeptTaxels", "TrialReport", "TrialsExcluded",
           "block_seq_gaps", "check_beside", "length_bounds", "max_count", "precheck", "seq_gaps", "usable_trials"]

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


@dataclass
class TrialReport:
    """What :func:`usable_trials` found.

    ids : usable complete trials, plan order. excluded : trial id -> one-line reason (complete trials only).
    dropped_frames : usable trial id -> frames missing by its ``seq`` column (or its attribute, if larger).
    nonfinite : trial id -> its non-finite readings in words (NaN / inf in a force or speed trace or their times):
        excluded trials unless ``keep_nonfinite``, then usable and listed here.
    taxel_extremes : trial id -> ``(2, n_channels)`` uint16: each taxel's minimum (row 0) and maximum (row 1) ADC
        count over the trial's samples, as the check read them (schema 4, a trial with samples: computed beside the
        checksums from the same read, so a command that needs the session's per-taxel range - the encoder's
        normalisation - need not read every sample again); absent for older files' trials.
    """

    ids: list[int] = field(default_factory=list)
    excluded: dict[int, str] = field(default_factory=dict)
    dropped_frames: dict[int, int] = field(default_factory=dict)
    nonfinite: dict[int, str] = field(default_factory=dict)
    taxel_extremes: dict[int, np.ndarray] = field(default_factory=dict)
    #: usable trial id -> its repeated samples (rows identical on every taxel to the one before: a held reading),
    #: recounted from the counts read, never taken from a stored attribute; absent: 0
    repeated_samples: dict[int, int] = field(default_factory=dict)

    def summary(self) -> str:
        """One line: how many complete trials are usable and which were excluded (first three reasons)."""
        n = len(self.ids) + len(self.excluded)
        kept = (f"; {len(self.nonfinite)} kept with non-finite readings (--keep-nonfinite)"
                if self.nonfinite and set(self.nonfinite) & set(self.ids) else "")
        if not self.excluded:
            return f"{len(self.ids)} of {n} complete trials usable{kept}"
        shown = "; ".join(f"trial {t}: {why}" for t, why in list(self.excluded.items())[:3])
        more = f"; +{len(self.excluded) - 3} more" if len(self.excluded) > 3 else ""
        return (f"{len(self.ids)} of {n} complete trials usable, {len(self.excluded)} excluded ({shown}{more})"
                f"{kept}")


class KeptTaxels:
    """The taxels of chosen trials as :func:`usable_trials`' check read them, kept for the caller in the blocks it
    will use them in (``groups``: lists of trial ids, each a block as :meth:`SessionReader.read_taxels` of that list
    returns it). A trial is kept only once its checks pass (its counts met the checksum sealed with them, where the
    file holds one); each is copied once, from the check's block into its group's rows (one array a group, made up
    front and filled as the check goes: no copy per trial that a block would copy again). Schema 4 only (an older
    file's trials are never kept). Memory: the groups' counts, until :meth:`block` hands them over."""

    def __init__(self, session: Session, groups: Iterable[Sequence[int]]) -> None:
        self._groups: dict[tuple[int, ...], tuple[np.ndarray, np.ndarray, list[bool]]] = {}
        self._where: dict[int, tuple[tuple[int, ...], int]] = {}
        index = session.recording_index()
        n_ch = session.layout.n_channels
        for group in (tuple(int(t) for t in g) for g in groups):
            if not group or group in self._groups or not all(t in index and t not in self._where for t in group):
                continue
            starts = np.concatenate([[0], np.cumsum([int(index[t]["n_samples"]) for t in group])]).astype(np.int64)
            self._groups[group] = (zeroed((int(starts[-1]), n_ch), np.uint16), starts, [False] * len(group))
            self._where.update((t, (group, i)) for i, t in enumerate(group))

    def take(self, tid: int, taxels: np.ndarray) -> None:
        """Keep trial ``tid``'s ``(n, n_channels)`` counts if it is wanted (called by the check as it passes it)."""
        where = self._where.get(int(tid))
        if where is None:
            return
        data, starts, have = self._groups[where[0]]
        a, b = int(starts[where[1]]), int(starts[where[1] + 1])
        if taxels.shape == (b - a, data.shape[1]):
            data[a:b] = taxels
            have[where[1]] = True

    def __len__(self) -> int:
        """Trials kept so far."""
        return sum(sum(have) for _, _, have in self._groups.values())

    def block(self, session: Session, ids: Sequence[int], *, traces: bool = False) -> TaxelBlock | None:
        """:meth:`SessionReader.read_taxels` of ``ids`` (a group given, every trial of it kept) from the kept counts,
        which it hands over (frees), the lost frames and speed traces (``traces``: read here) from the file; None
        otherwise (the caller reads them)."""
        group = tuple(int(t) for t in ids)
        kept = self._groups.get(group)
        if kept is None or not all(kept[2]):
            return None
        data, starts, _ = self._groups.pop(group)
        rows, _ = session.index_rows(group)
        speed = [(t[2], t[3]) for t in session.read_traces(group)] if traces else None
        return TaxelBlock(data, starts, rows["dropped_frames"].astype(np.int64), rows["n_speed"] > 0, speed)


#: how an excluded trial's non-finite readings end their reason (the option that keeps them)
KEEP_HINT = " (--keep-nonfinite keeps it)"


def usable_trials(session: Session, *, keep_nonfinite: bool = False,
                  progress: ProgressCallback | None = None, kept: KeptTaxels | None = None) -> TrialReport:
    """Check every complete trial of ``session`` (module docstring); computed once per open session (the report
    for either ``keep_nonfinite`` is derived from one pass) and cached on it.

    keep_nonfinite : trials whose force or speed traces hold NaN or inf are usable (listed in
        :attr:`TrialReport.nonfinite`) instead of excluded.
    progress : ``rigctl.core.progress`` callback: stage ``"checking trials"`` (trials).
    kept : where this check's read hands the taxels of the trials it wants once they pass (:class:`KeptTaxels`: a
        caller that uses those counts next, e.g. the encoder's force fit, need not read them again). Only a check
        that reads them hands any: a schema-4 session not yet checked on this open file (a report already cached,
        or an older schema, hands none; the caller then reads them itself).
    """
    key = "kept" if keep_nonfinite else "default"
    cached = session.trial_reports.get(key)
    if isinstance(cached, TrialReport):
        return cached
    full = session.trial_reports.get("kept")
    if not isinstance(full, TrialReport):
        full = _check_session(session, progress, kept)
        session.trial_reports["kept"] = full
    report = full
    if not keep_nonfinite and full.nonfinite:
        order = {t: i for i, t in enumerate(session.plan["trial_id"].tolist())}
        excluded = dict(full.excluded)
        excluded.update({t: f"non-finite readings: {why}{KEEP_HINT}" for t, why in full.nonfinite.items()})
        report = TrialReport(ids=[t for t in full.ids if t not in full.nonfinite],
                             excluded=dict(sorted(excluded.items(), key=lambda kv: order.get(kv[0], 0))),
                             dropped_frames={t: d for t, d in full.dropped_frames.items()
                                             if t not in full.nonfinite},
                             nonfinite=dict(full.nonfinite), taxel_extremes=full.taxel_extremes,
                             repeated_samples={t: n for t, n in full.repeated_samples.items()
                                               if t not in full.nonfinite})
    session.trial_reports[key] = report
    for tid, why in report.excluded.items():  # one line per trial, each command the same
        session._problem(f"{session.path}: trial {tid} is damaged: {why}; its data are not used (excluded)")
    if keep_nonfinite:
        for tid, why in full.nonfinite.items():
            session._problem(f"{session.path}: trial {tid} holds non-finite readings ({why}); kept")
    return report


def precheck(session: Session) -> list[int]:
    """The complete trials that pass every check made without reading their data (schema 4: the plan, the index,
    declared sizes, counters, the group; older files: all of :func:`usable_trials`), plan order: what an estimate of
    an output's size may count (``rigctl export nwb``)."""
    if not session._flat:
        return usable_trials(session, keep_nonfinite=True).ids
    ids = session.completed_ids()
    rate = float(session.layout.sample_rate_hz)
    if not (math.isfinite(rate) and 0 < rate <= MAX_RATE_HZ) or _recording_problem(session) is not None:
        return []
    plan = {int(r["trial_id"]): r for r in session.plan}
    return [t for t, _ in _precheck_recorded(session, ids, plan, rate, TrialReport(), Stage(None, "", len(ids)))[0]]


#: taxel bytes of the trials passing :func:`precheck` above which :func:`check_beside` checks in a process of its own
BESIDE_BYTES = 256 << 20


class Beside:
    """:func:`usable_trials`' full report of a session computed in a process of its own while the caller works on
    the trials that pass :func:`precheck` (``guess``: the usable ones unless reading the data excludes some, which
    the caller finds out after :meth:`adopt` and then redoes its work with the report's trials). The report is the
    one this process would compute (the same function on the same file, this interpreter, rigctl and ``sys.path``;
    a plain ``python -c``, not multiprocessing, which would run the caller's main script again in the child); should
    the process fail, :func:`usable_trials` computes it here as usual (and says the error)."""

    def __init__(self, path: str | os.PathLike[str], guess: list[int]) -> None:
        self.guess = guess
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p))
        self._proc: subprocess.Popen[bytes] | None = subprocess.Popen(
            [sys.executable, "-c", "import sys; from rigctl.storage.validate import _report_main; "
                                   "_report_main(sys.argv[1])", os.fspath(path)],
            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env)

    def adopt(self, session: Session) -> None:
        """Wait for the report and cache it on ``session`` (:func:`usable_trials` returns it); idempotent."""
        proc = self._proc
        if proc is None:
            return
        try:
            assert proc.stdout is not None
            data = proc.stdout.read()
            full = pickle.loads(data) if proc.wait() == 0 and data else None
        finally:
            self.close()
        if isinstance(full, TrialReport):
            session.trial_reports.setdefault("kept", full)

    def close(self) -> None:
        """End the checking process (also for a caller that fails or is interrupted before :meth:`adopt`)."""
        proc, self._proc = self._proc, None
        if proc is not None:
            if proc.poll() is None:
                proc.kill()
            proc.wait()
            if proc.stdout is not None:
                proc.stdout.close()


def _report_main(path: str) -> None:
    """The checking process (:class:`Beside`): the report pickled to stdout."""
    with Session(path) as s:  # the reader open_session's Session is (this module is below the facade)
        report = _check_session(s, None)
    sys.stdout.buffer.write(pickle.dumps(report, protocol=pickle.HIGHEST_PROTOCOL))
    sys.stdout.flush()


def check_beside(session: Session, path: str | os.PathLike[str]) -> Beside | None:
    """:class:`Beside` for a large schema-4 session (the trials passing :func:`precheck` hold more than
    :data:`BESIDE_BYTES` of taxels) not yet checked in this process; None otherwise (the caller then calls
    :func:`usable_trials` as usual: a small session is checked sooner here than a process starts)."""
    if not session._flat or session.trial_reports.get("kept") is not None:
        return None
    guess = precheck(session)
    rows, _ = session.index_rows(guess)
    if int(rows["n_samples"].sum()) * session.layout.n_channels * 2 <= BESIDE_BYTES:
        return None
    return Beside(path, guess)


def _check_session(session: Session, progress: ProgressCallback | None, kept: KeptTaxels | None = None
                   ) -> TrialReport:
    """The report with trials of non-finite readings usable (and listed); ``kept`` as :func:`usable_trials`'."""
    report = TrialReport()
    rate = float(session.layout.sample_rate_hz)
    plan = {int(r["trial_id"]): r for r in session.plan}
    ids = session.completed_ids()
    stage = Stage(progress, "checking trials", len(ids))
    session_problem = None
    if not (math.isfinite(rate) and 0 < rate <= MAX_RATE_HZ):
        session_problem = f"the sensor's sample rate {rate:g} Hz is impossible (above {MAX_RATE_HZ:g} Hz)"
    elif session._flat:
        session_problem = _recording_problem(session)
    if session_problem is not None:
        report.excluded = dict.fromkeys(ids, session_problem)
    elif session._flat:  # schema 4: the recording arrays, in blocks
        _check_recorded(session, ids, plan, rate, report, stage, kept)
    else:
        copies = _Copies()
        for k, tid in enumerate(ids):
            try:
                why, dropped, bad, held = _check_trial(session, tid, plan[tid], rate, copies)
            except (SessionError, KeyError) as exc:
                why, dropped, bad, held = _reason(exc, tid), 0, None, 0
            _record(report, tid, why, dropped, bad)
            if why is None and held:
                report.repeated_samples[tid] = held
            if k % 64 == 63:
                stage.advance(64)
    stage.advance(len(ids) - stage.done)
    return report


def _recording_problem(session: Session) -> str | None:
    """Schema 4: what makes every trial unusable in the recording arrays themselves (a type or shape other than
    the documented one), or None."""
    from rigctl.storage.session_recording import STORED_DTYPES
    from rigctl.storage.trial_seal import SEAL, foreign_problem, root_problem

    f = session._f
    rec = f[GROUP]
    for parent, name, where in ((f, "plan", "/plan"), (f, GROUP, f"/{GROUP}"),
                                *((rec, n, f"/{GROUP}/{n}") for n in (*STORED_DTYPES, "index", "facts", SEAL))):
        why = foreign_problem(parent, name, where)  # data of another file are not the session's (issue 77 item 6)
        if why:
            return why
    why = root_problem(f)
    if why:
        return why
    for name, dt in STORED_DTYPES.items():
        ds = rec.get(name)
        if not isinstance(ds, h5py.Dataset):
            return f"/recording/{name} is missing or not a dataset"
        rows = ds.shape[0] if ds.ndim else 0
        shape = (rows, session.layout.n_channels) if name == "taxels" else (rows,)
        if ds.shape != shape or ds.dtype.kind != dt.kind or ds.dtype.itemsize != dt.itemsize:
            return f"/recording/{name} is {ds.dtype} {ds.shape}, not the documented {dt} {shape}"
    return None


def _reason(exc: BaseException, tid: int) -> str:
    """The part of a SessionError that says what is wrong with the trial."""
    text = str(exc.args[0]) if isinstance(exc, KeyError) and exc.args else str(exc)
    marker = f"trial {tid} is damaged: "
    if marker in text:
        text = text.split(marker, 1)[1]
    return text.replace("; its data are not used", "")


def _count(attrs: dict[str, Any], name: str) -> int:
    v = as_count(attrs.get(name, 0))
    return -1 if v is None else v


def _check_trial(session: Session, tid: int, row: Any, rate: float, copies: "_Copies"
                 ) -> tuple[str | None, int, str | None, int]:
    """(reason or None, frames missing by the seq column, non-finite readings or None, repeated samples recounted)
    for one complete trial of a file with one group of datasets per trial (schema 1-3)."""
    why = _check_duration(row)
    if why:
        return why, 0, None, 0
    for name in ("taxels", "seq", "flags", "host_time_s", *_TRACE_NAMES):  # data of another file: not the trial's
        foreign = foreign_problem(session._f[trial_group_name(tid)], name, f"{trial_group_name(tid)}/{name}")
        if foreign:
            return foreign, 0, None, 0
    attrs = session.trial_attrs(tid)  # shape checks (SessionError names the problem)
    g = session._f[trial_group_name(tid)]
    taxels = g["taxels"]
    n = int(taxels.shape[0])
    why = _too_long(float(row["duration_s"]), rate, n) or _too_big(session, taxels, n)
    if why:
        return why, 0, None, 0
    def load() -> np.ndarray:
        return np.asarray(taxels[()])

    n, why = _encoded_samples(session, tid, n)
    if why:
        return why, 0, None, 0
    why, dropped = _check_data(float(row["duration_s"]), rate, n, seq_gaps(np.asarray(g["seq"][()])),
                               _count(attrs, "dropped_frames"), _count(attrs, "crc_errors"),
                               lambda: _check_counts(session, load(), tid, copies, load))
    bad, held = None, 0
    if why is None:
        bad = _nonfinite_text({name: np.asarray(g[name][()]) for name in _TRACE_NAMES})
        held = repeated_samples(load())
    return why, dropped, bad, held


def _check_duration(row: Any) -> str | None:
    duration = float(row["duration_s"])
    if not (math.isfinite(duration) and 0 < duration <= MAX_TRIAL_S):
        return f"its plan duration {duration:g} s is impossible (not in 0..{MAX_TRIAL_S:g} s)"
    return None


def length_bounds(duration_s: float, rate_hz: float) -> tuple[float, float]:
    """The length check's bounds, samples (recorded + missing) of a trial planned ``duration_s`` s at ``rate_hz``:
    half and twice the planned count, +-2 (module docstring). A recorder that can tell a trial will not pass (the
    handheld rig: an operator far slower or faster than the cue) cues it again instead of recording it."""
    planned = int(round(duration_s * rate_hz))
    return planned / 2 - 2, 2 * planned + 2


def _too_long(duration: float, rate: float, n: int) -> str | None:
    """The length check's upper bound, made before any data is read (frames missing only make it longer)."""
    planned = int(round(duration * rate))
    if n > length_bounds(duration, rate)[1]:
        return f"it holds {n} samples, its plan asks {duration:g} s = {planned} at {rate:g} Hz"
    return None


#: the most a compressed dataset's data can shrink (deflate's limit is 1,032:1), for :func:`_too_big`
_MAX_COMPRESSION = 1100


def _capacity_rows(session: Session, ds: Any) -> int:
    """The most rows of ``ds`` the file can hold: its real size over a row's bytes (x :data:`_MAX_COMPRESSION`
    for a compressed dataset), + 1 MiB of slack."""
    row_bytes = max(1, int(np.prod(ds.shape[1:], dtype=np.int64)) * ds.dtype.itemsize)
    size = session.path.stat().st_size
    return int((size * (_MAX_COMPRESSION if ds.compression else 1) + (1 << 20)) // row_bytes)


def _too_big(session: Session, ds: Any, n: int) -> str | None:
    """A trial declaring more rows of ``ds`` than the file can hold (a dataset declared large with no data
    written), checked against the file's real size before anything is read."""
    if n > _capacity_rows(session, ds):
        row_bytes = int(np.prod(ds.shape[1:], dtype=np.int64)) * ds.dtype.itemsize
        size = session.path.stat().st_size
        return (f"it declares {n} samples ({size_text(n * row_bytes)} of taxels), more than this "
                f"{size_text(size)} file holds (declared, never written)")
    return None


def _check_data(duration: float, rate: float, n: int, gaps: int, said: int, crc: int,
                counts: Callable[[], str | None]) -> tuple[str | None, int]:
    """(reason or None, frames missing) from a trial's plan duration (s), the sensor's rate (Hz), its sample count,
    counters, frames missing by its ``seq`` column (:func:`seq_gaps`) and ``counts()``, the check of its taxel
    counts (:func:`_check_counts`, :func:`_check_known_counts`), made only when the other checks pass."""
    planned = int(round(duration * rate))
    why = _count_problem(said, crc, planned + n)
    if why:
        return why, 0
    if gaps > said:
        return (f"its seq column shows {gaps} missing frames, its dropped_frames attribute says {said}"), gaps
    lo, hi = length_bounds(duration, rate)
    if not lo <= n + gaps <= hi:
        return (f"it holds {n} samples ({gaps} missing), its plan asks {duration:g} s = {planned} at "
                f"{rate:g} Hz"), gaps
    return counts(), max(gaps, said)


def _encoded_samples(session: Session, tid: int, n: int) -> tuple[int, str | None]:
    """A trial's length for the length check: its ``n`` taxel frames, or, for a trial with none that is marked
    encoded on the board with a whole record (:func:`rigctl.storage.onboard_group.onboard_samples`), the samples the
    board encoded; with a reason when it is marked but its record is not whole. Only a trial of 0 frames has its
    group opened for this."""
    if n != 0:
        return n, None
    try:
        group = session._f[trial_group_name(tid)]
    except (KeyError, OSError):
        return n, None
    samples, why = onboard_samples(group)
    return (n, why) if samples is None else (samples, None)


def _count_problem(said: int, crc: int, slots: int) -> str | None:
    for name, value in (("dropped_frames", said), ("crc_errors", crc)):
        if value < 0:
            return f"its {name} attribute is not a count"
        if value > max_count(slots):
            return f"its {name} attribute {value} is impossible for {slots} frame slots"
    return None


def _nonfinite_text(traces: dict[str, np.ndarray]) -> str | None:
    """``"2 NaN in force_g, 1 inf in speed_mm_s"`` for the traces holding non-finite values, or None."""
    counts = {}
    for name, values in traces.items():
        if values.dtype.kind == "f":
            counts[f"NaN in {name}"] = int(np.count_nonzero(np.isnan(values)))
            counts[f"inf in {name}"] = int(np.count_nonzero(np.isinf(values)))
    return nonfinite_text(counts)


#: rows of the recording arrays checked at once (schema 4): 36 MB of the paper's taxels
_BLOCK_ROWS = 1 << 20


def _precheck_recorded(session: Session, ids: list[int], plan: dict[int, Any], rate: float, report: TrialReport,
                       stage: Stage) -> tuple[list[tuple[int, np.void]], np.ndarray, np.ndarray]:
    """The checks of a schema-4 file that read no data (duration, the index row, counters, length upper bound,
    declared size, the group); the trials passing them, with their index rows, their facts rows
    (:data:`rigctl.storage.trial_facts.FACTS_DTYPE`) and whether those are trusted. The checks on numbers run on all
    trials at once; only a trial one of them refuses is looked at alone (for its reason). A trial with trusted facts
    (:meth:`Session.trusted_facts`: the file is as rigctl's writer left it, which made its group from the index row)
    has its group as written: not opened."""
    rows, have = session.index_rows(ids)
    facts, trusted = aligned(session.trusted_facts(), ids, rows)
    trusted &= have
    dups = session.index_duplicates()
    n_rows, (force_rows, speed_rows) = session._array_rows()
    taxels_ds = session._f[GROUP]["taxels"]
    duration = np.array([float(plan[t]["duration_s"]) for t in ids], dtype=np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        planned = np.where(np.isfinite(duration), np.round(duration * rate), 0).astype(np.int64)
        n = rows["n_samples"]
        slots = np.maximum(planned + n, 0)
        ok = (np.isfinite(duration) & (duration > 0) & (duration <= MAX_TRIAL_S) & have
              & ~np.isin(np.asarray(ids, dtype=np.int64), list(dups)))
        for prefix, total in (("sample", n_rows), ("force", force_rows), ("speed", speed_rows)):
            start, count = rows[f"{prefix}_start"], rows["n_samples" if prefix == "sample" else f"n_{prefix}"]
            ok &= (start >= 0) & (count >= 0) & (start <= total - count)
        for name in ("dropped_frames", "crc_errors"):
            ok &= (rows[name] >= 0) & (rows[name] <= 16 * slots + 1024)
        ok &= n <= 2 * planned + 2
        ok &= n <= _capacity_rows(session, taxels_ds)
    todo: list[tuple[int, np.void]] = []
    passed: list[int] = []
    for i, tid in enumerate(ids):
        row = rows[i]
        if ok[i]:
            why = None if trusted[i] else session.flat_group_problem(tid, row)
        else:  # the same checks one by one, for the reason
            why = _check_duration(plan[tid])
            if why is None and tid in dups:
                why = f"/recording/index lists it {dups[tid]} times"
            why = why or session.index_problem(row if have[i] else None, n_rows, (force_rows, speed_rows))
            if why is None:
                m = int(row["n_samples"])
                why = (_count_problem(int(row["dropped_frames"]), int(row["crc_errors"]), int(slots[i]))
                       or _too_long(float(duration[i]), rate, m) or _too_big(session, taxels_ds, m)
                       or session.flat_group_problem(tid, row))
        if why is None:
            todo.append((tid, row))
            passed.append(i)
        else:
            report.excluded[tid] = str(why)
        if i % 256 == 255:
            stage.advance(256)
    stage.advance(len(ids) - stage.done)
    return todo, facts[passed], trusted[passed]


def _check_recorded(session: Session, ids: list[int], plan: dict[int, Any], rate: float,
                    report: TrialReport, stage: Stage, kept: KeptTaxels | None = None) -> None:
    """The checks of :func:`_check_trial` for a schema-4 file, from ``/recording/index``, each trial's group
    (:meth:`Session.flat_group_problem`) and the recording arrays read in blocks of about :data:`_BLOCK_ROWS` rows
    (memory bounded by two blocks: one hashed while the next is read). A trial with trusted facts
    (:meth:`Session.trusted_facts`) is judged on them instead of its samples, unless they show counts outside the ADC
    range (read then, for the reason's sample). ``kept``: as :func:`usable_trials`'."""
    copies = _Copies()
    todo, facts, trusted = _precheck_recorded(session, ids, plan, rate, report,
                                              Stage(stage.callback, "checking trial groups", len(ids)))
    stage.advance(len(ids) - len(todo))
    # integrity from the content (issue 52): every trial's samples are read and, where the seal holds facts of it,
    # its taxels compared with the checksum stored with them; a trial edited since (its modification time put back)
    # or whose stored chunk cannot be read is excluded by itself, named
    known = np.zeros(len(todo), dtype=bool)
    entries: list[Entry] = [(tid, r, None, False, facts[i] if trusted[i] else None) for i, (tid, r) in enumerate(todo)]
    # the seal of everything else the analysis reads (trial_seal): compared whether or not the modification time
    # still holds, as a plain edit moves it
    seals = read_seal(session._f)
    sealed = [tid in seals and describes(seals[tid], r) for tid, r in todo]
    for k, (tid, _) in enumerate(todo):  # the taxels met against the seal's checksum where no trusted facts row is
        if entries[k][4] is None and sealed[k]:
            row = np.zeros(1, dtype=facts.dtype)[0]
            row["taxels_sha256"] = seals[tid]["taxels_sha256"]
            entries[k] = (*entries[k][:4], row)
    seals = {tid: seals[tid] for k, (tid, _) in enumerate(todo) if sealed[k]}
    spans: list[tuple[int, int]] = []
    k = 0
    while k < len(todo):
        j, rows = k, 0
        while j < len(todo) and (j == k or known[j] or rows + int(todo[j][1]["n_samples"]) <= _BLOCK_ROWS):
            rows += 0 if known[j] else int(todo[j][1]["n_samples"])
            j += 1
        spans.append((k, j))
        k = j
    # two blocks in flight: a worker thread hashes block k (SHA-256 against the seal, the seq gaps, the ADC maximum:
    # hashlib and numpy release the GIL) while this thread reads block k + 1 and judges block k - 1, in order
    adc_max = session.layout.adc_max
    with ThreadPoolExecutor(1, thread_name_prefix="rigctl-validate") as pool:
        pending: tuple[Block, Future[Sums], int] | None = None
        for k, j in spans:
            blk = read_entries(session._f[GROUP], entries[k:j], sealed[k:j])
            sums = pool.submit(block_sums, blk, adc_max)
            if pending is not None:
                _judge_block(session, pending[0], pending[1].result(), plan, rate, report, copies, kept, seals)
                stage.advance(pending[2])
            pending = (blk, sums, j - k)
        if pending is not None:
            _judge_block(session, pending[0], pending[1].result(), plan, rate, report, copies, kept, seals)
            stage.advance(pending[2])
    order = {t: i for i, t in enumerate(ids)}  # the report in plan order, as for older files
    report.ids.sort(key=order.__getitem__)
    report.excluded = dict(sorted(report.excluded.items(), key=lambda kv: order[kv[0]]))


def _judge_block(session: Session, blk: Block, sums: Sums, plan: dict[int, Any], rate: float,
                 report: TrialReport, copies: "_Copies", kept: KeptTaxels | None = None,
                 seals: dict[int, np.void] | None = None) -> None:
    """:func:`_check_data` of a block's trials in order: those with facts on them, the others on their samples
    (read in :func:`read_entries`, summed in :func:`block_sums`); each usable trial's taxels handed to ``kept``."""
    taxels_ds = session._f[GROUP]["taxels"]
    n_ch = int(taxels_ds.shape[1])
    gaps, in_range, digests, extremes, repeated = sums
    tax, pos, failed = blk.tax, blk.pos, blk.failed
    i = 0  # the next trial read
    for tid, r, q, nonfinite, sealed in blk.entries:
        duration, said, crc = float(plan[tid]["duration_s"]), int(r["dropped_frames"]), int(r["crc_errors"])
        if q is not None:
            n, why = _encoded_samples(session, tid, int(r["n_samples"]))
            why, dropped = (why, 0) if why else _check_data(duration, rate, n, int(q["seq_gaps"]), said, crc,
                                                            functools.partial(_check_known_counts, tid, q, n_ch,
                                                                              copies))
            _record(report, tid, why, dropped, facts_nonfinite_text(q) if nonfinite else None)
            continue
        a, b = int(pos[i]), int(pos[i + 1])
        if i in failed:
            _record(report, tid, failed[i], 0)
            i += 1
            continue
        data, load = tax[a:b], functools.partial(_read_trial, taxels_ds, int(blk.starts[i]), b - a)
        n, why = _encoded_samples(session, tid, b - a)
        why, dropped = (why, 0) if why else _check_data(duration, rate, n, int(gaps[i]), said, crc,
                                                        functools.partial(_check_counts, session, data, tid, copies,
                                                                          load, in_range))
        changed = ("its stored taxels differ from the checksum sealed with them when they were recorded (changed "
                   "since)" if sealed is not None and digests[i] is not None
                   and digests[i] != bytes(sealed["taxels_sha256"]) else None)
        changed = changed or _seal_problem((seals or {}).get(tid), blk.sealed_arrays[i], plan[tid])
        if changed:  # excluded whatever else it holds; what reading it finds besides is said with it
            detail = why or blk.bad[i]
            why = changed + (f": {detail}" if detail else "")
        _record(report, tid, why, dropped, blk.bad[i])
        if why is None and repeated[i]:
            report.repeated_samples[tid] = int(repeated[i])
        if kept is not None and why is None:
            kept.take(tid, data)
        ext = extremes[i]
        if ext is not None:
            report.taxel_extremes[tid] = ext
        i += 1


def _seal_problem(seal: np.void | None, arrays: bytes | None, plan_row: Any) -> str | None:
    """What of a trial differs from its seal row (:mod:`rigctl.storage.trial_seal`): its other recording arrays'
    checksum (``arrays``: as read, None when it has no seal row to meet) or its plan row's labels; None."""
    if seal is None:
        return None
    if arrays is not None and arrays != bytes(seal["arrays_sha256"]):
        return ("its seq, flags, host times or force / speed traces differ from the checksum sealed with them when "
                "they were recorded (changed since)")
    if plan_digest(plan_row) != bytes(seal["plan_sha256"]):
        return ("its /plan labels (texture, speed, force, duration, ...) differ from those sealed when it was "
                "recorded (changed since)")
    return None


def _read_trial(ds: Any, start: int, n: int) -> np.ndarray:
    return np.asarray(ds[start:start + n])


def _record(report: TrialReport, tid: int, why: str | None, dropped: int, nonfinite: str | None = None) -> None:
    if why:
        report.excluded[tid] = why
    else:
        report.ids.append(tid)
        report.dropped_frames[tid] = dropped
        if nonfinite:
            report.nonfinite[tid] = nonfinite


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


def _check_known_counts(tid: int, facts: np.void, n_channels: int, copies: "_Copies") -> str | None:
    """:func:`_check_counts` of a trial's taxel counts inside the ADC range from its facts (their fingerprint,
    SHA-256 and whether they are constant)."""
    n = int(facts["n_samples"])
    if n * n_channels == 0:
        return None
    key = (np.dtype(np.uint16).str, (n, n_channels), int(facts["taxels_print"]))
    earlier = copies.copy_of_known(tid, key, bytes(facts["taxels_sha256"]),
                                   int(facts["taxels_min"]) == int(facts["taxels_max"]))
    return None if earlier is None else f"its taxels are a byte copy of trial {earlier}'s"


class _Copies:
    """Byte copies among the trials' taxel counts, in the order the trials are checked: every non-constant trial is
    remembered by its fingerprint (dtype, shape, Adler-32 of about :data:`rigctl.storage.trial_facts.PRINT_ROWS`
    rows spread over the trial: a copy always has its original's; hashing every byte cost as much as reading them);
    trials equal in that are compared by SHA-256 of all their counts (computed only then, re-reading an earlier trial's counts if needed, or
    taken from the trial facts). A constant trial (a silent sensor) is no evidence of a copy. So a trial is a copy of
    the first trial checked before it with the same type, shape and bytes, whichever way each was checked."""

    @staticmethod
    def fingerprint(data: np.ndarray) -> tuple[Any, ...]:
        """(dtype, shape, :func:`rigctl.storage.trial_facts.taxels_print`) of ``(n, ch)`` counts, ``n`` > 0."""
        return data.dtype.str, data.shape, taxels_print(data)

    def __init__(self) -> None:
        self._seen: dict[tuple[Any, ...], list[list[Any]]] = {}  # key -> [[tid, sha256 or None, load], ...]

    def copy_of(self, tid: int, data: np.ndarray, load: Callable[[], np.ndarray]) -> int | None:
        """The earlier trial whose counts ``data`` copies, or None (then ``tid`` is remembered; ``load()`` reads its
        counts again)."""
        data = np.ascontiguousarray(data)
        return self._copy_of(tid, self.fingerprint(data), None, lambda: int(data.min()) == int(data.max()),
                             lambda: sha256(data), load)

    def copy_of_known(self, tid: int, key: tuple[Any, ...], sha: bytes, constant: bool) -> int | None:
        """:meth:`copy_of` of a trial known by its fingerprint ``key``, SHA-256 and whether it is constant."""
        return self._copy_of(tid, key, sha, lambda: constant, lambda: sha, None)

    def _copy_of(self, tid: int, key: tuple[Any, ...], known: bytes | None, constant: Callable[[], bool],
                 sha: Callable[[], bytes], load: Callable[[], np.ndarray] | None) -> int | None:
        same = self._seen.setdefault(key, [])
        if same:
            if constant():
                return None
            mine = sha()
            for entry in same:
                if entry[1] is None:
                    entry[1] = sha256(entry[2]())
                if entry[1] == mine:
                    return int(entry[0])
            same.append([tid, mine, load])
        else:
            same.append([tid, known, load])
        return None


def status_of(session: Session, tid: int) -> str:
    """A trial's status for listings: the plan's (``complete`` / ``pending`` / ``failed``), or ``excluded`` for a
    complete trial :func:`usable_trials` refused."""
    row = session.plan[session.plan["trial_id"] == tid]
    status = TrialStatus(int(row["status"][0])).name.lower() if row.size else "unknown"
    if status == "complete" and tid in usable_trials(session).excluded:
        return "excluded"
    return status
