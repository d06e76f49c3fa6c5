"""Schema 4's trial facts: what the trial validator needs from a trial's samples, computed once by the writer from
the very arrays it stores, so that the validator need not read every sample of every trial again.

``/recording/facts`` holds one row per trial committed by a rigctl that writes them (:data:`FACTS_DTYPE`): where
its rows are (the index's extents, to pair them), its ``seq`` column's missing frames (:func:`seq_gaps`), the
minimum and maximum of its taxel counts, their fingerprint (:func:`taxels_print`) and SHA-256 (byte copies), and
the NaN and inf counts of its force and speed traces and their times.

The facts describe the samples only while nobody else has written to the file: a file edited afterwards (h5py in
``r+`` mode, a copy that was cut short and mended, another program) may hold other samples under the same facts.
So every commit of :class:`rigctl.storage.session_writer.SessionWriter` **seals** the file: it stores a time in the
root attribute :data:`SEAL_ATTR` and, once the commit is on disk, sets the file's modification time to exactly that
time (ns). Any later write by anyone moves the modification time, and the seal no longer holds: the readers then
trust no fact (:func:`trusted_facts`) and the validator reads the samples, as it does for files without facts. A
writer that finds the seal broken drops the facts of the trials already in the file before it adds its own (an
edit made before a resume is never hidden behind facts computed before it). A filesystem that cannot keep a
modification time to the microsecond (FAT's 2 s, some network shares) never holds a seal: always the full read
there.
"""

from __future__ import annotations

import hashlib
import os
import time
import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from rigctl.core.trial import TrialData
from rigctl.storage import session_recording
from rigctl.storage.session_recording import GROUP, TRACES

#: the facts' dataset in ``/recording``
FACTS = "facts"
#: root attribute: the modification time (ns since the epoch) the last commit gave the file
SEAL_ATTR = "facts_sealed_mtime_ns"
#: the traces whose non-finite readings are counted, in the validator's order (value, then its times)
TRACE_NAMES = tuple(name for value, times, _ in TRACES for name in (value, times))
#: one row per trial: its extents (as its ``/recording/index`` row), then what its samples hold
FACTS_DTYPE = np.dtype([
    ("trial_id", "<u4"),
    ("sample_start", "<i8"), ("n_samples", "<i8"),
    ("force_start", "<i8"), ("n_force", "<i8"),
    ("speed_start", "<i8"), ("n_speed", "<i8"),
    ("seq_gaps", "<i8"),
    ("taxels_min", "<i8"), ("taxels_max", "<i8"),
    ("taxels_print", "<u4"), ("taxels_sha256", "u1", (32,)),
    *((f"{name}_{what}", "<i8") for name in TRACE_NAMES for what in ("nan", "inf")),
])
#: the index fields a facts row repeats (a row describes the trial only if they agree)
EXTENTS = ("sample_start", "n_samples", "force_start", "n_force", "speed_start", "n_speed")
#: rows of a trial's counts in its fingerprint (:func:`taxels_print`)
PRINT_ROWS = 256


def seq_gaps(seq: np.ndarray) -> int:
    """Frames missing inside a trial by its uint16 ``seq`` column (wrapping at 65,536): the sum of the jumps beyond
    one. The steps are taken in uint16 arithmetic, which wraps at 65,536 itself (a uint16 column as it is, other
    integers cast, which keeps them modulo 65,536: ~3 us for 6,000 frames where int64 steps and their modulo took
    ~30)."""
    if seq.size < 2:
        return 0
    d = np.diff(np.asarray(seq).astype(np.uint16, copy=False))
    jumps = d[d > 1]
    return int(jumps.sum(dtype=np.int64)) - int(jumps.size)


