"""Encoded files: the one writer and the one reader of what ``rigctl encode`` produces (HDF5, h5py).

An encoded file holds, for every encoded trial of a session, the spiking features of each variant, optionally the
SA/RA spike trains, the per-taxel normalisation and the force coefficients (paper eqs. 1-5; Fig. 1B). It is written
by :func:`rigctl.encoding.pipeline.encode_session` through :class:`EncodedWriter` and read by the analyses, the
GUI and ``rigctl`` commands through :func:`open_encoded` (nobody else opens it with h5py).

Layout (schema :data:`ENCODED_SCHEMA_VERSION` = 3)::

    /trials                  compound table, one row per trial: trial_id u4, texture (variable-length UTF-8),
                             group (variable-length UTF-8, "" when the texture set has none), speed_mm_s f4 (NaN
                             when unknown), force_g f4 (NaN when unknown), profile (VL UTF-8), duration_s f4,
                             n_samples u4 (samples at the session's own rate)
    /features/<variant>      (n_trials, n_features) float32 (feature layout: rigctl.encoding.features)
    /spikes/<variant>/       NWB-style ragged trains, row = trial * n_trains + train; attrs n_trains, unit, trains;
                             either ticks: spike_ticks (uint32 model steps) + spike_times_index (int64 row ends) +
                             time_scale ((n_trials,) float64), attr tick_s (s, 1 / model rate): time (s) =
                             ticks * tick_s * time_scale[trial] (1, or eq. 2's speed / reference); a speed-scaled
                             variant whose unscaled base is stored keeps only its time_scale and names the base in
                             attr ticks_from; or float64 times: spike_times (s) + spike_times_index (times off a tick
                             grid: the real-time variant's piecewise scaling)
    /force_coefficients      table (texture, speed_mm_s, force_g, taxel, coeff, converged, target_rate, rate)
    /force_coefficients_label_free
    /normalisation/          taxel_min, taxel_max (ADC counts of the model input: after resampling, if any)
    attrs: schema_version (3), kind ("rigctl encoded"), sensor_layout (JSON, rigctl.core.sensor.SensorLayout),
           texture_set (JSON, rigctl.core.textures.TextureSet), parameters (JSON, EncodeParams), variants (JSON
           list), n_trials, n_taxels, input_rate_hz, model_rate_hz, resampled (bool), resampling (text),
           windows_note (text), skipped_variants (JSON {variant: reason}), feature_layout (text),
           source_session, encode_seconds, force_coefficients*_note / _n_not_converged / _n_coefficients

Schema 2 stored every variant's spike trains as gzip-compressed float64 ``spike_times`` (4 x 8 bytes a spike for
the paper's variants, written at ~80 MB per CPU-second); it still opens, as the same :class:`SpikeArrays`. Schema 3
stores 4 bytes a spike, once for a variant and its speed-scaled twin, uncompressed.

Schema 1 (files written before the schema was versioned, no ``schema_version`` attribute) still opens: the layout
is inferred from the taxel count (the paper's 3x3x2 for 18 channels) at the rate in ``parameters`` (1 kHz), the
texture set from the labels (with the stored groups), ``texture``/``group``/``profile`` were fixed-length bytes.

The variant registry (:data:`VARIANTS`) is the one list of feature variants of rigctl: names, the paper's titles
(Table 1, Fig. 3) and what each variant scales.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import sys
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple, cast

import h5py
import numpy as np

from rigctl.core.sensor import SensorLayout
from rigctl.core.textures import PAPER_TEXTURES, TextureSet, texture_set_from_labels
from rigctl.storage.outputs import output_file

__all__ = [
    "ENCODED_SCHEMA_VERSION", "ENCODED_KIND", "VariantInfo", "VARIANTS", "VARIANT_TITLES", "MAIN_VARIANTS",
    "LABEL_FREE_VARIANTS", "REALTIME_VARIANTS", "ALL_VARIANTS", "variant_info", "EncodedWriter", "EncodedFile",
    "open_encoded", "is_encoded_file", "NotEncodedError", "TRIAL_COLUMNS", "SpikeArrays",
]

#: schema of the files :class:`EncodedWriter` writes; files without the attribute are schema 1
ENCODED_SCHEMA_VERSION = 3
#: the ``kind`` attribute of an encoded file
ENCODED_KIND = "rigctl encoded"


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
        text = " ".join(str(exc).split())
        text = text if len(text) <= 160 else text[:157] + "..."
        raise NotEncodedError(f"{path}: cannot read {what} ({type(exc).__name__}: {text}); the encoded file is "
                              "damaged or not written by rigctl (encode the session again)") from None


def _damaged(path: object, what: str) -> NotEncodedError:
    return NotEncodedError(f"{path} is damaged: {what} (encode the session again)")


#: columns of :attr:`EncodedFile.trials` (and of the ``/trials`` table)
TRIAL_COLUMNS = ("trial_id", "texture", "group", "speed_mm_s", "force_g", "profile", "duration_s", "n_samples")

_STR = h5py.string_dtype("utf-8")
_TRIALS_DTYPE = np.dtype([("trial_id", "<u4"), ("texture", _STR), ("group", _STR), ("speed_mm_s", "<f4"),
                          ("force_g", "<f4"), ("profile", _STR), ("duration_s", "<f4"), ("n_samples", "<u4")])


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


# ------------------------------------------------------------------------------------------------- writer
class EncodedWriter:
    """Writes one encoded file (the layout in the module docstring), under ``<name>.part`` until :meth:`close`
    renames it into place; a writer left by an exception (context manager) removes the part file.

    Parameters
    ----------
    path : the encoded .h5 to write.
    layout : the session's :class:`SensorLayout` (stored as JSON; its rate is the *input* rate of the encoding).
    textures : the session's :class:`TextureSet` (stored as JSON; gives each trial's group).
    trials : mapping with the columns of :data:`TRIAL_COLUMNS` (``group`` optional: taken from ``textures``),
        one entry per trial, in the row order of every feature matrix and spike table.
    parameters : JSON-able encoding parameters (``EncodeParams`` as a dict).
    overwrite : replace an existing ``path`` (default False: FileExistsError).
    attrs : more root attributes (dicts and lists stored as JSON).

    Raises
    ------
    FileExistsError when ``path`` exists and ``overwrite`` is False; ValueError for trial columns of unequal length
    or without ``trial_id`` / ``texture``; rigctl.core.textures.TextureSetError for a label not in ``textures``.
    """

    def __init__(self, path: str | os.PathLike[str], *, layout: SensorLayout, textures: TextureSet,
                 trials: Mapping[str, Any], parameters: Mapping[str, Any] | None = None, overwrite: bool = False,
                 attrs: Mapping[str, Any] | None = None) -> None:
        self.path = Path(path)
        self.layout = layout
        self.textures = textures
        table = self._trials_table(trials, textures)
        self.n_trials = int(table.size)
        self._done = False
        self._output = output_file(self.path, overwrite=overwrite)  # the output policy: lock, part file, guard
        self._target = self._output.__enter__()
        self.part = self._target.part
        try:
            self._f = h5py.File(self._target.h5_file(), "w")
        except BaseException:
            self._output.__exit__(*sys.exc_info())
            raise
        self._features: dict[str, h5py.Dataset] = {}
        self._spikes: dict[str, h5py.Group] = {}
        self._batch_spikes: dict[str, int] = {}  # spikes of the last appended batch, per variant with ticks
        try:
            self._f.create_dataset("trials", data=table)
            a = self._f.attrs
            a["schema_version"] = ENCODED_SCHEMA_VERSION
            a["kind"] = ENCODED_KIND
            a["sensor_layout"] = layout.to_json()
            a["texture_set"] = textures.to_json()
            a["parameters"] = json.dumps(dict(parameters or {}), default=_json_default)
            a["n_trials"] = self.n_trials
            a["n_taxels"] = layout.n_channels
            self._f.create_group("features")
            self._f.create_group("spikes")
            self.set_attrs(**dict(attrs or {}))
        except BaseException:
            self.abort()
            raise

    @staticmethod
    def _trials_table(trials: Mapping[str, Any], textures: TextureSet) -> np.ndarray:
        if "trial_id" not in trials or "texture" not in trials:
            raise ValueError("trials need at least 'trial_id' and 'texture' columns")
        n = len(trials["trial_id"])
        bad = [k for k, v in trials.items() if len(v) != n]
        if bad:
            raise ValueError(f"trial columns {bad} do not have {n} entries like trial_id")
        out = np.zeros(n, dtype=_TRIALS_DTYPE)
        texture = _text(trials["texture"])
        out["trial_id"] = np.asarray(trials["trial_id"])
        out["texture"] = np.array(texture, dtype=object)
        if "group" in trials:
            group = _text(trials["group"])
        else:
            group = np.array([textures.group_of(t) or "" for t in texture], dtype=str)
        out["group"] = np.array(group, dtype=object)
        out["profile"] = np.array(_text(trials.get("profile", np.full(n, "constant"))), dtype=object)
        for k in ("speed_mm_s", "force_g", "duration_s"):
            out[k] = np.asarray(trials.get(k, np.full(n, np.nan)), np.float64)
        out["n_samples"] = np.asarray(trials.get("n_samples", np.zeros(n)))
        return out

    # -- content -------------------------------------------------------------------------------------------------
    def set_attrs(self, **attrs: Any) -> None:
        """Root attributes (dicts, lists and None stored as JSON text)."""
        for k, v in attrs.items():
            self._f.attrs[k] = _jsonable(v)

    def write_normalisation(self, taxel_min: Any, taxel_max: Any, *, source: str = "") -> None:
        """``/normalisation/taxel_min`` and ``taxel_max``: (n_taxels,) float64, the per-taxel range (ADC counts)."""
        g = self._f.require_group("normalisation")
        g.create_dataset("taxel_min", data=np.asarray(taxel_min, np.float64))
        g.create_dataset("taxel_max", data=np.asarray(taxel_max, np.float64))
        if source:
            g.attrs["source"] = source

    def write_force_coefficients(self, table: np.ndarray, *, label_free: bool = False, **attrs: Any) -> None:
        """The force coefficient table (eq. 1) and its fit statistics (``n_not_converged``, ``n_coefficients``,
        ``n_iter``, ``n_fit_trials``; also copied to root attributes ``<name>_<stat>``)."""
        name = "force_coefficients_label_free" if label_free else "force_coefficients"
        ds = self._f.create_dataset(name, data=_h5_table(table))
        for k, v in attrs.items():
            ds.attrs[k] = _jsonable(v)
            if k in ("n_not_converged", "n_coefficients"):
                self._f.attrs[f"{name}_{k}"] = _jsonable(v)

    def note_force_coefficients(self, note: str, *, label_free: bool = False) -> None:
        """Why there is no coefficient table (root attribute ``<name>_note``)."""
        name = "force_coefficients_label_free" if label_free else "force_coefficients"
        self._f.attrs[f"{name}_note"] = str(note)

    def write_features(self, variant: str, start: int, rows: Any) -> None:
        """Rows ``start .. start + len(rows) - 1`` of ``/features/<variant>`` ((n_trials, n_features) float32; made
        on the first call). Raises ValueError for a feature count that differs from earlier rows."""
        rows = np.asarray(rows, np.float32)
        ds = self._features.get(variant)
        if ds is None:
            ds = self._f["features"].create_dataset(
                variant, shape=(self.n_trials, rows.shape[1]), dtype="f4",
                chunks=(max(1, min(256, self.n_trials)), max(1, rows.shape[1])))
            ds.attrs["title"] = VARIANTS[variant].title if variant in VARIANTS else variant
            self._features[variant] = ds
        if rows.shape[1] != ds.shape[1]:
            raise ValueError(f"{variant}: {rows.shape[1]} features, earlier rows had {ds.shape[1]}")
        ds[start:start + rows.shape[0]] = rows
        self._target.check()  # a full disk ends the write here, in one line

    def add_spikes(self, variant: str, n_trains: int, trains: str = "", *, tick_s: float | None = None,
                   ticks_from: str | None = None) -> None:
        """Make ``/spikes/<variant>`` (appendable) for trains of ``n_trains`` per trial; ``trains`` says what they
        are (e.g. ``"SA taxels 0..n-1 then RA taxels 0..n-1"``).

        Parameters
        ----------
        tick_s : None -> spike times stored as float64 s (any times, e.g. the real-time variant's piecewise
            scaling); a float (the model's step, ``1 / fs`` s) -> the compact tick layout: uint32 sample ticks,
            time = ticks x ``tick_s`` x the trial's ``time_scale`` (1, or eq. 2's speed / reference), read back
            bit-identical to the encoder's times.
        ticks_from : a variant already added with ticks (same ``n_trains``) whose ticks and row ends this one
            shares, storing only its per-trial ``time_scale`` (a speed-scaled variant and its unscaled base).

        Raises
        ------
        ValueError for a ``ticks_from`` variant that is not stored with ticks or has another train count.
        """
        if ticks_from is not None:
            base = self._spikes.get(ticks_from)
            if base is None or "spike_ticks" not in base:
                raise ValueError(f"{variant}: ticks_from={ticks_from!r} is not a variant stored with ticks")
            if int(base.attrs["n_trains"]) != int(n_trains):
                raise ValueError(f"{variant}: {n_trains} trains per trial, {ticks_from} has {base.attrs['n_trains']}")
            tick_s = float(base.attrs["tick_s"])
        g = self._f["spikes"].create_group(variant)
        g.attrs["n_trains"] = int(n_trains)
        g.attrs["unit"] = "s"
        g.attrs["trains"] = trains
        if tick_s is None:
            g.create_dataset("spike_times", shape=(0,), maxshape=(None,), dtype="f8", chunks=(1 << 16,),
                             compression="gzip", compression_opts=1)
            g.attrs["layout"] = "NWB ragged: row r = spike_times[index[r-1]:index[r]], r = trial*n_trains+train"
        else:
            if not (math.isfinite(tick_s) and tick_s > 0):
                raise ValueError(f"{variant}: tick_s must be a positive time step, got {tick_s}")
            g.attrs["tick_s"] = float(tick_s)
            g.create_dataset("time_scale", shape=(0,), maxshape=(None,), dtype="f8", chunks=(1 << 14,))
            if ticks_from is not None:
                g.attrs["ticks_from"] = ticks_from
            else:  # uncompressed: 4 bytes a spike, written at memory speed
                g.create_dataset("spike_ticks", shape=(0,), maxshape=(None,), dtype="u4", chunks=(1 << 18,))
            g.attrs["layout"] = ("NWB ragged in ticks: row r = spike_ticks[index[r-1]:index[r]], "
                                 "r = trial*n_trains+train; time (s) = ticks * tick_s * time_scale[trial]"
                                 + (f"; ticks and index are {ticks_from}'s" if ticks_from else ""))
        if ticks_from is None:
            g.create_dataset("spike_times_index", shape=(0,), maxshape=(None,), dtype="i8", chunks=(1 << 14,),
                             compression="gzip", compression_opts=1)
        self._spikes[variant] = g

    @staticmethod
    def _append(ds: h5py.Dataset, values: np.ndarray) -> int:
        """Append ``values`` to the 1-d resizable ``ds``; returns the row where they start."""
        base = int(ds.shape[0])
        ds.resize((base + values.size,))
        ds[base:] = values
        return base

    def append_spikes(self, variant: str, trains: Any, time_scale: Any = None) -> None:
        """Append the next trials' trains (anything with ``spike_times``, ``spike_times_index`` (row ends) and
        ``n_trains``, e.g. :class:`rigctl.encoding.spikes.SpikeTrains`), in trial order.

        ``time_scale`` : scalar or (n_trials,) the factor the trials' times carry beyond ``ticks x tick_s`` (eq. 2's
        speed / reference for a speed-scaled variant; default 1); used by variants stored with ticks.

        Raises KeyError if :meth:`add_spikes` was not called for ``variant``; ValueError for another train count,
        times off the tick grid, or a ``ticks_from`` variant whose spikes are not its base's (counts differ).
        """
        self._append_spikes(variant, trains, time_scale)
        self._target.check()  # a full disk ends the write here, in one line

    def _append_spikes(self, variant: str, trains: Any, time_scale: Any) -> None:
        g = self._spikes[variant]
        n_trains = int(g.attrs["n_trains"])
        if int(trains.n_trains) != n_trains:
            raise ValueError(f"{variant}: {trains.n_trains} trains per trial, the file has {n_trains}")
        idx = np.asarray(trains.spike_times_index, np.int64)
        st = np.asarray(trains.spike_times, np.float64)
        if "spike_times" in g:  # float64 times
            base = self._append(g["spike_times"], st)
            self._append(g["spike_times_index"], idx + base)
            return
        n_trials = idx.size // n_trains
        scale = np.broadcast_to(np.asarray(1.0 if time_scale is None else time_scale, np.float64), (n_trials,))
        ticks_from = g.attrs.get("ticks_from")
        if ticks_from is not None:  # the base's ticks and rows: only the scale is this variant's
            if self._batch_spikes.get(str(ticks_from)) != st.size:
                raise ValueError(f"{variant}: {st.size} spikes in this batch, {ticks_from} had "
                                 f"{self._batch_spikes.get(str(ticks_from))}: not the same trains")
            self._append(g["time_scale"], np.ascontiguousarray(scale))
            return
        tick_s = float(g.attrs["tick_s"])
        per_spike = _per_spike(scale, idx, n_trains)
        ticks = np.rint(st / (per_spike * tick_s))
        if st.size and (ticks.min() < 0 or ticks.max() > np.iinfo(np.uint32).max
                        or not np.allclose(ticks * tick_s * per_spike, st, rtol=1e-12, atol=0.0)):
            raise ValueError(f"{variant}: spike times are not multiples of tick_s = {tick_s:g} s x time_scale")
        base = self._append(g["spike_ticks"], ticks.astype(np.uint32))
        self._append(g["spike_times_index"], idx + base)
        self._append(g["time_scale"], np.ascontiguousarray(scale))
        self._batch_spikes[variant] = st.size

    # -- finish --------------------------------------------------------------------------------------------------
    def check(self) -> None:
        """Raise :class:`rigctl.storage.outputs.OutputWriteError` (one line) if the disk has refused a write (the
        writer then aborts: see :mod:`rigctl.storage.outputs`)."""
        self._target.check()

    def close(self) -> Path:
        """Close and rename the part file to ``path`` (mode per the umask); returns ``path``.

        Raises OutputWriteError (the part file removed) if the disk refused any of the file."""
        if self._done:
            raise ValueError(f"{self.path}: the writer is closed")
        self._done = True
        try:
            self._f.close()
            self._target.check()
        except BaseException:
            self._output.__exit__(*sys.exc_info())
            raise
        self._output.__exit__(None, None, None)
        return self.path

    def abort(self) -> None:
        """Close and delete the part file (nothing is written to ``path``; idempotent)."""
        if self._done:
            return
        self._done = True
        try:
            self._f.close()
        finally:
            self._output.__exit__(RuntimeError, RuntimeError("aborted"), None)

    def __enter__(self) -> "EncodedWriter":
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


# ------------------------------------------------------------------------------------------------- reader
class EncodedFile:
    """An open encoded file (read-only). Use :func:`open_encoded`; a context manager (closes the file).

    Attributes
    ----------
    path : Path
    attrs : dict of the root attributes (bytes decoded, numpy scalars as Python; JSON text left as text).
    schema_version : int (1 for files written before the schema was versioned).
    layout : :class:`SensorLayout` of the encoded session (rate = the session's sample rate).
    textures : :class:`TextureSet` of the encoded session.
    variants : tuple of the variants under ``/features`` (registry order, then others).
    spike_variants : tuple of the variants whose spike trains are stored.
    n_trials : int
    """

    def __init__(self, path: str | os.PathLike[str], h5: h5py.File) -> None:
        self.path = Path(path)
        self._f = h5
        with _reading(self.path, "the root attributes"):
            self.attrs: dict[str, Any] = {k: _attr_value(v) for k, v in h5.attrs.items()}
            self.schema_version = int(self.attrs.get("schema_version", 1))
        with _reading(self.path, "/features and /spikes"):
            for name in ("features", "spikes"):
                if name in h5 and not isinstance(h5[name], h5py.Group):
                    raise _damaged(self.path, f"/{name} is not a group")
            self.variants: tuple[str, ...] = _variant_order(h5["features"])
            self.spike_variants: tuple[str, ...] = _variant_order(h5["spikes"]) if "spikes" in h5 else ()
        self._trials: dict[str, np.ndarray] | None = None
        self.parameters: dict[str, Any] = self._json_attr("parameters", {})
        if not isinstance(self.parameters, dict):
            raise _damaged(self.path, "the parameters attribute is not a JSON object")
        with _reading(self.path, "the sensor layout"):
            self.layout = self._read_layout()
        with _reading(self.path, "the texture set"):
            self.textures = self._read_textures()
        self._check_trials()

    def _check_trials(self) -> None:
        """Refuse a ``/trials`` table that cannot be matched to the feature rows: columns of unequal length, a
        trial id listed twice, a label outside the texture set, negative sample counts."""
        cols = self.trials
        n = len(cols["trial_id"])
        bad = [k for k, v in cols.items() if np.ndim(v) != 1 or len(v) != n]
        if bad:
            raise _damaged(self.path, f"/trials columns {bad} do not have {n} entries like trial_id")
        ids, counts = np.unique(cols["trial_id"], return_counts=True)
        if ids.size != n:
            raise _damaged(self.path, f"/trials lists trial {int(ids[counts > 1][0])} {int(counts.max())} times")
        unknown = sorted(set(cols["texture"].tolist()) - set(self.textures.labels))
        if unknown:
            raise _damaged(self.path, f"/trials holds texture labels outside its texture set: {unknown[:5]}")
        if n and cols["n_samples"].min() < 0:
            raise _damaged(self.path, "/trials holds a negative n_samples")

    def _json_attr(self, name: str, default: Any) -> Any:
        raw = self.attrs.get(name)
        if raw is None:
            return default
        try:
            return json.loads(raw)
        except (TypeError, ValueError):
            raise _damaged(self.path, f"its {name} attribute is not JSON") from None

    def _read_layout(self) -> SensorLayout:
        if "sensor_layout" in self.attrs:
            return SensorLayout.from_json(self.attrs["sensor_layout"])
        # schema 1: the old pipeline assumed the paper's rig (1 kHz; 18 taxels = 3x3x2)
        n = int(self.attrs.get("n_taxels", 0) or 0)
        if not n and "normalisation" in self._f:
            n = int(self._f["normalisation"]["taxel_min"].shape[0])
        rate = float(self.parameters.get("fs_hz", 1000.0) or 1000.0)
        return SensorLayout.for_channels(n or 18, sample_rate_hz=rate)

    def _read_textures(self) -> TextureSet:
        if "texture_set" in self.attrs:
            return TextureSet.from_json(self.attrs["texture_set"])
        cols = self.trials
        labels = cols["texture"]
        groups: dict[str, list[str]] = {}
        for t, g in zip(labels, cols["group"]):
            if g and t not in groups.setdefault(g, []):
                groups[g].append(t)
        ts = texture_set_from_labels(labels)
        if ts is PAPER_TEXTURES or not groups:
            return ts  # the paper's A-P (with its groups and geometry), or no groups stored
        if all(g for g in cols["group"]):
            return texture_set_from_labels(labels, groups=groups)
        return ts  # some textures without a group: keep the set ungrouped

    # -- content -------------------------------------------------------------------------------------------------
    @property
    def n_trials(self) -> int:
        return int(len(self.trials["trial_id"]))

    @property
    def trials(self) -> dict[str, np.ndarray]:
        """Per-trial labels, one array per column of :data:`TRIAL_COLUMNS`: ``trial_id`` int64, ``texture``,
        ``group`` (``""`` when none), ``profile`` str arrays, ``speed_mm_s``, ``force_g`` (NaN when unknown),
        ``duration_s`` float64 (s), ``n_samples`` int64 (samples at the session's rate). Read once, cached."""
        if self._trials is None:
            self._trials = self._read_trials()
        return self._trials

    def _read_trials(self) -> dict[str, np.ndarray]:
        with _reading(self.path, "/trials"):
            return self._read_trials_table()

    def _read_trials_table(self) -> dict[str, np.ndarray]:
        if "trials" not in self._f:
            raise NotEncodedError(f"{self.path} has no /trials table")
        obj = self._f["trials"]
        if isinstance(obj, h5py.Group):  # some schema-1 writers: a group of column datasets
            raw = {k: obj[k][()] for k in obj if isinstance(obj[k], h5py.Dataset)}
        else:
            data = obj[()]
            if data.dtype.names is None or data.ndim != 1:
                raise NotEncodedError(f"{self.path}: /trials is neither a table nor a group of columns")
            raw = {k: data[k] for k in data.dtype.names}
        if "texture" not in raw:
            raise NotEncodedError(f"{self.path}: /trials has no 'texture' column (has: {', '.join(raw)})")
        n = len(raw["texture"])
        cols: dict[str, np.ndarray] = {
            "trial_id": np.asarray(raw.get("trial_id", np.arange(n)), np.int64),
            "texture": _text(raw["texture"]),
            "group": _text(raw["group"]) if "group" in raw else np.full(n, "", dtype=str),
            "speed_mm_s": np.asarray(raw.get("speed_mm_s", np.full(n, np.nan)), np.float64),
            "force_g": np.asarray(raw.get("force_g", np.full(n, np.nan)), np.float64),
            "profile": _text(raw["profile"]) if "profile" in raw else np.full(n, "constant"),
            "duration_s": np.asarray(raw.get("duration_s", np.full(n, np.nan)), np.float64),
            "n_samples": np.asarray(raw.get("n_samples", np.zeros(n)), np.int64),
        }
        for k, v in raw.items():  # extra columns pass through
            if k not in cols:
                cols[k] = _text(v) if np.asarray(v).dtype.kind in "SO" else np.asarray(v)
        return cols

    def _features_dataset(self, variant: str) -> h5py.Dataset:
        if variant not in self.variants:
            raise KeyError(f"variant {variant!r} not in {self.path} (has: {', '.join(self.variants) or 'none'})")
        with _reading(self.path, f"/features/{variant}"):
            ds = self._f["features"][variant]
            if not isinstance(ds, h5py.Dataset) or ds.ndim != 2 or ds.dtype.kind not in "iuf":
                what = f"{ds.dtype} {ds.shape}" if isinstance(ds, h5py.Dataset) else "a group"
                raise _damaged(self.path, f"/features/{variant} is {what}, not (trials, features) numbers")
            if ds.shape[0] != self.n_trials:
                raise _damaged(self.path, f"/features/{variant} has {ds.shape[0]} rows for {self.n_trials} trials")
            return ds

    def features(self, variant: str) -> np.ndarray:
        """``(n_trials, n_features)`` float32 features of a variant (rows in :attr:`trials` order).

        Raises KeyError naming the stored variants; NotEncodedError if the stored array is not
        ``(n_trials, n_features)`` numbers (or cannot be read)."""
        ds = self._features_dataset(variant)
        with _reading(self.path, f"/features/{variant}"):
            return np.asarray(ds[()], dtype=np.float32)

    def feature_shape(self, variant: str) -> tuple[int, int]:
        """``(n_trials, n_features)`` of a variant without reading it. Raises as :meth:`features`."""
        return cast(tuple[int, int], tuple(int(n) for n in self._features_dataset(variant).shape))

    @property
    def skipped_variants(self) -> dict[str, str]:
        """Variants the encoding skipped (speed-scaled ones, when trials had no speed): {variant: reason}."""
        return dict(self._json_attr("skipped_variants", {}) or {})

    def n_trains(self, variant: str) -> int:
        """Spike trains per trial behind a variant's features: from ``/spikes/<variant>`` if stored, else from the
        layout (SA + RA per taxel; the real-time variants: the real-time taxels of ``parameters``)."""
        if variant in self.spike_variants:
            return self._n_trains_stored(variant)
        if variant in REALTIME_VARIANTS:
            taxels = self.parameters.get("realtime_taxels")
            return len(taxels) if taxels else len(self.layout.layer_channels(0))
        return 2 * self.layout.n_channels

    def _n_trains_stored(self, variant: str) -> int:
        with _reading(self.path, f"/spikes/{variant}"):
            n = int(np.asarray(self._f["spikes"][variant].attrs["n_trains"]).reshape(-1)[0])
        if n < 1:
            raise _damaged(self.path, f"/spikes/{variant} says {n} trains per trial")
        return n

    def spikes(self, variant: str, trials: slice | None = None) -> SpikeArrays:
        """Spike trains of a variant: :class:`SpikeArrays` (``spike_times`` s, ``spike_times_index`` row ends,
        ``n_trains``), NWB-style; ``rigctl.encoding.spikes.SpikeTrains(*f.spikes(v))`` gives the trains' methods.

        ``trials`` : a slice of trial rows (step 1) to read only those (e.g. ``slice(i, i + 1)``: one trial of a
        paper-size file without reading its ~10^8 spikes); None = every trial.

        Raises KeyError if the file has no spike trains for ``variant`` (encoded with ``--no-spikes``, or a variant
        whose trains are not stored); ValueError for a slice with a step; NotEncodedError for damaged tables."""
        if variant not in self.spike_variants:
            raise KeyError(f"no spike trains of {variant!r} in {self.path} "
                           f"(stored: {', '.join(self.spike_variants) or 'none'})")
        t0, t1, step = (trials if trials is not None else slice(None)).indices(self.n_trials)
        if step != 1:
            raise ValueError(f"spikes(trials=...) takes a slice of consecutive trials, not step {step}")
        t1 = max(t0, t1)
        n_trains = self._n_trains_stored(variant)
        r0, r1 = t0 * n_trains, t1 * n_trains
        with _reading(self.path, f"/spikes/{variant}"):
            g = self._f["spikes"][variant]
            scale_ds = tick_s = None
            if "spike_times" in g:  # float64 s (schema 2, and variants whose times are not on a tick grid)
                times_ds, index_ds = g["spike_times"], g["spike_times_index"]
                ok = times_ds.dtype.kind == "f"
                what = f"spike_times {times_ds.dtype} {times_ds.shape}"
            else:  # ticks (schema 3), possibly another variant's
                src = self._f["spikes"][str(_attr_value(g.attrs.get("ticks_from", variant)))]
                times_ds, index_ds, scale_ds = src["spike_ticks"], src["spike_times_index"], g["time_scale"]
                tick_s = float(np.asarray(_attr_value(g.attrs["tick_s"])).reshape(-1)[0])
                ok = times_ds.dtype.kind == "u" and scale_ds.ndim == 1 and scale_ds.dtype.kind == "f"
                what = f"spike_ticks {times_ds.dtype} {times_ds.shape}, time_scale {scale_ds.dtype} {scale_ds.shape}"
            if not ok or times_ds.ndim != 1 or index_ds.ndim != 1 or index_ds.dtype.kind not in "iu":
                raise _damaged(self.path, f"/spikes/{variant}: {what} and spike_times_index {index_ds.dtype} "
                                          f"{index_ds.shape} are not 1-d spike times and row ends")
            if index_ds.shape[0] != self.n_trials * n_trains:
                raise _damaged(self.path, f"/spikes/{variant} has {index_ds.shape[0]} trains, not {self.n_trials} "
                                          f"trials x {n_trains}")
            index = np.asarray(index_ds[max(r0 - 1, 0):r1], np.int64)  # with the row end before the first row
            s0 = int(index[0]) if r0 > 0 else 0
            index = index[1:] if r0 > 0 else index
            s1 = int(index[-1]) if index.size else s0
            n_stored = int(times_ds.shape[0])
            if s0 < 0 or (index.size and (index[0] < s0 or np.any(np.diff(index) < 0))) or s1 > n_stored:
                raise _damaged(self.path, f"/spikes/{variant}: spike_times_index is not row ends into spike_times "
                                          f"({n_stored} spikes)")
            raw = times_ds[s0:s1]
            scale = None
            if scale_ds is not None:
                if scale_ds.shape[0] != self.n_trials:
                    raise _damaged(self.path, f"/spikes/{variant} has {scale_ds.shape[0]} time scales, not "
                                              f"{self.n_trials}")
                scale = np.asarray(scale_ds[t0:t1], np.float64)
        if tick_s is None:
            times = np.asarray(raw, np.float64)
        else:
            times = raw.astype(np.float64) * tick_s  # the encoder's own operations: bit-identical times
        index = index - s0
        if scale is not None and np.any(scale != 1.0):
            times *= _per_spike(scale, index, n_trains)
        return SpikeArrays(times, index, n_trains)

    def spike_trains_description(self, variant: str) -> str:
        """What the trains of a variant are (``"SA taxels 0..n-1 then RA taxels 0..n-1"``), "" if not stored."""
        if variant not in self.spike_variants:
            return ""
        return str(_attr_value(self._f["spikes"][variant].attrs.get("trains", "")))

    @property
    def normalisation(self) -> dict[str, np.ndarray]:
        """``{"taxel_min": (n_taxels,), "taxel_max": (n_taxels,)}`` float64 ADC counts: the per-taxel range the
        encoding normalised with (needed to encode new trials the same way)."""
        out = {}
        with _reading(self.path, "/normalisation"):
            if "normalisation" not in self._f:
                raise _damaged(self.path, "it has no /normalisation")
            for k in ("taxel_min", "taxel_max"):
                arr = np.asarray(self._f["normalisation"][k][()])
                if arr.shape != (self.layout.n_channels,) or arr.dtype.kind not in "iuf":
                    raise _damaged(self.path, f"/normalisation/{k} is {arr.dtype} {arr.shape}, not "
                                              f"({self.layout.n_channels},) numbers")
                out[k] = arr.astype(np.float64)
        return out

    def force_coefficients(self, *, label_free: bool = False) -> np.ndarray | None:
        """The eq. (1) coefficient table (structured array: texture str (``"*"`` label-free), speed_mm_s, force_g,
        taxel, coeff, converged, target_rate, rate), or None when it was not fitted (see
        ``attrs["force_coefficients_note"]``)."""
        name = "force_coefficients_label_free" if label_free else "force_coefficients"
        with _reading(self.path, f"/{name}"):
            if name not in self._f:
                return None
            table = self._f[name][()]
            if table.dtype.names is None or table.ndim != 1:
                raise _damaged(self.path, f"/{name} is not a table")
            return _str_table(table)

    def force_fit_stats(self, *, label_free: bool = False) -> dict[str, Any]:
        """Attributes of the coefficient table (``n_not_converged``, ``n_coefficients``, ...); {} when none."""
        name = "force_coefficients_label_free" if label_free else "force_coefficients"
        with _reading(self.path, f"/{name}"):
            return {k: _attr_value(v) for k, v in self._f[name].attrs.items()} if name in self._f else {}

    @property
    def resampling(self) -> dict[str, Any]:
        """``{"input_rate_hz", "model_rate_hz", "resampled"}``: the rate of the session, the model's step rate, and
        whether the readings were resampled before encoding (schema 1: 1 kHz, 1 kHz, False)."""
        rate = self.layout.sample_rate_hz
        with _reading(self.path, "the rate attributes"):
            return {"input_rate_hz": float(self.attrs.get("input_rate_hz", rate)),
                    "model_rate_hz": float(self.attrs.get("model_rate_hz", self.parameters.get("fs_hz", rate))),
                    "resampled": bool(self.attrs.get("resampled", False))}

    # -- lifetime ------------------------------------------------------------------------------------------------
    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> "EncodedFile":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return (f"EncodedFile({str(self.path)!r}, schema {self.schema_version}, {self.layout.shape_text} @ "
                f"{self.layout.sample_rate_hz:g} Hz, variants {list(self.variants)})")


def open_encoded(path: str | os.PathLike[str]) -> EncodedFile:
    """Open an encoded file for reading (any schema; see the module docstring).

    Raises
    ------
    FileNotFoundError
        No such file.
    NotEncodedError (a ValueError)
        Not HDF5, or no ``/features`` (e.g. a session file: the message says to run ``rigctl encode``), or no
        ``/trials``, or a schema newer than this rigctl reads, or malformed contents (truncated, damaged, a
        ``/trials`` table with repeated ids or unknown labels, a layout or texture set that does not parse).
        :meth:`EncodedFile.features`, :meth:`~EncodedFile.spikes` and :meth:`~EncodedFile.normalisation` check
        their arrays' shapes and types against ``/trials`` and the layout when read, and raise it too.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    try:
        f = h5py.File(path, "r")
    except (OSError, ValueError, RuntimeError) as exc:
        raise NotEncodedError(f"{path} is not an HDF5 file ({' '.join(str(exc).split())[:160]})") from None
    try:
        with _reading(path, "the file's top level"):
            has_features = "features" in f
            session_like = "plan" in f or "trials" in f
            version = int(np.asarray(_attr_value(f.attrs.get("schema_version", 1))).reshape(-1)[0])
        if not has_features:
            kind = "a session file (raw taxel readings)" if session_like else "not an encoded file"
            raise NotEncodedError(f"{path} is {kind}: it has no /features; run `rigctl encode {path}` first")
        if version > ENCODED_SCHEMA_VERSION:
            raise NotEncodedError(f"{path} is an encoded file of schema {version}; this rigctl reads up to "
                                  f"{ENCODED_SCHEMA_VERSION} (upgrade rigctl)")
        return EncodedFile(path, f)
    except BaseException:
        f.close()
        raise
