"""Feature sets for the analyses: read the encoded file written by :mod:`rigctl.encoding.pipeline`.

Encoded-file layout used here (docs/architecture.md, ``rigctl.encoding.pipeline.encode_session``):

* ``/features/<variant>``: ``(n_trials, n_features)`` float32, variants ``original``, ``speed_scaled``,
  ``force_scaled``, ``speed_force_scaled`` (720 features when speed scaled, 2160 otherwise, for 18 taxels);
* ``/trials``: per-trial labels, either a compound dataset or a group of equal-length column datasets, with at least
  ``texture`` and ``speed_mm_s`` / ``force_g``; ``trial_id``, ``group`` and ``profile`` (velocity-profile name of
  ramp trials, for the real-time analysis) are used when present.

A *session* file (raw taxel readings, docs/session-format.md) has no ``/features`` group: :func:`load_features`
raises :class:`NotEncodedError` naming the command to run (``rigctl encode``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rigctl.texture_set import GROUP_OF

__all__ = [
    "VARIANTS",
    "VARIANT_TITLES",
    "PAPER_GROUPS",
    "FeatureSet",
    "NotEncodedError",
    "load_features",
    "list_variants",
    "is_encoded_file",
    "REALTIME_VARIANTS",
    "remove_baseline",
    "default_variants",
]

#: the four feature variants of the paper, in Table 1's column order
VARIANTS: tuple[str, ...] = ("original", "speed_scaled", "force_scaled", "speed_force_scaled")
#: the paper's names for them (Table 1 / Fig. 3 legends)
VARIANT_TITLES = {
    "original": "Original",
    "speed_scaled": "Speed Scaled",
    "force_scaled": "Force Scaled",
    "speed_force_scaled": "Speed and Force Scaled",
    "force_scaled_label_free": "Force Scaled (label-free)",
    "speed_force_scaled_label_free": "Speed+Force Scaled (label-free)",
    "realtime_original": "Original (real-time)",
    "realtime_speed_scaled": "Speed Scaled (real-time)",
}
#: the real-time features of the encoding pipeline (9 top-layer SA trains x 20 windows, Methods real-time)
REALTIME_VARIANTS: tuple[str, ...] = ("realtime_original", "realtime_speed_scaled")
#: the paper's texture groups by letter (Fig. 2B): A smooth; B-F circular ridges; G-K rectangular ridges; L-P waves.
#: Used only when ``/trials`` carries no ``group`` column.
#: letter -> texture group of the paper (Fig. 2B)
PAPER_GROUPS = GROUP_OF


class NotEncodedError(ValueError):
    """The file is a session file (raw readings) or something else without ``/features``: run ``rigctl encode``."""


def _text(values):
    a = np.asarray(values)
    if a.dtype.kind in "SO":
        return np.array([v.decode() if isinstance(v, bytes) else str(v) for v in a.ravel()], dtype=object).reshape(
            a.shape
        ).astype(str)
    return a


@dataclass
class FeatureSet:
    """Feature matrices of several variants over the same trials, plus the trial labels.

    Attributes
    ----------
    features : dict[str, ndarray]
        variant -> ``(n_trials, n_features)`` float32 (spike rates in spikes/s and spike counts per 100 ms window).
    texture : ndarray (n_trials,) str
    speed_mm_s : ndarray (n_trials,) float64
        Drum surface speed in mm/s (nominal; ramp trials: mean speed).
    force_g : ndarray (n_trials,) float64
        Force setpoint in g.
    group : ndarray (n_trials,) str or None
    profile : ndarray (n_trials,) str or None
        Velocity-profile name for ramp trials (real-time analysis), else None.
    trial_id : ndarray (n_trials,) int64
    source : str
        Where it came from (file path or "synthetic").
    """

    features: dict
    texture: np.ndarray
    speed_mm_s: np.ndarray
    force_g: np.ndarray
    group: np.ndarray | None = None
    profile: np.ndarray | None = None
    trial_id: np.ndarray | None = None
    source: str = "memory"
    attrs: dict = field(default_factory=dict)

    def __post_init__(self):
        self.texture = _text(self.texture)
        n = len(self.texture)
        self.speed_mm_s = np.asarray(self.speed_mm_s, dtype=np.float64)
        self.force_g = np.asarray(self.force_g, dtype=np.float64)
        if self.group is None and len(self.texture) and set(np.unique(self.texture)) <= set(PAPER_GROUPS):
            self.group = np.array([PAPER_GROUPS[t] for t in self.texture])
        if self.group is not None:
            self.group = _text(self.group)
            if not np.any(self.group != ""):  # no group labels (e.g. FabricSlide fabrics)
                self.group = None
        if self.profile is not None:
            self.profile = _text(self.profile)
        self.trial_id = np.arange(n, dtype=np.int64) if self.trial_id is None else np.asarray(self.trial_id)
        for name, arr in self.features.items():
            if arr.ndim != 2 or arr.shape[0] != n:
                raise ValueError(f"features '{name}' has shape {arr.shape}; expected ({n}, n_features)")
        for name in ("speed_mm_s", "force_g", "trial_id"):
            if len(getattr(self, name)) != n:
                raise ValueError(f"{name} has {len(getattr(self, name))} entries for {n} trials")

    @property
    def n_trials(self) -> int:
        return len(self.texture)

    @property
    def variants(self) -> list[str]:
        """Variants present, in Table 1 order first, then any others."""
        return [v for v in VARIANTS if v in self.features] + [v for v in self.features if v not in VARIANTS]

    def subset(self, index) -> "FeatureSet":
        """A FeatureSet of the selected trials (copies)."""
        return FeatureSet(
            {k: v[index] for k, v in self.features.items()},
            self.texture[index],
            self.speed_mm_s[index],
            self.force_g[index],
            None if self.group is None else self.group[index],
            None if self.profile is None else self.profile[index],
            self.trial_id[index],
            self.source,
            dict(self.attrs),
        )


def list_variants(path) -> list[str]:
    """Feature variants stored under ``/features`` of an encoded file (empty if none)."""
    import h5py

    with h5py.File(path, "r") as f:
        return list(f["features"]) if "features" in f else []


def default_variants(available, task="table1") -> list[str]:
    """Variants analysed when none are asked for: the real-time ones for ``task="realtime"`` (else original /
    speed_scaled), otherwise the paper's four (Table 1 order), else everything available."""
    available = list(available)
    if task == "realtime":
        rt = [v for v in REALTIME_VARIANTS if v in available]
        return rt or [v for v in ("original", "speed_scaled") if v in available] or available
    main = [v for v in VARIANTS if v in available]
    return main or available


