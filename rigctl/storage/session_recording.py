"""Schema 4's recording arrays: every trial's data back to back in one dataset per quantity, with a trial index.

``/recording`` holds eight extendable datasets, appended to (never rewritten) as trials are committed, in commit
order, and ``/recording/index``, one row per recorded trial (:data:`INDEX_DTYPE`) saying where its rows are:

- per sample, rows ``sample_start .. sample_start + n_samples``: ``taxels`` (n, n_channels) uint16 ADC counts,
  ``seq`` uint16, ``flags`` uint8, ``host_time_s`` float64;
- the load-cell trace, rows ``force_start .. + n_force``: ``force_g``, ``force_time_s`` float64;
- the speed trace, rows ``speed_start .. + n_speed``: ``speed_mm_s``, ``speed_time_s`` float64.

Each trial's group ``/trials/<id>`` keeps its attributes and, in schema 4, the same eight names as schema 3, as HDF5
*virtual datasets* mapping its rows of these arrays (an empty trace is a plain empty dataset): a plain ``h5py`` reader
reads ``f["trials/000001/taxels"]`` as before. Schema 5 (the dataset generator's) makes no views: a trial's rows are
found by its index row only. The encoder reads many trials in one hyperslab (:func:`read_rows`) without opening a
group per trial. The arrays are written inside the same journaled commit as
the trial's group and its ``/plan`` status (:mod:`rigctl.storage.journal`), so a killed writer leaves every
finished trial readable and nothing of an unfinished one (``docs/session-format.md``, "Crash safety").
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import h5py
import numpy as np
from h5py import h5d, h5p, h5s

from rigctl.core.trial import TrialData
from rigctl.storage import h5objects

#: the group of the recording arrays
GROUP = "recording"
#: per-sample arrays, (name, dtype); ``taxels`` is 2-d (samples, channels)
SAMPLE_ARRAYS = (("taxels", np.dtype("<u2")), ("seq", np.dtype("<u2")), ("flags", np.dtype("u1")),
                 ("host_time_s", np.dtype("<f8")))
#: traces, (value, times, the index's prefix)
TRACES = (("force_g", "force_time_s", "force"), ("speed_mm_s", "speed_time_s", "speed"))
#: ``/recording/index``: one row per recorded trial, in commit order
INDEX_DTYPE = np.dtype([
    ("trial_id", "<u4"),
    ("sample_start", "<i8"), ("n_samples", "<i8"),
    ("force_start", "<i8"), ("n_force", "<i8"),
    ("speed_start", "<i8"), ("n_speed", "<i8"),
    ("dropped_frames", "<i8"), ("crc_errors", "<i8"),
])
#: bytes of taxels per chunk of the per-sample arrays (4,096 samples of the paper's 18 taxels): large enough for
#: reads at disk speed, small enough that a new file and each append allocate little (a chunk is allocated whole)
SAMPLE_CHUNK_BYTES = 4096 * 36
#: rows per chunk of the 1-d trace arrays (a few s of 10-100 Hz traces per trial)
TRACE_CHUNK_ROWS = 1024
INDEX_CHUNK_ROWS = 256


def sample_chunk_rows(n_channels: int, chunk_bytes: int) -> int:
    """Rows per chunk of the per-sample arrays: ``chunk_bytes`` of taxels (at most 65,536 rows)."""
    return max(1, min(65536, chunk_bytes // (2 * max(1, int(n_channels)))))


def create(f: h5py.File, n_channels: int, *, compression: str | None) -> None:
    """Make the empty ``/recording`` arrays and index in a new schema-4 file (``compression`` as the writer's:
    "gzip" level 1 with shuffle, "lzf", or None; fixed for the file's life)."""
    g = f.create_group(GROUP)
    rows = sample_chunk_rows(n_channels, SAMPLE_CHUNK_BYTES)
    comp = {"compression": compression, "shuffle": True} if compression else {}
    if compression == "gzip":
        comp["compression_opts"] = 1
    for name, dt in SAMPLE_ARRAYS:
        shape = (0, n_channels) if name == "taxels" else (0,)
        g.create_dataset(name, shape=shape, maxshape=(None,) + shape[1:], chunks=(rows,) + shape[1:], dtype=dt,
                         **comp)
    for value, times, _ in TRACES:
        for name in (value, times):
            g.create_dataset(name, shape=(0,), maxshape=(None,), chunks=(TRACE_CHUNK_ROWS,), dtype="<f8", **comp)
    g.create_dataset("index", shape=(0,), maxshape=(None,), chunks=(INDEX_CHUNK_ROWS,), dtype=INDEX_DTYPE)
    g["taxels"].attrs.update(unit="ADC counts")


#: the session schemas whose trial groups hold views of their rows (HDF5 virtual datasets); schema 5 has none
VIEW_SCHEMAS = (4,)


def has_views(attrs: Mapping[str, Any]) -> bool:
    """True for a session (its checked root attributes) whose trial groups hold views of their rows: schema 4."""
    return int(np.asarray(attrs.get("schema_version", 0)).reshape(-1)[0]) in VIEW_SCHEMAS


def is_flat(f: h5py.File) -> bool:
    """True for a file with recording arrays (schema 4)."""
    return isinstance(f.get(GROUP), h5py.Group)


def _append(ds: h5py.Dataset, data: np.ndarray) -> int:
    """Append ``data`` to the extendable ``ds`` (one resize, one write); returns the first new row."""
    start = int(ds.shape[0])
    if len(data):
        ds.resize((start + len(data),) + ds.shape[1:])
        ds[start:] = data
    return start


#: every recording array's stored type: the per-sample arrays', then the traces' (float64)
STORED_DTYPES: dict[str, np.dtype[Any]] = {**dict(SAMPLE_ARRAYS),
                                           **{name: np.dtype("<f8") for v, t, _ in TRACES for name in (v, t)}}


def stored(name: str, array: Any, n_channels: int) -> np.ndarray:
    """One trial's ``array`` as recording array ``name`` stores it (its type; ``taxels`` as ``(n, n_channels)``):
    the bytes written, from which the trial facts (:mod:`rigctl.storage.trial_facts`) are computed too."""
    return np.asarray(array, dtype=STORED_DTYPES[name]).reshape((-1, n_channels) if name == "taxels" else (-1,))


def _stack(name: str, arrays: list[Any], n_channels: int) -> np.ndarray:
    if not arrays:
        return np.zeros((0, n_channels) if name == "taxels" else (0,), STORED_DTYPES[name])
    return np.concatenate([stored(name, a, n_channels) for a in arrays])


class BatchArrays:
    """The per-sample arrays of a batch of trials, each trial copied once, in its stored type, into buffers kept from
    batch to batch (grown by doubling): what :func:`append_trials` writes without concatenating the trials again
    (the dataset generator's writer copied each trial out of its shared-memory slot, then the batch into one array).

    ``n_channels``: the session's taxel count."""

    def __init__(self, n_channels: int) -> None:
        self.n_channels = int(n_channels)
        self._bufs: dict[str, np.ndarray] = {}
        self._used = 0

    def clear(self) -> None:
        """Start a new batch (the buffers are kept; views handed out before now are overwritten by later takes)."""
        self._used = 0

    def take(self, data: TrialData) -> dict[str, np.ndarray]:
        """Copy ``data``'s per-sample arrays (:data:`SAMPLE_ARRAYS`, as :func:`stored`) after the batch's earlier
        trials; returns them as views of the buffers (valid until :meth:`clear`)."""
        arrays = {name: stored(name, getattr(data, name), self.n_channels) for name, _ in SAMPLE_ARRAYS}
        start = self._used
        end = start + len(arrays["taxels"])
        if any(len(a) != end - start for a in arrays.values()):
            raise ValueError(f"a trial's per-sample arrays differ in length: "
                             f"{ {k: len(a) for k, a in arrays.items()} }")
        out = {}
        for name, dtype in SAMPLE_ARRAYS:
            buf = self._bufs.get(name)
            if buf is None or len(buf) < end:  # grown: the earlier trials' rows come along (their views stay valid)
                cap = max(end, 2 * (0 if buf is None else len(buf)), 1024)
                new = np.empty((cap, self.n_channels) if name == "taxels" else (cap,), dtype)
                if buf is not None:
                    new[:start] = buf[:start]
                self._bufs[name] = buf = new
            dst = buf[start:end]
            dst[...] = arrays[name]
            out[name] = dst
        self._used = end
        return out

    def stacked(self) -> dict[str, np.ndarray]:
        """The batch's per-sample arrays so far, trial after trial (what :func:`append_trials` appends)."""
        return {name: (self._bufs[name][:self._used] if name in self._bufs else
                       np.zeros((0, self.n_channels) if name == "taxels" else (0,), dtype))
                for name, dtype in SAMPLE_ARRAYS}


def append_trials(f: h5py.File, items: list[tuple[Any, int, TrialData]], *, views: bool = True,
                  stacked: dict[str, np.ndarray] | None = None) -> tuple[list[Any], np.ndarray]:
    """Append trials to ``/recording`` (each array once for the whole batch) and their index rows, and (``views``:
    schema 4) make each trial's views in its new, empty group. ``items``: (group low-level id, trial id, data).
    ``stacked``: the items' per-sample arrays already back to back (:meth:`BatchArrays.stacked`, taken in ``items``
    order), written as they are. Returns the low-level ids of the ``taxels`` views, in ``items`` order (for their
    attributes; none without ``views``), and the new index rows."""
    rec = f[GROUP]
    rows = np.zeros(len(items), dtype=INDEX_DTYPE)
    rows["trial_id"] = [int(t) for _, t, _ in items]
    data = [d for _, _, d in items]
    rows["n_samples"] = [d.n_samples for d in data]
    n_ch = rec["taxels"].shape[1]
    for name, _ in SAMPLE_ARRAYS:
        whole = stacked[name] if stacked is not None else _stack(name, [getattr(d, name) for d in data], n_ch)
        first = _append(rec[name], whole)
    rows["sample_start"] = first + np.concatenate([[0], np.cumsum(rows["n_samples"])[:-1]])
    for value, times, prefix in TRACES:
        rows[f"n_{prefix}"] = [np.size(getattr(d, value)) for d in data]
        first = _append(rec[value], _stack(value, [getattr(d, value) for d in data], n_ch))
        _append(rec[times], _stack(times, [getattr(d, times) for d in data], n_ch))
        rows[f"{prefix}_start"] = first + np.concatenate([[0], np.cumsum(rows[f"n_{prefix}"])[:-1]])
    rows["dropped_frames"] = [d.dropped_frames for d in data]
    rows["crc_errors"] = [d.crc_errors for d in data]
    _append(rec["index"], rows)
    if not views:  # schema 5: the index is where a trial's rows are (8 views cost ~1 ms a trial to make)
        return [], rows
    sources = {name: _Source(rec[name]) for name, _ in SAMPLE_ARRAYS}
    sources.update({name: _Source(rec[name]) for value, times, _ in TRACES for name in (value, times)})
    out = []
    for (gid, _, _), row in zip(items, rows):
        gid = gid.id if isinstance(gid, h5py.HLObject) else gid
        for name, _ in SAMPLE_ARRAYS:
            view = sources[name].view(gid, name, int(row["sample_start"]), int(row["n_samples"]))
            if name == "taxels":
                out.append(view)
        for value, times, prefix in TRACES:
            for name in (value, times):
                sources[name].view(gid, name, int(row[f"{prefix}_start"]), int(row[f"n_{prefix}"]))
    return out, rows


class _Source:
    """One recording array as the source of views (its type, name and extent read once per batch)."""

    def __init__(self, ds: h5py.Dataset) -> None:
        self.id = ds.id
        self.name = ds.name.encode()
        self.type = ds.id.get_type()
        self.space = ds.id.get_space()
        self.dtype = ds.dtype
        self.tail = tuple(ds.shape[1:])

    def view(self, gid: Any, name: str, start: int, n: int) -> Any:
        """A virtual dataset ``name`` in ``gid`` mapping rows ``start .. start + n`` of this array (in the same
        file), or a plain empty dataset when ``n`` is 0. Returns its low-level id."""
        shape = (n,) + self.tail
        if n == 0:
            return h5objects.create_dataset(gid, name, np.zeros(shape, dtype=self.dtype))
        src = self.space.copy()
        src.select_hyperslab((start,) + (0,) * len(self.tail), shape)
        vspace = h5s.create_simple(shape)
        dcpl = h5p.create(h5p.DATASET_CREATE)
        dcpl.set_obj_track_times(False)
        dcpl.set_virtual(vspace, b".", self.name, src)
        return h5d.create(gid, name.encode(), self.type, vspace, dcpl=dcpl)


def read_index(f: h5py.File) -> np.ndarray:
    """``/recording/index`` (:data:`INDEX_DTYPE`), one row per recorded trial."""
    return np.asarray(f[GROUP]["index"][()])


def runs(starts: np.ndarray, lengths: np.ndarray) -> list[tuple[int, int, int, int]]:
    """Contiguous runs of the row ranges ``starts[i] .. starts[i] + lengths[i]`` taken in order: ``(first trial,
    end trial, first row, end row)`` for each run of trials whose rows follow each other in the file."""
    out = []
    i, n = 0, len(starts)
    while i < n:
        j = i + 1
        while j < n and starts[j] == starts[j - 1] + lengths[j - 1]:
            j += 1
        out.append((i, j, int(starts[i]), int(starts[j - 1] + lengths[j - 1])))
        i = j
    return out


def read_rows(ds: h5py.Dataset, starts: np.ndarray, lengths: np.ndarray, out: np.ndarray) -> None:
    """Read the rows of many trials of the recording array ``ds`` back to back into ``out`` (preallocated,
    ``sum(lengths)`` rows): one read per run of trials stored one after another (:func:`runs`)."""
    pos = 0
    for _, _, lo, hi in runs(starts, lengths):
        if hi > lo:
            ds.read_direct(out, np.s_[lo:hi], np.s_[pos:pos + hi - lo])
        pos += hi - lo


def rows_by_trial(f: h5py.File, name: str, dtype: np.dtype[Any]) -> dict[int, np.void]:
    """Trial id -> its row of the per-trial table ``/recording/<name>`` (the trial facts, the seal) when that is the
    documented 1-d table of ``dtype``; ``{}`` otherwise or on a read error. A trial listed more than once gets none
    (which row is its is ambiguous)."""
    try:
        ds = f[GROUP].get(name)
        if not isinstance(ds, h5py.Dataset) or ds.dtype != dtype or ds.ndim != 1:
            return {}
        table = ds[()]
    except (OSError, KeyError, ValueError, TypeError, RuntimeError):
        return {}
    out: dict[int, np.void] = {}
    seen: set[int] = set()
    for row in table:
        tid = int(row["trial_id"])
        if tid in seen:
            out.pop(tid, None)
        else:
            out[tid] = row
        seen.add(tid)
    return out
