"""The trial validator's block reads (schema 4): the trials of a block read from the recording arrays together
(their ``seq`` column, taxels and traces), and what their samples say (sequence gaps, whether the counts are inside
the ADC range, each trial's SHA-256 and per-taxel extremes), for :mod:`rigctl.storage.validate` to judge.

A block's trials are stored back to back: trial ``i`` is rows ``pos[i]:pos[i + 1]`` of the block's arrays.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from rigctl.core.normalisation import column_extremes
from rigctl.storage.session_recording import TRACES, read_rows
from rigctl.storage.trial_facts import nonfinite_text, sha256

__all__ = ["READ_ERRORS", "Block", "Entry", "Sums", "block_nonfinite", "block_seq_gaps", "block_sums", "read_block",
           "read_entries"]


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



def read_block(rec: Any, read: list[np.void], n_ch: int) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                                   list[str | None], dict[int, str]]:
    """(seq, taxels, row offsets, non-finite texts, {i: why} of the trials whose stored data cannot be read) of the
    trials ``read`` back to back: read together, or, when a damaged chunk stops that, trial by trial."""
    starts = np.array([int(r["sample_start"]) for r in read], dtype=np.int64)
    lengths = np.array([int(r["n_samples"]) for r in read], dtype=np.int64)
    pos = np.concatenate([[0], np.cumsum(lengths)])
    seq = np.zeros(int(pos[-1]), dtype=np.uint16)
    tax = np.zeros((int(pos[-1]), n_ch), dtype=np.uint16)
    try:
        read_rows(rec["seq"], starts, lengths, seq)
        read_rows(rec["taxels"], starts, lengths, tax)
        return seq, tax, pos, block_nonfinite(rec, read), {}
    except READ_ERRORS:
        pass
    failed: dict[int, str] = {}
    bad: list[str | None] = []
    for i, r in enumerate(read):
        a, b = int(pos[i]), int(pos[i + 1])
        try:
            read_rows(rec["seq"], starts[i:i + 1], lengths[i:i + 1], seq[a:b])
            read_rows(rec["taxels"], starts[i:i + 1], lengths[i:i + 1], tax[a:b])
            bad += block_nonfinite(rec, [r])
        except READ_ERRORS as exc:
            failed[i] = (f"its stored data cannot be read (a damaged chunk: {' '.join(str(exc).split())[:120]}); "
                         "the other trials are read as usual")
            bad.append(None)
    return seq, tax, pos, bad, failed


#: what h5py raises for a chunk that does not decompress or a read the file cannot give
READ_ERRORS = (OSError, RuntimeError, ValueError)


#: a trial of a block: (trial id, index row, facts row or None, whether the facts count non-finite readings, the
#: sealed facts row its taxels are checked against or None)
Entry = tuple[int, np.void, np.void | None, bool, np.void | None]


@dataclass
class Block:
    """A block of trials as read (:func:`read_entries`): the entries, and of the trials read (those without facts
    used instead of their samples), their seq and taxels back to back, row offsets, first rows in the file,
    non-finite texts and the trials whose stored data cannot be read (:func:`read_block`)."""

    entries: list[Entry]
    seq: np.ndarray
    tax: np.ndarray
    pos: np.ndarray
    starts: np.ndarray
    bad: list[str | None]
    failed: dict[int, str]
    #: of each trial read: the SHA-256 of its other recording arrays (:func:`rigctl.storage.trial_seal
    #: .arrays_digest`) where it has a seal row to meet, else None
    sealed_arrays: list[bytes | None] = field(default_factory=list)


#: (seq gaps per trial read, counts all inside the ADC range, SHA-256 of each read trial's taxels that has a sealed
#: checksum to meet, else None, each read trial's per-taxel (minimum, maximum) or None: empty or unreadable, each
#: read trial's repeated samples: rows identical on every taxel to the one before, recounted from the counts read)
Sums = tuple[np.ndarray, bool, list[bytes | None], list[np.ndarray | None], np.ndarray]


def read_entries(rec: Any, block: list[Entry], sealed: list[bool] | None = None) -> Block:
    """Read a block's trials (those without facts used instead of their samples) together (:func:`read_block`)
    from ``rec``, the file's ``/recording`` group; ``sealed``: per entry, whether it has a seal row whose arrays'
    checksum it must meet (:mod:`rigctl.storage.trial_seal`: those arrays are read and hashed too)."""
    read = [r for _, r, q, _, _ in block if q is None]
    seq, tax, pos, bad, failed = read_block(rec, read, int(rec["taxels"].shape[1]))
    starts = np.array([int(r["sample_start"]) for r in read], dtype=np.int64)
    blk = Block(block, seq, tax, pos, starts, bad, failed)
    want = [w for (_, _, q, _, _), w in zip(block, sealed or [False] * len(block)) if q is None]
    blk.sealed_arrays = _sealed_digests(rec, read, want, failed) if any(want) else [None] * len(read)
    return blk


def _sealed_digests(rec: Any, rows: list[np.void], want: list[bool], failed: dict[int, str]) -> list[bytes | None]:
    """:func:`rigctl.storage.trial_seal.arrays_digest` of each trial of ``rows`` that ``want`` marks (its arrays
    read together, one read per array and run of trials), None for the others and the unreadable."""
    from rigctl.storage.session_recording import STORED_DTYPES
    from rigctl.storage.trial_seal import SEALED_ARRAYS, arrays_digest

    prefix = {name: "sample" for name in ("seq", "flags", "host_time_s")}
    prefix.update({name: p for v, t, p in TRACES for name in (v, t)})
    parts: list[list[np.ndarray]] = [[] for _ in rows]
    try:
        for name in SEALED_ARRAYS:
            start_f, n_f = f"{prefix[name]}_start", "n_samples" if prefix[name] == "sample" else f"n_{prefix[name]}"
            take = [i for i, w in enumerate(want) if w and i not in failed]
            starts = np.array([int(rows[i][start_f]) for i in take], dtype=np.int64)
            lengths = np.array([int(rows[i][n_f]) for i in take], dtype=np.int64)
            pos = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
            buf = np.empty(int(pos[-1]), dtype=STORED_DTYPES[name])
            read_rows(rec[name], starts, lengths, buf)
            for k, i in enumerate(take):
                parts[i].append(buf[pos[k]:pos[k + 1]])
    except READ_ERRORS:
        return [None] * len(rows)
    return [arrays_digest(p) if w and i not in failed else None for i, (p, w) in enumerate(zip(parts, want))]


def block_sums(blk: Block, adc_max: int) -> Sums:
    """What a block's samples say, computed apart from the judging (on the validator's worker thread): the seq
    gaps, whether every count is inside ``0 .. adc_max``, the SHA-256 of each read trial's taxels that has a
    sealed checksum and each read trial's per-taxel extremes (:attr:`TrialReport.taxel_extremes`; neither for a
    trial whose data cannot be read, nor an empty one)."""
    gaps = block_seq_gaps(blk.seq, blk.pos)
    digests: list[bytes | None] = []
    extremes: list[np.ndarray | None] = []
    for sealed in (e[4] for e in blk.entries if e[2] is None):
        i = len(digests)
        a, b = int(blk.pos[i]), int(blk.pos[i + 1])
        readable = b > a and i not in blk.failed
        digests.append(sha256(blk.tax[a:b]) if sealed is not None and readable else None)
        extremes.append(np.stack(column_extremes(blk.tax[a:b])).astype(blk.tax.dtype) if readable else None)
    # every count read is inside the range (uint16: never below 0), from the trials' maxima: no pass of its own
    in_range = all(int(x[1].max()) <= adc_max for x in extremes if x is not None)
    return gaps, in_range, digests, extremes, block_repeated(blk.tax, blk.pos)


def block_repeated(tax: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """:func:`rigctl.core.trial.repeated_samples` of every trial of a block stored back to back (trial ``i`` is
    ``tax[pos[i]:pos[i + 1]]``): rows identical on every channel to the row before within the trial; (n_trials,)
    int64 (0 for one channel)."""
    n = max(int(np.asarray(pos).size) - 1, 0)
    if tax.ndim != 2 or tax.shape[1] < 2 or tax.shape[0] < 2:
        return np.zeros(n, dtype=np.int64)
    same = np.all(tax[1:] == tax[:-1], axis=1)  # row k + 1 repeats row k
    c = np.concatenate([[0], np.cumsum(same, dtype=np.int64)])
    lo, hi = np.asarray(pos[:-1], np.int64), np.asarray(pos[1:], np.int64)
    # pairs (k, k + 1) with both rows inside the trial: k from lo to hi - 2
    top = c.size - 1  # (an empty trial at the block's end starts past the last pair: clipped, counted 0)
    return np.where(hi - lo >= 2, c[np.clip(hi - 1, 0, top)] - c[np.clip(lo, 0, top)], 0).astype(np.int64)



def block_nonfinite(rec: Any, rows: list[np.void]) -> list[str | None]:
    """:func:`_nonfinite_text` of each trial of a block, from the trace arrays (one read per run of trials)."""
    counts: dict[str, list[np.ndarray]] = {}
    for value, times, prefix in ((v, t, p) for v, t, p in TRACES):
        starts = np.array([int(r[f"{prefix}_start"]) for r in rows], dtype=np.int64)
        lengths = np.array([int(r[f"n_{prefix}"]) for r in rows], dtype=np.int64)
        pos = np.concatenate([[0], np.cumsum(lengths)])
        for name in (value, times):
            buf = np.empty(int(pos[-1]), dtype=np.float64)
            read_rows(rec[name], starts, lengths, buf)
            for what, test in (("NaN", np.isnan), ("inf", np.isinf)):
                c = np.concatenate([[0], np.cumsum(test(buf))])
                counts[f"{what} in {name}"] = c[pos[1:]] - c[pos[:-1]]
    return [nonfinite_text({key: int(c[i]) for key, c in counts.items()}) for i in range(len(rows))]