def is_encoded_file(path) -> bool:
    """True if ``path`` is an HDF5 file with a ``/features`` group (an encoded file)."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            return "features" in f
    except OSError:
        return False


def _read_trials(obj):
    """Columns of ``/trials`` as a dict of arrays (compound dataset or group of datasets)."""
    import h5py

    if isinstance(obj, h5py.Group):
        return {k: obj[k][()] for k in obj if isinstance(obj[k], h5py.Dataset)}
    data = obj[()]
    if data.dtype.names is None:
        raise ValueError("/trials is neither a compound dataset nor a group of columns")
    return {k: data[k] for k in data.dtype.names}


def load_features(path, variants=None) -> FeatureSet:
    """Read an encoded file into memory.

    Parameters
    ----------
    path : str or Path
        Encoded HDF5 file (``rigctl encode`` output).
    variants : sequence of str, optional
        Variants to read (default: all under ``/features``).

    Returns
    -------
    FeatureSet

    Raises
    ------
    FileNotFoundError
        No such file.
    NotEncodedError
        The file has no ``/features`` group (e.g. a session file: run ``rigctl encode SESSION`` first).
    KeyError
        A requested variant or a required ``/trials`` column (``texture``) is missing.
    """
    import h5py

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(path)
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise NotEncodedError(f"{path} is not an HDF5 file ({exc})") from exc
    with f:
        if "features" not in f:
            kind = "a session file (raw taxel readings)" if ("trials" in f or "plan" in f) else "not an encoded file"
            raise NotEncodedError(
                f"{path} is {kind}: it has no /features. Run `rigctl encode {path}` first "
                "(or pass --encode to encode it on the fly)."
            )
        names = list(f["features"]) if variants is None else list(variants)
        feats = {}
        for v in names:
            if v not in f["features"]:
                raise KeyError(f"variant '{v}' not in {path} (has: {', '.join(f['features'])})")
            feats[v] = np.asarray(f["features"][v][()], dtype=np.float32)
        if "trials" not in f:
            raise KeyError(f"{path} has no /trials labels table")
        cols = _read_trials(f["trials"])
        attrs = {k: (v.item() if hasattr(v, "item") and np.ndim(v) == 0 else v) for k, v in f.attrs.items()}
        # spike trains per trial of each variant (for remove_baseline), from /spikes/<variant> attrs
        attrs["n_trains"] = {v: int(f["spikes"][v].attrs["n_trains"]) for v in names
                             if "spikes" in f and v in f["spikes"] and "n_trains" in f["spikes"][v].attrs}
    if "texture" not in cols:
        raise KeyError(f"/trials of {path} has no 'texture' column (has: {', '.join(cols)})")
    n = len(cols["texture"])
    nan = np.full(n, np.nan)
    return FeatureSet(
        feats,
        cols["texture"],
        cols.get("speed_mm_s", nan),
        cols.get("force_g", nan),
        cols.get("group"),
        cols.get("profile"),
        cols.get("trial_id"),
        str(path),
        attrs,
    )


def remove_baseline(features, n_channels):
    """Remove each trial's per-channel level: subtract, per spike train, its mean over the time windows.

    The FabricSlide README warns that the steady per-taxel level separates the fabrics on its own; this keeps only
    the temporal modulation of each spike train. Zero-padded windows (unscaled trials shorter than the longest) are
    left at zero and excluded from the mean.

    Parameters
    ----------
    features : ndarray (n_trials, n_channels * n_windows)
        Channel-major layout (all windows of spike train 0, then of train 1, ...), as written by
        ``rigctl.encoding.features.spike_features``.
    n_channels : int
        Number of spike trains per trial (36 for 18 taxels x SA/RA).

    Returns
    -------
    ndarray, same shape, float32

    Raises
    ------
    ValueError
        If the feature count is not a multiple of ``n_channels``.
    """
    x = np.asarray(features, dtype=np.float32)
    if x.shape[1] % n_channels:
        raise ValueError(f"{x.shape[1]} features are not a multiple of {n_channels} channels")
    w = x.reshape(x.shape[0], n_channels, -1)
    valid = np.any(x.reshape(x.shape[0], n_channels, -1) != 0, axis=1, keepdims=True)  # window present in trial
    cnt = np.maximum(valid.sum(axis=2, keepdims=True), 1)
    mean = (w * valid).sum(axis=2, keepdims=True) / cnt
    return ((w - mean) * valid).reshape(x.shape).astype(np.float32)
