"""Encoded files: the one writer and the one reader of what ``rigctl encode`` produces (HDF5, h5py).

An encoded file holds, for every encoded trial of a session, the spiking features of each variant, optionally the
SA/RA spike trains, the per-taxel normalisation and the force coefficients (paper eqs. 1-5; Fig. 1B). It is written
by :func:`rigctl.encoding.pipeline.encode_session` through :class:`EncodedWriter` and read by the analyses, the
GUI and ``rigctl`` commands through :func:`open_encoded` (nobody else opens it with h5py).

Layout (schema :data:`ENCODED_SCHEMA_VERSION` = 3)::

    /trials                  compound table, one row per trial: trial_id u4, texture (variable-length UTF-8),
                             group (variable-length UTF-8, "" when the texture set has none), speed_mm_s f4 (NaN
                             when unknown), force_g f4 (NaN when unknown), profile (VL UTF-8), duration_s f4,
                             n_samples u4 (samples at the session's own rate); an imported session's trials also
                             recording (VL UTF-8: the source file) and recording_start_s f8 (where in it the trial
                             starts), optional columns every reader passes through (OPTIONAL_TRIAL_COLUMNS)
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
           source_session, encode_seconds, force_coefficients*_note / _n_not_converged / _n_coefficients,
           operator_paced (bool: the trials' lengths are the operator's, a handheld session's scans; the length
           warning of rigctl.encoding.lengths reads it)

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

import json
import os
from pathlib import Path
from typing import Any, cast

import h5py
import numpy as np

from rigctl.core.encoding_model import MODEL_RATE_HZ
from rigctl.core.sensor import SensorLayout
from rigctl.core.textures import PAPER_TEXTURES, TextureSet, texture_set_from_labels
from rigctl.storage.encoded_format import (
    ALL_VARIANTS,
    ENCODED_KIND,
    ENCODED_SCHEMA_VERSION,
    ENCODED_SUFFIX,
    LABEL_FREE_VARIANTS,
    MAIN_VARIANTS,
    REALTIME_VARIANTS,
    TRIAL_COLUMNS,
    VARIANT_TITLES,
    VARIANTS,
    NotEncodedError,
    SpikeArrays,
    VariantInfo,
    _attr_value,
    _damaged,
    _per_spike,
    _reading,
    _str_table,
    _text,
    _variant_order,
    is_encoded_file,
    variant_info,
)
from rigctl.storage.encoded_writer import EncodedWriter

__all__ = [
    "ENCODED_SCHEMA_VERSION", "ENCODED_KIND", "ENCODED_SUFFIX", "VariantInfo", "VARIANTS", "VARIANT_TITLES", "MAIN_VARIANTS",
    "LABEL_FREE_VARIANTS", "REALTIME_VARIANTS", "ALL_VARIANTS", "variant_info", "EncodedWriter", "EncodedFile",
    "open_encoded", "is_encoded_file", "NotEncodedError", "TRIAL_COLUMNS", "SpikeArrays",
]


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
        rate = float(self.parameters.get("fs_hz", MODEL_RATE_HZ) or MODEL_RATE_HZ)
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
        raw, tick_s, scale, index, n_trains = self.spikes_stored(variant, trials)
        if tick_s is None:
            times = np.asarray(raw, np.float64)
        else:
            times = raw.astype(np.float64) * tick_s  # the encoder's own operations: bit-identical times
        if scale is not None and np.any(scale != 1.0):
            times *= _per_spike(scale, index, n_trains)
        return SpikeArrays(times, index, n_trains)

    def spike_index(self, variant: str) -> tuple[np.ndarray, int]:
        """``(spike_times_index, n_trains)`` of a variant (every trial), without reading or decoding its spike times
        (a paper-size variant holds ~10^8 spikes: 0.9 GB as float64 seconds). Errors as :meth:`spikes`."""
        _, _, _, index, n_trains = self.spikes_stored(variant, times=False)
        return index, n_trains

    def spikes_stored(self, variant: str, trials: slice | None = None, *, times: bool = True
                      ) -> tuple[np.ndarray, float | None, np.ndarray | None, np.ndarray, int]:
        """A variant's spike trains as stored, not yet decoded to seconds (what :meth:`spikes` decodes; a tick grid
        holds them in 4 bytes a spike instead of 8): ``(raw, tick_s, time_scale, index, n_trains)``. Schema 3 ticks:
        ``raw`` uint32 ticks, the time of a spike of trial ``t`` is ``raw * tick_s * time_scale[t]`` (``time_scale``
        (n_trials,) float64 or None: 1); float times (``tick_s`` None): ``raw`` s. ``index`` int64 row ends into
        ``raw``. ``trials`` and the errors as :meth:`spikes`. ``times`` False: ``raw`` is empty (the index only)."""
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
            raw = times_ds[s0:s1] if times else times_ds[s0:s0]
            scale = None
            if scale_ds is not None:
                if scale_ds.shape[0] != self.n_trials:
                    raise _damaged(self.path, f"/spikes/{variant} has {scale_ds.shape[0]} time scales, not "
                                              f"{self.n_trials}")
                scale = np.asarray(scale_ds[t0:t1], np.float64)
        return raw, tick_s, scale, index - s0, n_trains

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

