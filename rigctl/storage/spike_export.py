"""Spike trains and readings where spiking-network labs load them: events in Tonic's layout, and the per-trial layout
of a peer lab's public texture pipeline (``rigctl export events``, ``rigctl export trials``; docs/spiking-networks.md).

Written with numpy only: rigctl depends on no GPL/AGPL event library (Tonic is GPLv3), the files are plain ``.npz``
and ``.csv`` any of them reads.

**Events** (``export_events``): one ``trial_<id>.npz`` per trial (``numpy.savez``), holding

- ``events``: a structured array with fields ``x``, ``y``, ``t``, ``p`` (all int64), sorted by ``t`` then ``x``,
  ``y``, ``p``: Tonic's event layout (its datasets' ``dtype([("x", int), ("y", int), ("t", int), ("p", int)])``, time
  in microseconds; tonic.readthedocs.io, "Events"), one event per spike of the trial:
    - ``t``: the spike's time from the trial's first sample, microseconds (the encoded file's time in s x 1e6,
      rounded to the nearest microsecond: the encoder's step is 1 ms, so the rounding is < 0.1 % of a step; the
      largest rounding of the file is in the manifest as ``t_rounding_max_us``), in the variant's time base
      (``time_base``: ``real time``, or ``speed-scaled`` for a speed-scaled variant, eq. 2: real time x the trial's
      speed / the reference speed, so a 40 mm/s trial of 1 s ends at 0.333 s);
    - ``x``: the taxel within its layer (row-major: ``row * cols + col``, :meth:`SensorLayout.channel_position`);
    - ``y``: the layer (0 = top, the paper's type I; 1 = bottom, type II);
    - ``p``: the neuron type, SA = 0, RA = 1 (eqs. 3-5);
- ``sensor_size``: int64 ``(taxels per layer (the largest layer), layers, 2)``: Tonic's ``(W, H, P)``;
- the labels: ``texture`` (str), ``texture_code`` (its position in the texture set), ``speed_mm_s``, ``force_g``
  (float64; NaN when unknown), ``repeat`` (0-based, the trial's rank among the trials of its texture, speed and force
  in trial-id order), ``session`` (the session file's name), ``trial_id``, ``variant``, ``profile`` (the velocity
  profile's name, e.g. ``slow-to-fast``; ``constant`` for a trial at one speed), ``time_base`` and ``duration_s``
  (the trial's duration in that time base; ``duration_real_s`` in real time).

**Per-trial layout** (``export_trials``): the peer lab's naming, one trial a file:
``Data[Texture(NNN)][Speed(S)][Force(F)][Trial(k)].csv`` (taxel readings: a header of the channel labels, one row a
sample, ADC counts) and/or ``SpikeTrains[...].npz`` (``spikes``: uint8 ``(T, C)`` spike counts per model step (1 ms;
the count, not a 0/1 flag, so a speed-scaled variant's denser steps lose nothing), ``C`` = the trains: SA of taxels
0..n-1 then RA; ``trains``: their names), ``NNN`` the texture's code (3 digits), ``S`` / ``F`` as ``%g``, ``k`` the
repeat; a velocity-profile session's names add ``[Profile(name)]`` before ``[Trial(k)]`` (the repeat then counts
within texture, speed, force and profile), so that no two trials share a name. ``rigctl_import.toml`` beside the
CSVs imports them back (``rigctl import DIR/*.csv --mapping DIR/rigctl_import.toml``: rate, sensor, texture set, and
the label pattern that reads speed, force, profile and repeat from the names; each file's texture label in its
``[files]`` table).

Each export folder carries its manifest (:mod:`rigctl.storage.export_folder`) and, when the lead command gives it,
``splits.json`` (:func:`write_splits`).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rigctl.core.progress import ProgressCallback, Stage
from rigctl.core.sensor import SensorLayout
from rigctl.core.textures import TextureSet
from rigctl.core.trial import has_profiles
from rigctl.storage.encoded import REALTIME_VARIANTS, VARIANTS, EncodedFile, open_encoded
from rigctl.storage.export_folder import FolderOutput, folder_output

__all__ = ["EVENT_DTYPE", "EVENTS_KIND", "TRIALS_KIND", "SPLITS_NAME", "LAYOUTS", "ExportSummary", "TrialLabels",
           "export_events", "export_trials", "read_events", "trial_file_name", "write_splits", "default_variant"]

#: Tonic's event layout (module docstring)
EVENT_DTYPE = np.dtype([("x", "<i8"), ("y", "<i8"), ("t", "<i8"), ("p", "<i8")])
#: the manifests' kinds
EVENTS_KIND = "rigctl spike events"
TRIALS_KIND = "rigctl per-trial export"
#: the splits file beside an export
SPLITS_NAME = "splits.json"
#: ``export_trials``' layouts
LAYOUTS = ("per-trial-csv", "per-trial-npz")
#: the import mapping beside a per-trial CSV export
IMPORT_MAPPING_NAME = "rigctl_import.toml"
#: the label pattern of the peer lab's names (``rigctl import --label-pattern``); the texture is each file's own
LABEL_PATTERN = "Data[Texture({texture_code})][Speed({speed_mm_s})][Force({force_g})][Trial({repeat})].csv"
#: the same with the velocity profile (a profile session's export)
PROFILE_LABEL_PATTERN = ("Data[Texture({texture_code})][Speed({speed_mm_s})][Force({force_g})][Profile({profile})]"
                         "[Trial({repeat})].csv")
#: the events' time bases (``time_base``): a speed-scaled variant's spike times are eq. 2's scaled times
REAL_TIME, SPEED_SCALED_TIME = "real time", "speed-scaled"


@dataclass(frozen=True)
class TrialLabels:
    """Per-trial labels of an export, in trial order: ``trial_id`` int64, ``texture`` str, ``texture_code`` int64,
    ``speed_mm_s`` / ``force_g`` float64 (NaN unknown), ``repeat`` int64, ``duration_s`` float64 (real time),
    ``profile`` str (the velocity profile; ``""`` unknown)."""

    trial_id: np.ndarray
    texture: np.ndarray
    texture_code: np.ndarray
    speed_mm_s: np.ndarray
    force_g: np.ndarray
    repeat: np.ndarray
    duration_s: np.ndarray
    profile: np.ndarray

    @property
    def has_profiles(self) -> bool:
        """A velocity-profile session (any profile but ``constant`` / unknown): names carry the profile."""
        return has_profiles(self.profile)

    @classmethod
    def of(cls, trial_id: Sequence[int] | np.ndarray, texture: Sequence[str] | np.ndarray,
           labels: Sequence[str], speed_mm_s: Sequence[float] | np.ndarray, force_g: Sequence[float] | np.ndarray,
           duration_s: Sequence[float] | np.ndarray, repeat: Sequence[int] | np.ndarray | None = None,
           profile: Sequence[str] | np.ndarray | None = None) -> "TrialLabels":
        """From the columns; ``labels`` is the texture set's order (codes); ``repeat`` None: each trial's rank
        among its (texture, speed, force, profile) cell in trial-id order; ``profile`` None: unknown (``""``)."""
        ids = np.asarray(trial_id, np.int64)
        tex = np.asarray(texture).astype(str)
        spd = np.asarray(speed_mm_s, np.float64)
        frc = np.asarray(force_g, np.float64)
        prof = np.full(ids.shape, "", dtype=object) if profile is None else np.asarray(profile)
        prof = np.asarray([str(p) for p in prof.ravel()], dtype=str) if prof.size else np.zeros(0, str)
        code_of = {lab: i for i, lab in enumerate(labels)}
        codes = np.asarray([code_of[t] for t in tex], np.int64)
        if repeat is None:
            seen: dict[tuple[str, str, str, str], int] = {}
            rep = np.zeros(ids.size, np.int64)
            for i in np.argsort(ids, kind="stable"):
                key = (tex[i], repr(float(spd[i])), repr(float(frc[i])), str(prof[i]))
                rep[i] = seen.get(key, 0)
                seen[key] = int(rep[i]) + 1
        else:
            rep = np.asarray(repeat, np.int64)
        return cls(ids, tex, codes, spd, frc, rep, np.asarray(duration_s, np.float64), prof)


@dataclass
class ExportSummary:
    """What an export wrote: ``out`` (the folder), ``n_trials``, ``n_files``, ``n_spikes`` (events), ``variant``,
    ``notes`` (lines for the user)."""

    out: Path
    n_trials: int = 0
    n_files: int = 0
    n_spikes: int = 0
    variant: str | None = None
    notes: list[str] = field(default_factory=list)


def _num(x: float) -> str:
    return "nan" if math.isnan(x) else f"{x:g}"


def trial_file_name(prefix: str, code: int, speed_mm_s: float, force_g: float, repeat: int, suffix: str,
                    profile: str = "") -> str:
    """The peer lab's per-trial name: ``Data[Texture(003)][Speed(80)][Force(500)][Trial(2)].csv``; with a
    ``profile``, ``...[Force(500)][Profile(slow-to-fast)][Trial(2)].csv``."""
    named = f"[Profile({profile})]" if profile else ""
    return (f"{prefix}[Texture({int(code):03d})][Speed({_num(float(speed_mm_s))})][Force({_num(float(force_g))})]"
            f"{named}[Trial({int(repeat)})]{suffix}")


def default_variant(enc: EncodedFile) -> str:
    """The variant exported when none is named: Original when its trains are stored, else the first stored one.
    Raises KeyError when the file stores no spike trains (encoded with ``--no-spikes``)."""
    if not enc.spike_variants:
        raise KeyError(f"{enc.path} stores no spike trains (encoded with --no-spikes?): encode it again with them")
    return "original" if "original" in enc.spike_variants else enc.spike_variants[0]


def _train_map(enc: EncodedFile, variant: str) -> tuple[np.ndarray, np.ndarray]:
    """Per train of ``variant``: its channel and its neuron type (SA 0, RA 1). Raises KeyError for a variant whose
    trains are not SA then RA of every taxel (the real-time variants' taxel subsets)."""
    n_ch = enc.layout.n_channels
    n_trains = enc.n_trains(variant)
    if variant in REALTIME_VARIANTS or n_trains != 2 * n_ch:
        raise KeyError(f"variant {variant!r} holds {n_trains} trains, not SA and RA of the {n_ch} taxels: export "
                       f"one of {', '.join(v for v in enc.spike_variants if v not in REALTIME_VARIANTS)}")
    ch = np.concatenate([np.arange(n_ch), np.arange(n_ch)]).astype(np.int64)
    return ch, np.repeat(np.asarray([0, 1], np.int64), n_ch)


def encoded_labels(enc: EncodedFile) -> TrialLabels:
    """The labels of an encoded file's trials (:class:`TrialLabels`)."""
    t = enc.trials
    return TrialLabels.of(t["trial_id"], t["texture"], enc.textures.labels, t["speed_mm_s"], t["force_g"],
                          t["duration_s"], profile=t["profile"])


def _session_name(enc: EncodedFile) -> str:
    src = str(enc.attrs.get("source_session", "") or "")
    return Path(src).name if src else enc.path.name


def export_events(encoded_path: str | os.PathLike[str], out_dir: str | os.PathLike[str], *,
                  variant: str | None = None, overwrite: bool = False,
                  extra_files: Mapping[str, Callable[[Path], None]] | None = None,
                  progress: ProgressCallback | None = None) -> ExportSummary:
    """Every trial's spike trains of ``variant`` as events in Tonic's layout (module docstring), one ``.npz`` a
    trial in the new folder ``out_dir``.

    ``extra_files``: ``{name: write(path)}`` written into the same folder (the lead command's ``splits.json``).
    Raises KeyError (no such variant / no stored trains), :class:`rigctl.storage.outputs.OutputError` (the folder),
    :class:`rigctl.storage.encoded.NotEncodedError`.
    """
    with open_encoded(encoded_path) as enc:
        variant = variant or default_variant(enc)
        if variant not in enc.spike_variants:
            raise KeyError(f"no spike trains of {variant!r} in {enc.path} (stored: "
                           f"{', '.join(enc.spike_variants) or 'none'})")
        channel, polarity = _train_map(enc, variant)
        layout = enc.layout
        pos = np.asarray([layout.channel_position(c) for c in range(layout.n_channels)], np.int64)
        x_of = pos[:, 1] * np.asarray([layout.layers[li].cols for li in pos[:, 0]], np.int64) + pos[:, 2]
        y_of = pos[:, 0]
        sensor_size = np.asarray([max(la.n_channels for la in layout.layers), layout.n_layers, 2], np.int64)
        labels = encoded_labels(enc)
        session = _session_name(enc)
        summary = ExportSummary(Path(out_dir), variant=variant)
        scaled = bool(VARIANTS[variant].speed_scaled) if variant in VARIANTS else False
        time_base = SPEED_SCALED_TIME if scaled else REAL_TIME
        reference = float(enc.parameters.get("reference_speed_mm_s", 120.0))
        # the trial's duration in the time base: eq. 2 contracts a trial by speed / reference speed
        duration = labels.duration_s * (labels.speed_mm_s / reference if scaled else 1.0)
        worst = 0.0
        n = enc.n_trials
        bar = Stage(progress, "writing events", n, unit="trial")
        manifest = {"variant": variant, "source_encoded": str(enc.path), "session": session,
                    "sensor_size": sensor_size.tolist(), "event_dtype": [list(f) for f in EVENT_DTYPE.descr],
                    "fields": {"x": "taxel within its layer (row-major)", "y": "layer (0 top, type I; 1 bottom, "
                               "type II)", "t": ("spike time from the trial's first sample, us, in speed-scaled "
                                                 "time (eq. 2: real time x speed / reference_speed_mm_s)") if scaled
                               else "spike time from the trial's first sample, us (real time)", "p": "SA 0, RA 1"},
                    "time_base": time_base, "reference_speed_mm_s": reference if scaled else None,
                    "layout": layout.to_dict(), "textures": list(enc.textures.labels)}
        with folder_output(out_dir, kind=EVENTS_KIND, overwrite=overwrite, manifest=manifest) as fo:
            for i in range(n):
                st = enc.spikes(variant, slice(i, i + 1))
                ends = st.spike_times_index
                starts = np.concatenate([[0], ends[:-1]])
                per_train = ends - starts
                train = np.repeat(np.arange(per_train.size), per_train)
                t_us = st.spike_times * 1e6
                t_int = np.rint(t_us).astype(np.int64)
                if t_us.size:
                    worst = max(worst, float(np.max(np.abs(t_us - t_int))))
                ev = np.empty(t_int.size, EVENT_DTYPE)
                ch = channel[train]
                ev["x"], ev["y"], ev["t"], ev["p"] = x_of[ch], y_of[ch], t_int, polarity[train]
                ev = ev[np.lexsort((ev["p"], ev["y"], ev["x"], ev["t"]))]
                tid = int(labels.trial_id[i])
                np.savez(fo.file(f"trial_{tid:06d}.npz"), events=ev, sensor_size=sensor_size,
                         texture=np.str_(labels.texture[i]), texture_code=labels.texture_code[i],
                         speed_mm_s=labels.speed_mm_s[i], force_g=labels.force_g[i], repeat=labels.repeat[i],
                         session=np.str_(session), trial_id=np.int64(tid), variant=np.str_(variant),
                         profile=np.str_(labels.profile[i] or "constant"), time_base=np.str_(time_base),
                         duration_s=np.float64(duration[i]), duration_real_s=labels.duration_s[i])
                summary.n_spikes += int(ev.size)
                bar.advance(1)
            manifest["t_rounding_max_us"] = round(worst, 6)
            _write_extra(fo, extra_files)
        summary.n_trials = summary.n_files = n
    return summary


def _write_extra(fo: FolderOutput, extra_files: Mapping[str, Callable[[Path], None]] | None) -> None:
    for name, write in (extra_files or {}).items():
        write(fo.file(name))


def read_events(path: str | os.PathLike[str]) -> tuple[np.ndarray, dict[str, Any]]:
    """One exported trial: ``(events, meta)``; ``events`` the :data:`EVENT_DTYPE` array, ``meta`` the other arrays
    of the file as Python values (``sensor_size`` a tuple). What a user's loader does, with numpy alone."""
    with np.load(path, allow_pickle=False) as z:
        events = z["events"]
        meta: dict[str, Any] = {k: z[k].item() if z[k].ndim == 0 else tuple(z[k].tolist())
                                for k in z.files if k != "events"}
    return events, meta


def _spike_counts(times_s: np.ndarray, index: np.ndarray, n_steps: int, tick_s: float) -> np.ndarray:
    """``(n_steps, n_trains)`` uint8 spike counts per model step of one trial's trains. Raises ValueError when a
    step holds more than 255 spikes (not representable in uint8)."""
    starts = np.concatenate([[0], index[:-1]])
    train = np.repeat(np.arange(index.size), index - starts)
    step = np.minimum(np.floor(times_s / tick_s + 1e-9).astype(np.int64), max(n_steps - 1, 0))
    counts = np.zeros((max(n_steps, 1), index.size), np.int64)
    np.add.at(counts, (step, train), 1)
    if counts.size and counts.max() > 255:
        raise ValueError(f"{int(counts.max())} spikes in one model step: not representable as uint8 counts")
    return counts.astype(np.uint8)


def _toml_str(s: str) -> str:
    return json.dumps(s)  # a TOML basic string is a JSON string for these characters


def _toml_value(v: Any) -> str:
    if isinstance(v, float) and math.isinf(v):
        return "inf" if v > 0 else "-inf"
    return json.dumps(v)


def _texture_set_toml(textures: TextureSet) -> list[str]:
    """The ``[texture_set]`` table of a mapping: the protocol-file form (labels, groups, geometry), every value
    kept (an unbounded period as TOML's ``inf``)."""
    d = textures.to_dict()
    lines = ["[texture_set]", f"name = {json.dumps(d.get('name', ''))}",
             f"textures = {json.dumps([t['label'] for t in d['textures']])}"]
    groups: dict[str, list[str]] = {g: [] for g in d.get("groups") or []}
    for t in d["textures"]:
        if t.get("group"):
            groups.setdefault(t["group"], []).append(t["label"])
    if groups:
        lines.append("[texture_set.groups]")
        lines += [f"{json.dumps(g)} = {json.dumps(m)}" for g, m in groups.items()]
    for t in d["textures"]:
        geo = {k: (math.inf if k == "period_mm" and v is None else v) for k, v in (t.get("geometry") or {}).items()}
        geo = {k: v for k, v in geo.items() if v is not None}
        if geo:
            lines.append(f"[texture_set.geometry.{json.dumps(t['label'])}]")
            lines += [f"{k} = {_toml_value(v)}" for k, v in geo.items()]
    return lines


def _import_mapping(layout: SensorLayout, textures: TextureSet, files: Mapping[str, str],
                    label_pattern: str = LABEL_PATTERN) -> str:
    """The TOML mapping that imports a per-trial CSV export back (``rigctl import --mapping``)."""
    lines = [f"# rigctl import DIR/*.csv --mapping DIR/{IMPORT_MAPPING_NAME} --out SESSION.h5",
             f"rate_hz = {float(layout.sample_rate_hz)!r}",
             f"adc_bits = {int(layout.adc_bits)}",
             f"label_pattern = {_toml_str(label_pattern)}",
             "[sensor]", *(f"{k} = {json.dumps(v)}" for k, v in layout.to_dict().items() if k not in ("layers", "n_channels")
                           and v is not None)]
    for la in layout.to_dict()["layers"]:
        lines += ["[[sensor.layers]]", *(f"{k} = {json.dumps(v)}" for k, v in la.items())]
    lines += _texture_set_toml(textures)
    for name, tex in files.items():
        lines += [f"[files.{_toml_str(name)}]", f"texture = {_toml_str(tex)}"]
    return "\n".join(lines) + "\n"


def export_trials(out_dir: str | os.PathLike[str], *, layouts: Sequence[str], session_path: str | None = None,
                  encoded_path: str | None = None, variant: str | None = None, overwrite: bool = False,
                  extra_files: Mapping[str, Callable[[Path], None]] | None = None,
                  progress: ProgressCallback | None = None) -> ExportSummary:
    """The peer lab's per-trial layout (module docstring): ``per-trial-csv`` (taxel readings of the session's usable
    trials) and/or ``per-trial-npz`` (the encoded file's spike counts of ``variant``) into the new folder ``out_dir``.

    With both, the trials are the encoded file's (the session's usable trials that were encoded). Raises ValueError
    (an unknown layout, a layout without its input, two trials with one name), KeyError (variant), OutputError,
    SessionError, NotEncodedError.
    """
    from rigctl.storage.session import open_session
    from rigctl.storage.validate import usable_trials

    bad = [lay for lay in layouts if lay not in LAYOUTS]
    if bad or not layouts:
        raise ValueError(f"--layout must be one of {', '.join(LAYOUTS)}, got {', '.join(bad) or 'none'}")
    if "per-trial-csv" in layouts and session_path is None:
        raise ValueError("--layout per-trial-csv writes the session's readings: give the session file")
    if "per-trial-npz" in layouts and encoded_path is None:
        raise ValueError("--layout per-trial-npz writes spike trains: give --encoded ENC.h5")
    enc = open_encoded(encoded_path) if encoded_path is not None else None
    ses = open_session(session_path) if session_path is not None else None
    try:
        if enc is not None:
            labels = encoded_labels(enc)
            texture_labels: Sequence[str] = enc.textures.labels
            variant = variant or default_variant(enc)
            _train_map(enc, variant)
        else:
            assert ses is not None
            ids = usable_trials(ses).ids
            plan = {int(r["trial_id"]): r for r in ses.plan}
            rows = [plan[t] for t in ids]
            texture_labels = ses.textures.labels
            profiles = [str(r["profile"]) for r in rows]
            labels = TrialLabels.of(ids, [r["texture"] for r in rows], texture_labels,
                                    [r["speed_mm_s"] for r in rows], [r["force_g"] for r in rows],
                                    [r["duration_s"] for r in rows],
                                    None if has_profiles(profiles) else
                                    [r["repeat"] for r in rows], profile=profiles)
        unlabelled = np.flatnonzero(~(np.isfinite(labels.speed_mm_s) & np.isfinite(labels.force_g)))
        if unlabelled.size:
            raise ValueError(f"trial {int(labels.trial_id[unlabelled[0]])} has no speed or force label: the per-trial "
                             "layout names every trial by its speed and force (export events instead)")
        named = labels.has_profiles
        names = [trial_file_name("", c, s, f, r, "", str(p) if named else "") for c, s, f, r, p in
                 zip(labels.texture_code, labels.speed_mm_s, labels.force_g, labels.repeat, labels.profile)]
        if len(set(names)) != len(names):
            dup = next(n for n in names if names.count(n) > 1)
            raise ValueError(f"two trials would share the name {dup}: their texture, speed, force, profile and "
                             "repeat are equal (the session's repeats are not unique: check its plan)")
        summary = ExportSummary(Path(out_dir), n_trials=len(names), variant=variant if enc else None)
        manifest = {"layouts": list(layouts), "source_session": str(session_path or ""),
                    "source_encoded": str(encoded_path or ""), "variant": summary.variant,
                    "textures": list(texture_labels),
                    "name_pattern": PROFILE_LABEL_PATTERN if named else LABEL_PATTERN}
        bar = Stage(progress, "writing trials", len(names), unit="trial")
        with folder_output(out_dir, kind=TRIALS_KIND, overwrite=overwrite, manifest=manifest) as fo:
            csv_files: dict[str, str] = {}
            for i, stem in enumerate(names):
                tid = int(labels.trial_id[i])
                if "per-trial-csv" in layouts:
                    assert ses is not None
                    trial = ses.trial(tid)
                    name = f"Data{stem}.csv"
                    header = ",".join(ses.layout.channel_labels())
                    np.savetxt(fo.file(name), np.asarray(trial.taxels), fmt="%d", delimiter=",", header=header,
                               comments="")
                    csv_files[name] = str(labels.texture[i])
                if "per-trial-npz" in layouts:
                    assert enc is not None and variant is not None
                    st = enc.spikes(variant, slice(i, i + 1))
                    tick_s = 1.0 / float(enc.attrs.get("model_rate_hz", 1000.0))
                    n_steps = int(math.ceil(float(labels.duration_s[i]) / tick_s - 1e-9))
                    if st.spike_times.size:
                        n_steps = max(n_steps, int(np.floor(st.spike_times.max() / tick_s + 1e-9)) + 1)
                    spikes = _spike_counts(st.spike_times, st.spike_times_index, n_steps, tick_s)
                    n_ch = enc.layout.n_channels
                    np.savez(fo.file(f"SpikeTrains{stem}.npz"), spikes=spikes,
                             trains=np.asarray([f"SA {c}" for c in range(n_ch)] + [f"RA {c}" for c in range(n_ch)]),
                             tick_s=np.float64(tick_s), texture=np.str_(labels.texture[i]),
                             speed_mm_s=labels.speed_mm_s[i], force_g=labels.force_g[i], repeat=labels.repeat[i],
                             trial_id=np.int64(tid), variant=np.str_(variant),
                             profile=np.str_(labels.profile[i] or "constant"))
                    summary.n_spikes += int(spikes.sum())
                bar.advance(1)
            if csv_files:
                assert ses is not None
                fo.file(IMPORT_MAPPING_NAME).write_text(
                    _import_mapping(ses.layout, ses.textures, csv_files,
                                    PROFILE_LABEL_PATTERN if named else LABEL_PATTERN), encoding="utf-8")
            _write_extra(fo, extra_files)
            summary.n_files = len(fo.files)
    finally:
        if enc is not None:
            enc.close()
        if ses is not None:
            ses.close()
    return summary


def write_splits(path: str | os.PathLike[str], splits: Mapping[str, Any], *, source: str) -> None:
    """Write the paper's splits (:func:`rigctl.analysis.splits.paper_splits`) as JSON: ``{"kind": "rigctl
    splits", "source", "trial_ids_are": ..., **splits}``; every trial id is the ``trial_id`` of the export's files."""
    doc = {"kind": "rigctl splits", "source": source,
           "trial_ids_are": "the trial_id of each exported trial (trial_<id>.npz; the session's trial ids)",
           **dict(splits)}
    with open(path, "w", encoding="utf-8") as fh:
        json.dump(doc, fh, indent=1)
        fh.write("\n")
