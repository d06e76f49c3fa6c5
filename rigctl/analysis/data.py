"""Feature sets for the analyses, read through :mod:`rigctl.storage.encoded` (the one reader of encoded files).

An encoded file (``rigctl encode`` output; format and variant registry in :mod:`rigctl.storage.encoded`) holds, per
variant, a ``(n_trials, n_features)`` float32 matrix of spiking features, the per-trial labels (texture, group,
speed, force, profile), the sensor layout (:class:`rigctl.core.SensorLayout`) and the texture set
(:class:`rigctl.core.TextureSet`). :func:`load_features` turns it into a :class:`FeatureSet`, which carries the
layout (the spike-train count per trial: SA/RA x the layout's channels) and the texture set (stable texture codes and
the groups of the groups task; data whose set has no groups is refused by that task).

A *session* file (raw taxel readings, docs/session-format.md) is not an encoded file: :func:`load_features` raises
:class:`NotEncodedError` naming the command to run (``rigctl encode``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rigctl.core import SensorLayout, TextureSet, TextureSetError, texture_set_from_labels
from rigctl.storage import encoded as _encoded

log = logging.getLogger(__name__)

__all__ = [
    "VARIANTS",
    "VARIANT_TITLES",
    "FeatureSet",
    "NotEncodedError",
    "GroupsError",
    "load_features",
    "list_variants",
    "is_encoded_file",
    "REALTIME_VARIANTS",
    "remove_baseline",
    "default_variants",
    "variant_title",
    "n_spike_trains",
]


#: the paper's four feature variants, in Table 1's column order (the registry of rigctl.storage.encoded)
VARIANTS: tuple[str, ...] = tuple(_encoded.MAIN_VARIANTS)
#: variant -> the paper's name for it (Table 1 / Fig. 3 legends), from the same registry
VARIANT_TITLES: dict[str, str] = _encoded.VARIANT_TITLES
#: the real-time variants of the registry (top-layer SA trains, Methods real-time)
REALTIME_VARIANTS: tuple[str, ...] = tuple(_encoded.REALTIME_VARIANTS)

NotEncodedError = _encoded.NotEncodedError


class GroupsError(ValueError):
    """The groups task was asked for on data whose texture set defines no groups."""


def variant_title(name: str) -> str:
    """The paper's name of a variant (``"speed_scaled"`` -> ``"Speed Scaled"``); the name itself if unregistered."""
    return VARIANT_TITLES.get(name, name)


def _text(values):
    a = np.asarray(values)
    if a.dtype.kind in "SO":
        return np.array([v.decode() if isinstance(v, bytes) else str(v) for v in a.ravel()], dtype=object).reshape(
            a.shape
        ).astype(str)
    return a.astype(str) if a.dtype.kind != "U" else a


def n_spike_trains(variant: str, layout: SensorLayout) -> int:
    """Spike trains per trial of a variant for a sensor: SA and RA per channel (``2 * layout.n_channels``: 36 for the
    paper's 18 taxels), or the top layer's SA trains for the real-time variants (9 for the paper's sensor; Methods,
    real-time)."""
    if variant in REALTIME_VARIANTS or variant.startswith("realtime"):
        return len(layout.layer_channels(0))
    return 2 * layout.n_channels


