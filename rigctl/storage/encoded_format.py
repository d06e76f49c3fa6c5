"""The encoded file's format shared by its writer and reader: schema version, the variant registry, the trials
table and attribute encodings, the error type. Re-exported by :mod:`rigctl.storage.encoded`."""

from __future__ import annotations

import contextlib
import json
import math
import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import h5py
import numpy as np

from rigctl.core.errors import describe_error

#: schema of the files :class:`EncodedWriter` writes; files without the attribute are schema 1
ENCODED_SCHEMA_VERSION = 3
#: the ``kind`` attribute of an encoded file
ENCODED_KIND = "rigctl encoded"
#: the default name of a session's encoded file: ``d.h5`` -> ``d.enc.h5`` (``rigctl encode`` and the docs)
ENCODED_SUFFIX = ".enc.h5"


# ------------------------------------------------------------------------------------------------- variant registry
@dataclass(frozen=True)
class VariantInfo:
    """One feature variant of the encoding (paper Table 1 columns, plus rigctl's label-free and real-time ones).

    Attributes
    ----------
    name : str, the key under ``/features`` (``"speed_force_scaled"``).
    title : str, the paper's name (``"Speed and Force Scaled"``).
    speed_scaled : spike times scaled by the trial's speed (eq. 2): needs a finite, positive speed per trial.
    force_scaled : SA input scaled by force coefficients (eq. 1).
    label_free : force coefficients pooled over textures (not using the texture label).
    realtime : the real-time system's features (top-layer SA trains only, 20 windows; Methods, real-time).
    """

    name: str
    title: str
    speed_scaled: bool = False
    force_scaled: bool = False
    label_free: bool = False
    realtime: bool = False

    @property
    def main(self) -> bool:
        """One of the paper's four Table 1 variants."""
        return not (self.label_free or self.realtime)


_REGISTRY = (
    VariantInfo("original", "Original"),
    VariantInfo("speed_scaled", "Speed Scaled", speed_scaled=True),
    VariantInfo("force_scaled", "Force Scaled", force_scaled=True),
    VariantInfo("speed_force_scaled", "Speed and Force Scaled", speed_scaled=True, force_scaled=True),
    VariantInfo("force_scaled_label_free", "Force Scaled (label-free)", force_scaled=True, label_free=True),
    VariantInfo("speed_force_scaled_label_free", "Speed and Force Scaled (label-free)", speed_scaled=True,
                force_scaled=True, label_free=True),
    VariantInfo("realtime_original", "Original (real-time)", realtime=True),
    VariantInfo("realtime_speed_scaled", "Speed Scaled (real-time)", speed_scaled=True, realtime=True),
)
#: name -> :class:`VariantInfo`, in Table 1 order, then label-free, then real-time
VARIANTS: dict[str, VariantInfo] = {v.name: v for v in _REGISTRY}
#: name -> the paper's title
VARIANT_TITLES: dict[str, str] = {v.name: v.title for v in _REGISTRY}
#: the paper's four variants, Table 1 column order
MAIN_VARIANTS: tuple[str, ...] = tuple(v.name for v in _REGISTRY if v.main)
LABEL_FREE_VARIANTS: tuple[str, ...] = tuple(v.name for v in _REGISTRY if v.label_free)
REALTIME_VARIANTS: tuple[str, ...] = tuple(v.name for v in _REGISTRY if v.realtime)
ALL_VARIANTS: tuple[str, ...] = tuple(VARIANTS)


def variant_info(name: str) -> VariantInfo:
    """The registry entry of a variant. Raises KeyError naming the known variants."""
    try:
        return VARIANTS[name]
    except KeyError:
        raise KeyError(f"unknown variant {name!r}; choose from {', '.join(ALL_VARIANTS)}") from None


def _variant_order(names: Iterable[str]) -> tuple[str, ...]:
    names = list(names)
    return tuple([v for v in ALL_VARIANTS if v in names] + [v for v in names if v not in VARIANTS])


# ------------------------------------------------------------------------------------------------- helpers
class SpikeArrays(NamedTuple):
    """Stored spike trains, NWB ragged layout (the fields of :class:`rigctl.encoding.spikes.SpikeTrains`, which
    storage does not import: ``SpikeTrains(*arrays)``).

    spike_times : (n_spikes,) float64, s from each trial's first sample.
    spike_times_index : (n_trials * n_trains,) int64 row ends; row ``r = trial * n_trains + train``.
    n_trains : int, trains per trial.
    """

    spike_times: np.ndarray
    spike_times_index: np.ndarray
    n_trains: int


class NotEncodedError(ValueError):
    """The file is not an encoded file (a session file with raw readings, or another HDF5 file, or not HDF5):
    run ``rigctl encode`` on a session first; or it is one whose contents are malformed (truncated, damaged,
    tables and arrays of the wrong shape or type): the message names the file, the object and what is wrong."""


