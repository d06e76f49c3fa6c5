"""The encoded file's one writer (:class:`EncodedWriter`), under the output policy of :mod:`rigctl.storage.outputs`.
Re-exported by :mod:`rigctl.storage.encoded`."""

from __future__ import annotations

import json
import math
import os
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from rigctl.core.encoding_model import SPIKE_TICK_RTOL
from rigctl.core.sensor import SensorLayout
from rigctl.core.textures import TextureSet
from rigctl.storage.encoded_format import (
    _TRIALS_DTYPE,
    ENCODED_KIND,
    ENCODED_SCHEMA_VERSION,
    OPTIONAL_TRIAL_COLUMNS,
    VARIANTS,
    _h5_table,
    _json_default,
    _jsonable,
    _per_spike,
    _text,
)
from rigctl.storage.outputs import output_file

#: each dataset's chunk cache while writing (bytes): a few spike-ticks chunks (1 MB) or a features chunk (256 rows)
_CHUNK_CACHE_BYTES = 4 << 20


class EncodedWriter:
    """Writes one encoded file (the layout in the module docstring), under ``<name>.part`` until :meth:`close`
    renames it into place; a writer left by an exception (context manager) removes the part file.

    Parameters
    ----------
    path : the encoded .h5 to write.
    layout : the session's :class:`SensorLayout` (stored as JSON; its rate is the *input* rate of the encoding).
    textures : the session's :class:`TextureSet` (stored as JSON; gives each trial's group).
    trials : mapping with the columns of :data:`TRIAL_COLUMNS` (``group`` optional: taken from ``textures``) and
        any of :data:`OPTIONAL_TRIAL_COLUMNS` (``recording``, ``recording_start_s``),
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
        self._output = output_file(self.path, overwrite=overwrite, kind="encoded")  # the output policy: lock, part file, guard
        self._target = self._output.__enter__()
        self.part = self._target.part
        try:
            # a chunk cache per dataset above one spike-ticks chunk (1 MB, HDF5's default cache size, which holds
            # no chunk that large): a batch's last, partial chunk stays in memory for the next batch's append
            # instead of being written, read back and written again
            self._f = h5py.File(self._target.h5_file(), "w", rdcc_nbytes=_CHUNK_CACHE_BYTES)
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
        extra = [(k, t) for k, t in OPTIONAL_TRIAL_COLUMNS.items() if k in trials]
        names = _TRIALS_DTYPE.names or ()
        out = np.zeros(n, dtype=np.dtype([(k, _TRIALS_DTYPE.fields[k][0]) for k in names] + extra)  # type: ignore[index]
                       if extra else _TRIALS_DTYPE)
        for k, t in extra:
            out[k] = np.array(_text(trials[k]), dtype=object) if t != "<f8" else np.asarray(trials[k], np.float64)
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
        scale = self._scale(idx, n_trains, time_scale)
        if g.attrs.get("ticks_from") is not None:  # the base's ticks and rows: only the scale is this variant's
            self._store_ticks(variant, None, idx, st.size, scale)
            return
        tick_s = float(g.attrs["tick_s"])
        # a scale of 1 (unscaled variants) multiplies nothing: the same numbers without the per-spike array
        per_spike: Any = 1.0 if np.all(scale == 1.0) else _per_spike(scale, idx, n_trains)
        ticks = np.rint(st / (per_spike * tick_s))
        if st.size and (ticks.min() < 0 or ticks.max() > np.iinfo(np.uint32).max
                        or not _on_grid(ticks * tick_s * per_spike, st)):
            raise ValueError(f"{variant}: spike times are not multiples of tick_s = {tick_s:g} s x time_scale")
        self._store_ticks(variant, ticks.astype(np.uint32), idx, st.size, scale)

    def append_spike_ticks(self, variant: str, ticks: np.ndarray, index: np.ndarray, time_scale: Any = None) -> None:
        """Append the next trials' trains already as ticks, in trial order: what :meth:`append_spikes` stores for
        a variant added with ``tick_s``, without converting times (e.g.
        :meth:`rigctl.encoding.spikes.SpikeTrains.hstack_ticks` of the encoder's trains).

        Parameters
        ----------
        ticks : (n_spikes,) uint32 ticks of the variant's ``tick_s``, unscaled (time = ticks x tick_s x
            ``time_scale``); for a ``ticks_from`` variant the base's ticks of the same trials (only their count is
            used: the file stores the base's once).
        index : (n_trials * n_trains,) int64 row ends into ``ticks``.
        time_scale : scalar or (n_trials,) as :meth:`append_spikes` (default 1).

        Raises
        ------
        KeyError if :meth:`add_spikes` was not called for ``variant``; ValueError for a variant stored as float64
        times, ticks that are not uint32, rows that are not a multiple of the train count or do not end at
        ``len(ticks)``, or a ``ticks_from`` variant whose count differs from its base's in this batch.
        """
        g = self._spikes[variant]
        ticks, idx = np.asarray(ticks), np.asarray(index, np.int64)
        if "spike_times" in g or ticks.dtype != np.uint32 or ticks.ndim != 1:
            raise ValueError(f"{variant}: uint32 ticks (n_spikes,) of a variant stored with ticks, got {ticks.dtype} "
                             f"{ticks.shape}")
        n_trains = int(g.attrs["n_trains"])
        if idx.ndim != 1 or idx.size % n_trains or (idx[-1] if idx.size else 0) != ticks.size:
            raise ValueError(f"{variant}: {idx.size} row ends for {n_trains} trains a trial ending at "
                             f"{idx[-1] if idx.size else 0}, not at the {ticks.size} ticks")
        scale = self._scale(idx, n_trains, time_scale)
        self._store_ticks(variant, None if g.attrs.get("ticks_from") is not None else ticks, idx, ticks.size, scale)
        self._target.check()  # a full disk ends the write here, in one line

    @staticmethod
    def _scale(idx: np.ndarray, n_trains: int, time_scale: Any) -> np.ndarray:
        """The per-trial ``time_scale`` (n_trials,) of rows ``idx``."""
        return np.broadcast_to(np.asarray(1.0 if time_scale is None else time_scale, np.float64),
                               (idx.size // n_trains,))

    def _store_ticks(self, variant: str, ticks: np.ndarray | None, idx: np.ndarray, n_spikes: int,
                     scale: np.ndarray) -> None:
        """Append a batch's ``ticks`` and row ends (None: a ``ticks_from`` variant, whose ``n_spikes`` must be its
        base's in this batch) and its per-trial ``scale``."""
        g = self._spikes[variant]
        ticks_from = g.attrs.get("ticks_from")
        if ticks is None:
            if self._batch_spikes.get(str(ticks_from)) != n_spikes:
                raise ValueError(f"{variant}: {n_spikes} spikes in this batch, {ticks_from} had "
                                 f"{self._batch_spikes.get(str(ticks_from))}: not the same trains")
        else:
            base = self._append(g["spike_ticks"], ticks)
            self._append(g["spike_times_index"], idx + base)
            self._batch_spikes[variant] = n_spikes
        self._append(g["time_scale"], np.ascontiguousarray(scale))

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


def _on_grid(back: np.ndarray, times: np.ndarray) -> bool:
    """Every ``back`` (ticks x tick_s x scale) within :data:`~rigctl.core.encoding_model.SPIKE_TICK_RTOL` of
    ``times`` relative (``np.allclose(back, times, rtol=SPIKE_TICK_RTOL, atol=0)`` for the finite times spikes have;
    NaN fails), in place on one temporary."""
    np.subtract(back, times, out=back)
    np.abs(back, out=back)
    return bool(np.all(back <= SPIKE_TICK_RTOL * np.abs(times)))