@dataclass
class FeatureSet:
    """Feature matrices of several variants over the same trials, plus the trial labels, sensor and texture set.

    Attributes
    ----------
    features : dict[str, ndarray]
        variant -> ``(n_trials, n_features)`` float32 (spike rates in spikes/s and spike counts per window);
        ``n_features = n_spike_trains(variant, layout) * n_windows``, train-major.
    texture : ndarray (n_trials,) str
    speed_mm_s : ndarray (n_trials,) float64
        Drum surface speed in mm/s (nominal; ramp trials: mean speed); NaN when unknown.
    force_g : ndarray (n_trials,) float64
        Force setpoint in g; NaN when unknown.
    group : ndarray (n_trials,) str or None
        Texture group per trial, from the texture set's groups; None when the set defines none (the groups task
        then refuses the data).
    profile : ndarray (n_trials,) str or None
        Velocity-profile name for ramp trials (real-time analysis), else None.
    trial_id : ndarray (n_trials,) int64
    source : str
        Where it came from (file path or "synthetic").
    attrs : dict, the encoded file's attributes.
    layout : SensorLayout or None
        The sensor the features were encoded from (channel count -> spike trains per trial); None if unknown.
    textures : TextureSet
        The texture set (codes = positions in the set; groups). Default: the set of the distinct labels
        (:func:`rigctl.core.texture_set_from_labels`), with groups from ``group`` when given.
    recording : ndarray (n_trials,) str or None
        The source recording of each trial (an imported session's file); None when the trials carry none (a session
        recorded here: the session is the one recording).
    recording_start_s : ndarray (n_trials,) float64 or None
        Where in its recording each trial starts, s (the order of time blocks); None with ``recording``.

    Raises
    ------
    ValueError
        Arrays of different lengths, or a label not in ``textures``.
    """

    features: dict
    texture: np.ndarray
    speed_mm_s: np.ndarray
    force_g: np.ndarray
    group: np.ndarray | None = None
    profile: np.ndarray | None = None
    # None (the default) is replaced in __post_init__: never None on an instance
    trial_id: np.ndarray = None  # type: ignore[assignment]
    source: str = "memory"
    attrs: dict = field(default_factory=dict)
    layout: SensorLayout | None = None
    textures: TextureSet = None  # type: ignore[assignment]  # as trial_id
    recording: np.ndarray | None = None
    recording_start_s: np.ndarray | None = None

    def __post_init__(self):
        self.texture = _text(self.texture)
        n = len(self.texture)
        self.speed_mm_s = np.asarray(self.speed_mm_s, dtype=np.float64)
        self.force_g = np.asarray(self.force_g, dtype=np.float64)
        if self.group is not None:
            self.group = _text(self.group)
            if not np.any(self.group != ""):  # no group labels (e.g. FabricSlide fabrics)
                self.group = None
        if self.textures is None:
            if self.group is not None:  # groups given per trial, no set: make the set from them
                pairs = dict(zip(self.texture.tolist(), self.group.tolist()))
                groups: dict = {}
                for lab in sorted(pairs):
                    groups.setdefault(pairs[lab], []).append(lab)
                self.textures = texture_set_from_labels(pairs, groups=groups) if all(groups) else \
                    texture_set_from_labels(pairs)
            else:
                self.textures = texture_set_from_labels(self.texture.tolist())
        missing = sorted(set(self.texture.tolist()) - set(self.textures.labels))
        if missing:
            raise ValueError(f"textures {missing[:10]} are not in the texture set {self.textures!r}")
        # the groups come from the set (one source of truth); a set without groups -> no groups task
        if self.textures.has_groups:
            of = {s.label: s.group for s in self.textures}
            self.group = np.array([of[t] for t in self.texture.tolist()], dtype=str)
        else:
            self.group = None
        if self.profile is not None:
            self.profile = _text(self.profile)
        self.trial_id = np.arange(n, dtype=np.int64) if self.trial_id is None else np.asarray(self.trial_id)
        for name, arr in self.features.items():
            if arr.ndim != 2 or arr.shape[0] != n:
                raise ValueError(f"features '{name}' has shape {arr.shape}; expected ({n}, n_features)")
        if self.recording is not None:
            self.recording = _text(self.recording)
            self.recording_start_s = (np.zeros(n) if self.recording_start_s is None
                                      else np.asarray(self.recording_start_s, dtype=np.float64))
        else:
            self.recording_start_s = None
        for name in ("speed_mm_s", "force_g", "trial_id", *(("recording", "recording_start_s")
                                                            if self.recording is not None else ())):
            if len(getattr(self, name)) != n:
                raise ValueError(f"{name} has {len(getattr(self, name))} entries for {n} trials")

    @property
    def n_trials(self) -> int:
        return len(self.texture)

    @property
    def variants(self) -> list[str]:
        """Variants present, in Table 1 order first, then any others."""
        return [v for v in VARIANTS if v in self.features] + [v for v in self.features if v not in VARIANTS]

    @property
    def texture_code(self) -> np.ndarray:
        """(n_trials,) int64 texture codes: positions in the texture set (stable across imports)."""
        code = {lab: i for i, lab in enumerate(self.textures.labels)}
        return np.array([code[t] for t in self.texture.tolist()], dtype=np.int64)

    @property
    def texture_classes(self) -> list[str]:
        """Texture labels present, in the set's order (the order of confusion-matrix rows)."""
        present = set(self.texture.tolist())
        return [lab for lab in self.textures.labels if lab in present]

    @property
    def group_classes(self) -> list[str]:
        """Groups present, in the set's order. Raises :class:`GroupsError` when the set has no groups."""
        self.require_groups()
        assert self.group is not None  # require_groups raised otherwise
        present = set(self.group.tolist())
        return [g for g in self.textures.groups if g in present]

    def require_groups(self) -> None:
        """Raise :class:`GroupsError` (one line, naming the set) unless every texture of the set has a group."""
        if self.group is None:
            which = f"the texture set {self.textures.name!r}" if self.textures.name else "the file's texture set"
            raise GroupsError(
                f"{which} ({len(self.textures)} textures: "
                f"{', '.join(self.textures.labels[:8])}{' ...' if len(self.textures) > 8 else ''}) defines no "
                "texture groups, so the groups task has nothing to classify; give the set groups (a protocol's "
                "[texture_set] groups, or `rigctl import --mapping` with groups) or run --task textures")

    def n_spike_trains(self, variant: str) -> int:
        """Spike trains per trial of ``variant``: from the file's ``n_trains`` when recorded, else from the layout
        (:func:`n_spike_trains`). Raises ValueError when neither is known."""
        per_variant = self.attrs.get("n_trains")
        if isinstance(per_variant, dict) and variant in per_variant:
            return int(per_variant[variant])
        if self.layout is not None:
            return n_spike_trains(variant, self.layout)
        raise ValueError(f"the number of spike trains of '{variant}' is unknown (no sensor layout): pass it "
                         "explicitly (rigctl analyze --channels N)")

    def without_baseline(self, n_trains: int | None = None) -> "FeatureSet":
        """A copy with :func:`remove_baseline` applied to every variant (spike trains from the layout, or
        ``n_trains`` for every variant)."""
        out = self.subset(slice(None))
        out.features = {v: remove_baseline(x, n_trains or self.n_spike_trains(v)) for v, x in self.features.items()}
        return out

    def subset(self, index) -> "FeatureSet":
        """A FeatureSet of the selected trials (copies); same layout and texture set."""
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
            self.layout,
            self.textures,
            None if self.recording is None else self.recording[index],
            None if self.recording_start_s is None else self.recording_start_s[index],
        )

    def select_textures(self, labels) -> "FeatureSet":
        """The trials of the textures ``labels`` only (``rigctl analyze --textures``), with the texture set cut to
        them (groups kept). Raises ValueError naming a label the data does not hold."""
        labels = list(dict.fromkeys(str(t) for t in labels))
        have = set(self.texture.tolist())
        missing = [t for t in labels if t not in have]
        if missing:
            raise ValueError(f"--textures: {', '.join(missing)} not in the data (it has: "
                             f"{', '.join(self.texture_classes)})")
        out = self.subset(np.isin(self.texture, labels))
        out.textures = self.textures.subset(labels)
        return out