#: what h5py, numpy and json raise on a malformed file (turned into NotEncodedError by :func:`_reading`)
_READ_ERRORS = (OSError, KeyError, ValueError, TypeError, IndexError, AttributeError, RuntimeError, OverflowError)


@contextlib.contextmanager
def _reading(path: object, what: str) -> Iterator[None]:
    """Turn the errors of reading ``what`` from a malformed file into one NotEncodedError naming file and object."""
    try:
        yield
    except NotEncodedError:
        raise
    except _READ_ERRORS as exc:
        raise NotEncodedError(f"{path}: cannot read {what} ({describe_error(exc, 160)}); the encoded file is "
                              "damaged or not written by rigctl (encode the session again)") from None


def _damaged(path: object, what: str) -> NotEncodedError:
    return NotEncodedError(f"{path} is damaged: {what} (encode the session again)")


#: columns of :attr:`EncodedFile.trials` (and of the ``/trials`` table)
TRIAL_COLUMNS = ("trial_id", "texture", "group", "speed_mm_s", "force_g", "profile", "duration_s", "n_samples")

_STR = h5py.string_dtype("utf-8")
_TRIALS_DTYPE = np.dtype([("trial_id", "<u4"), ("texture", _STR), ("group", _STR), ("speed_mm_s", "<f4"),
                          ("force_g", "<f4"), ("profile", _STR), ("duration_s", "<f4"), ("n_samples", "<u4")])
#: columns the ``/trials`` table holds only when the encoder knows them (an additive change: readers of every schema
#: pass unknown columns through): ``recording`` (the source recording of an imported trial: its file, and
#: ``[block]`` for a stacked file) and ``recording_start_s`` (where in that recording the trial starts, s), what a
#: recording-grouped or time-blocked cross-validation holds out (``rigctl analyze --cv-groups``)
OPTIONAL_TRIAL_COLUMNS = {"recording": _STR, "recording_start_s": "<f8"}


def _text(values: Iterable[str]) -> np.ndarray[Any, Any]:
    """Bytes / object / str array -> numpy str array (UTF-8 decoded)."""
    a = np.asarray(values)
    if a.dtype.kind in "SO":
        return np.array([v.decode("utf-8") if isinstance(v, bytes) else str(v) for v in a.ravel()],
                        dtype=str).reshape(a.shape)
    return a.astype(str)


def _attr_value(v: Any) -> Any:
    if isinstance(v, bytes):
        return v.decode("utf-8", "replace")
    if isinstance(v, np.generic):
        return v.item()
    return v


def _jsonable(v: Any) -> Any:
    """An attribute value h5py can store: dicts/lists/tuples/None as JSON text, numpy scalars as Python."""
    if isinstance(v, (dict, list, tuple)) or v is None:
        return json.dumps(v, default=_json_default)
    if isinstance(v, np.generic):
        return v.item()
    return v


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    if isinstance(o, float) and not math.isfinite(o):
        return None
    raise TypeError(f"{type(o).__name__} is not JSON-able")


def _h5_table(table: np.ndarray) -> np.ndarray:
    """A structured array HDF5 can store: str (``U``) fields become variable-length UTF-8 (never truncated)."""
    table = np.asarray(table)
    if table.dtype.names is None or not any(table.dtype[k].kind in "UO" for k in table.dtype.names):
        return table
    dt = np.dtype([(k, _STR if table.dtype[k].kind in "UO" else table.dtype[k]) for k in table.dtype.names])
    out = np.zeros(table.shape, dtype=dt)
    for k in table.dtype.names:
        out[k] = np.array(table[k].astype(str), dtype=object) if table.dtype[k].kind in "UO" else table[k]
    return out


def _str_table(table: np.ndarray) -> np.ndarray:
    """Inverse of :func:`_h5_table` for reading: bytes / object fields become numpy str fields."""
    if table.dtype.names is None or not any(table.dtype[k].kind in "SO" for k in table.dtype.names):
        return table
    cols = {k: (_text(table[k]) if table.dtype[k].kind in "SO" else table[k]) for k in table.dtype.names}
    dt = np.dtype([(k, cols[k].dtype) for k in table.dtype.names])
    out = np.zeros(table.shape, dtype=dt)
    for k, v in cols.items():
        out[k] = v
    return out


def is_encoded_file(path: str | os.PathLike[str]) -> bool:
    """True if ``path`` is an HDF5 file with a ``/features`` group (an encoded file of any schema)."""
    try:
        with h5py.File(path, "r") as f:
            return "features" in f
    except (OSError, ValueError):
        return False


def _per_spike(scale: np.ndarray, index: np.ndarray, n_trains: int) -> np.ndarray:
    """Each spike's trial factor: ``scale`` (n_trials,) repeated by the trials' spike counts (row ends ``index``)."""
    return np.repeat(scale, np.diff(index[n_trains - 1::n_trains], prepend=0))