def taxels_print(data: np.ndarray) -> int:
    """Adler-32 of every ``len // PRINT_ROWS``-th row and the last of ``(n, channels)`` counts (``n`` > 0): equal
    for byte copies, cheap to compute (hashing every byte cost as much as reading them)."""
    step = max(1, data.shape[0] // PRINT_ROWS)
    crc = zlib.adler32(np.ascontiguousarray(data[::step]).data.cast("B"))
    return zlib.adler32(np.ascontiguousarray(data[-1]).data.cast("B"), crc)


def sha256(data: np.ndarray) -> bytes:
    """SHA-256 of an array's bytes (C order)."""
    return hashlib.sha256(np.ascontiguousarray(data).data.cast("B")).digest()


def nonfinite_text(counts: dict[str, int]) -> str | None:
    """``"2 NaN in force_g, 1 inf in speed_mm_s"`` from ``"<what> in <trace>"`` -> count (:data:`TRACE_NAMES`
    order, NaN before inf), or None when all are 0."""
    parts = [f"{int(counts.get(f'{what} in {name}', 0))} {what} in {name}" for name in TRACE_NAMES
             for what in ("NaN", "inf") if counts.get(f"{what} in {name}", 0)]
    return ", ".join(parts) or None


def sample_facts(data: TrialData, n_channels: int,
                 taxel_extremes: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """What a trial's samples hold, as one :data:`FACTS_DTYPE` row (shape ``(1,)``) whose trial id and extents are
    0 (:func:`facts_of` fills them in once the trial is appended): its ``seq`` gaps, the minimum, maximum,
    fingerprint and SHA-256 of its taxel counts (zeros without samples), the NaN and inf counts of its traces; each
    array converted as :func:`rigctl.storage.session_recording.stored` converts it (the bytes on disk). Needs no
    file: a process that made the trial can compute it (the dataset generator's render workers) and hand it to
    :meth:`rigctl.storage.session_writer.SessionWriter.write_trials` with the trial.

    ``taxel_extremes``: the per-channel minimum and maximum of these very taxels (``(channels,)`` each, e.g. the
    dataset generator's calibration extremes), if the caller has them: the counts' minimum and maximum are then
    theirs instead of another pass over every count."""
    out = np.zeros(1, dtype=FACTS_DTYPE)
    tax = session_recording.stored("taxels", data.taxels, n_channels)
    if tax.size:
        if taxel_extremes is None:
            out["taxels_min"], out["taxels_max"] = int(tax.min()), int(tax.max())
        else:
            out["taxels_min"], out["taxels_max"] = int(taxel_extremes[0].min()), int(taxel_extremes[1].max())
        out["taxels_print"] = taxels_print(tax)
        out["taxels_sha256"][0] = np.frombuffer(sha256(tax), dtype=np.uint8)
    out["seq_gaps"] = seq_gaps(session_recording.stored("seq", data.seq, n_channels))
    traces = [session_recording.stored(name, getattr(data, name), n_channels) for name in TRACE_NAMES]
    # one look at all of them first (one pass over the four joined: ~7 us against ~17 for four looks)
    if not np.isfinite(np.concatenate(traces)).all():
        for name, values in zip(TRACE_NAMES, traces):
            if not np.isfinite(values).all():  # (a simulated trace is always finite: nothing to count)
                out[f"{name}_nan"] = int(np.count_nonzero(np.isnan(values)))
                out[f"{name}_inf"] = int(np.count_nonzero(np.isinf(values)))
    return out


def facts_of(rows: np.ndarray, data: Sequence[TrialData], n_channels: int,
             known: Sequence[np.ndarray | None] | None = None) -> np.ndarray:
    """The facts rows of trials just appended: ``rows`` their ``/recording/index`` rows, ``data`` the trials, each
    array converted as :func:`rigctl.storage.session_recording.stored` converts it (the bytes on disk).

    ``known``: per trial, its :func:`sample_facts` computed elsewhere from these very arrays, or None to compute them
    here. Raises ValueError when a known row's taxel fingerprint (:func:`taxels_print`, checked here: ~10 us) is not
    the trial's (facts of other samples)."""
    out = np.zeros(len(data), dtype=FACTS_DTYPE)
    for i, d in enumerate(data):
        given = known[i] if known is not None else None
        if given is None:
            out[i] = sample_facts(d, n_channels)[0]
            continue
        given = np.asarray(given, dtype=FACTS_DTYPE).reshape(-1)
        tax = session_recording.stored("taxels", d.taxels, n_channels)
        if len(given) != 1 or int(given["taxels_print"][0]) != (taxels_print(tax) if tax.size else 0):
            raise ValueError(f"the facts handed over for trial {int(rows['trial_id'][i])} are not its samples' "
                             "(trial_facts.sample_facts of the arrays written)")
        out[i] = given[0]
    for name in ("trial_id", *EXTENTS):
        out[name] = rows[name]
    return out


def append(f: h5py.File, rows: np.ndarray, data: Sequence[TrialData],
           known: Sequence[np.ndarray | None] | None = None) -> None:
    """Append the facts of trials just appended to ``/recording`` (``rows`` their index rows; ``known`` as
    :func:`facts_of`'s), making ``/recording/facts`` in a file that has none (an older schema-4 file: its earlier
    trials stay without)."""
    rec = f[GROUP]
    new = facts_of(rows, data, int(rec["taxels"].shape[1]), known)
    ds = rec.get(FACTS)
    if ds is None:
        ds = rec.create_dataset(FACTS, shape=(0,), maxshape=(None,), chunks=(session_recording.INDEX_CHUNK_ROWS,),
                                dtype=FACTS_DTYPE)
    start = int(ds.shape[0])
    ds.resize((start + len(new),))
    ds[start:] = new


def mtime_ns(path: Path) -> int | None:
    """The file's modification time, ns (None if it cannot be read)."""
    try:
        return os.stat(path).st_mtime_ns
    except OSError:
        return None


def is_sealed(attrs: Any, file_mtime_ns: int | None) -> bool:
    """True when the file's modification time is the one its last rigctl commit gave it (``attrs``: the root
    attributes, a mapping): nobody has written to it since."""
    seal = attrs.get(SEAL_ATTR)
    try:
        return file_mtime_ns is not None and seal is not None and int(seal) == int(file_mtime_ns) and int(seal) > 0
    except (TypeError, ValueError, OverflowError):
        return False


def begin_commit(f: h5py.File, file_mtime_ns: int | None) -> int | None:
    """At the start of a commit to a schema-4 file (``file_mtime_ns``: the file's modification time before it):
    drop the facts when the seal is broken (they may describe other samples than the file's) and store a new seal.
    Returns the seal to give the file once the commit is on disk (:func:`seal`); None for older schemas."""
    if not session_recording.is_flat(f):
        return None
    if not is_sealed(f.attrs, file_mtime_ns) and FACTS in f[GROUP]:
        del f[GROUP][FACTS]
    # a whole microsecond: filesystems keeping 100 ns (NTFS) or 1 us hold it too; on a nanosecond one, another
    # write gets this exact time only if the kernel's clock tick fell on that very nanosecond
    stamp = time.time_ns() // 1000 * 1000
    f.attrs[SEAL_ATTR] = np.int64(stamp)
    return stamp


def seal(path: Path, stamp: int | None) -> None:
    """Give the committed file the modification time ``stamp`` (:func:`begin_commit`); a filesystem that refuses
    leaves it unsealed (the validator then reads the samples)."""
    if stamp is None:
        return
    try:
        os.utime(path, ns=(os.stat(path).st_atime_ns, stamp))
    except OSError:
        pass


def trusted_facts(f: h5py.File, attrs: Any, file_mtime_ns: int | None) -> dict[int, np.void]:
    """Trial id -> its facts row, for a sealed schema-4 file (:func:`is_sealed`) whose ``/recording/facts`` is the
    documented table; ``{}`` otherwise. A trial listed more than once gets none (which row is its is ambiguous).
    Read errors give ``{}`` (the validator then reads the samples and names the damage)."""
    if not is_sealed(attrs, file_mtime_ns):
        return {}
    return session_recording.rows_by_trial(f, FACTS, FACTS_DTYPE)


def aligned(facts: dict[int, np.void], ids: Sequence[int], index_rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(rows, trusted)``: the facts rows of ``ids`` (:data:`FACTS_DTYPE`, zeros where a trial has none) and whether
    each describes the rows ``index_rows`` (their ``/recording/index`` rows, same order) give the trial (every
    extent equal)."""
    rows = np.zeros(len(ids), dtype=FACTS_DTYPE)
    trusted = np.zeros(len(ids), dtype=bool)
    for i, tid in enumerate(ids):
        q = facts.get(int(tid))
        if q is not None:
            rows[i], trusted[i] = q, True
    for name in EXTENTS:
        trusted &= rows[name] == index_rows[name]
    return rows, trusted


#: (the validator's words, the facts field) of each non-finite count (:func:`nonfinite_text`)
NONFINITE_FIELDS = tuple((f"{what} in {name}", f"{name}_{what.lower()}") for name in TRACE_NAMES
                         for what in ("NaN", "inf"))


def facts_nonfinite_text(row: np.void) -> str | None:
    """:func:`nonfinite_text` of a facts row."""
    return nonfinite_text({words: int(row[name]) for words, name in NONFINITE_FIELDS})