def list_variants(path) -> list[str]:
    """Feature variants stored in an encoded file (empty if it is not one)."""
    try:
        with _encoded.open_encoded(path) as ef:
            return list(ef.variants)
    except (_encoded.NotEncodedError, OSError):
        return []


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
    """True if ``path`` is an encoded file (:func:`rigctl.storage.encoded.is_encoded_file`)."""
    return bool(_encoded.is_encoded_file(path))


def load_features(path, variants=None) -> FeatureSet:
    """Read an encoded file into memory (through :func:`rigctl.storage.encoded.open_encoded`).

    Parameters
    ----------
    path : str or Path
        Encoded HDF5 file (``rigctl encode`` output; unversioned old files too).
    variants : sequence of str, optional
        Variants to read (default: all in the file).

    Returns
    -------
    FeatureSet with the file's sensor layout and texture set.

    Raises
    ------
    FileNotFoundError
        No such file.
    NotEncodedError
        Not an encoded file (e.g. a session file: run ``rigctl encode SESSION`` first), or no ``texture`` column.
    KeyError
        A requested variant is missing.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(path)
    try:
        ef = _encoded.open_encoded(path)
    except _encoded.NotEncodedError as exc:
        raise NotEncodedError(f"{exc} (or pass --encode to encode it on the fly)") from None
    except OSError as exc:
        raise NotEncodedError(f"{path} is not an HDF5 file ({exc})") from exc
    with ef:
        have = list(ef.variants)
        names = have if variants is None else list(variants)
        feats = {}
        for v in names:
            if v not in have:
                raise KeyError(f"variant '{v}' not in {path} (has: {', '.join(have)})")
            feats[v] = np.asarray(ef.features(v), dtype=np.float32)
        cols = dict(ef.trials)
        attrs = dict(ef.attrs)
        attrs["n_trains"] = {v: int(ef.n_trains(v)) for v in names}  # spike trains per trial (remove_baseline)
        layout = ef.layout
        textures = ef.textures
    lossy = attrs.get("lossy_trials")
    if isinstance(lossy, str):  # JSON text
        import json

        lossy = json.loads(lossy)
    if lossy:
        log.warning("%s: %d trials were recorded with lost frames (%s in all; ids in attrs['lossy_trials'])", path,
                    len(lossy), attrs.get("lost_frames", "?"))
    try:  # every column of rigctl.storage.encoded.TRIAL_COLUMNS is there (NaN speed / force when unknown)
        return FeatureSet(
            feats,
            cols["texture"],
            cols["speed_mm_s"],
            cols["force_g"],
            None,  # groups come from the file's texture set
            cols["profile"],
            cols["trial_id"],
            str(path),
            attrs,
            layout,
            textures,
            cols.get("recording"),
            cols.get("recording_start_s"),
        )
    except TextureSetError as exc:
        raise ValueError(f"{path}: {exc}") from None


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
        Number of spike trains per trial (``2 * layout.n_channels``: SA and RA per taxel, 36 for the paper's
        sensor; :meth:`FeatureSet.n_spike_trains` gives it for a variant).

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
