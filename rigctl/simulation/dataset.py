"""Simulated datasets: trials rendered straight from the physical model, no real-time pacing.

:func:`render_trial` produces one trial as the acquisition runner would record it on the simulated rig (taxel frames
at the model sensor's rate, :func:`model_layout`: the paper's 3x3x2 at 1 kHz; the load-cell force trace and the
drum speed trace as polled over Modbus, the setpoints as attributes);
:func:`generate_dataset` renders a whole protocol (e.g. ``protocols/paper_dataset.toml``: the paper's 16 textures x
5 speeds x 3 forces x 100 trials, Materials and Methods "Tactile Texture Dataset - Data Collection") into a session
file with the same layout as a recorded session (:class:`rigctl.storage.session.SessionWriter`, kind
``"simulated-dataset"``; the session stores the model's sensor and the protocol's texture set, whose labels and
geometry the model renders), on all cores, streaming trial by trial.

Each trial starts at the drum's index mark, as a recorded trial does (:meth:`rigctl.acquisition.rig.Rig.record_trial`
starts its capture at the first taxel frame flagged SYNC_IN), so the trials of one texture are phase-aligned up to
a small jitter; ``DrumConfig.start_at_index = False`` starts them at an arbitrary drum angle instead (a rig whose
recorder has no index signal). Trial-to-trial variability (so that classification is not trivial; the texture stays
the dominant cause of differences): the start position jitter (``DrumConfig.start_jitter_mm``: the index pulse is
latched into the next 1 ms frame, plus the index sensor's repeatability and the plate's mounting), a static speed error and a slow speed
wobble of the stepper drive (:data:`SPEED_ERROR`, :data:`SPEED_WOBBLE`), a static force error (sd 1 % of the
setpoint) plus a slow force-loop residual (sd 0.5 %, tau 0.2 s), the drum's runout ripple (its phase is fixed to
the drum: :data:`RUNOUT_PHASE_RAD`), the fabric's sensitivity drift (``SensorConfig.sensitivity_drift``), the
per-taxel contact jitter of each press (``SensorConfig.contact_level_spread``) and the
sample noise. Each trial's random stream is
seeded from ``(seed, trial_id)``, so a dataset is reproducible whatever the number of workers or the order.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
import multiprocessing as mp
import os
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from rigctl.core.progress import ProgressCallback, Stage
from rigctl.core.provenance import software_provenance
from rigctl.core.sensor import PAPER_SENSOR, SensorLayout
from rigctl.core.textures import PAPER_TEXTURES, TextureSet
from rigctl.core.trial import TrialData
from rigctl.core.worker_signals import ctrl_c_held
from rigctl.simulation.model import RigConfig, SensorModel
from rigctl.simulation.noise import one_pole
from rigctl.simulation.textures import Texture, get_texture
from rigctl.simulation.trial_slots import TrialSlots, init_worker_slots
from rigctl.storage import trial_facts
from rigctl.storage.session import SCHEMA_VERSION, SessionWriter

#: travel of the drum surface in one trial of the paper's dataset, mm (6/4/3/2.4/2 s at 40-120 mm/s)
TRIAL_TRAVEL_MM = 240.0
#: rate at which the force and speed traces are sampled, like the runner polling the Mega's input registers
POLL_RATE_HZ = 50.0
#: trials a worker renders per task (multi-worker generation): fewer round trips, still a smooth progress bar
WORKER_CHUNK = 8
#: trials the writer commits at once (or what 2 s brought): one journaled commit of the session file
COMMIT_TRIALS = 256
#: blocks of :data:`WORKER_CHUNK` slots in flight: a whole commit's worth, so the render workers go on rendering
#: while the writer appends and commits a batch (with 3 blocks a worker idled after 24 trials of each batch's end)
SLOT_BLOCKS = -(-COMMIT_TRIALS // WORKER_CHUNK)
#: sd of the static relative speed error of a trial: the stepper's step rate is crystal-timed, so what varies from
#: trial to trial is tiny (a constant drum-diameter error would be the same in every trial and is not modelled)
SPEED_ERROR = 0.0005
#: sd of the slow relative speed wobble (tau :data:`SPEED_WOBBLE_TAU_S`): the coupling's compliance under the
#: load torque of the ridges (microstepping ripple is at kHz rates and averages out within a millisecond)
SPEED_WOBBLE = 0.001
SPEED_WOBBLE_TAU_S = 0.3
#: phase of the drum's runout relative to its index mark, rad (a property of the drum, the same in every trial)
RUNOUT_PHASE_RAD = 1.0


#: rows of a trial's taxels laid side by side for its per-taxel extremes (:func:`taxel_extrema`)
EXTREMA_FOLD = 64


def taxel_extrema(taxels: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Per-channel minimum and maximum of ``(n, channels)`` counts, ``(channels,)`` each in the counts' type (None
    for no samples): ``taxels.min(axis=0)`` and ``max(axis=0)`` exactly, computed over :data:`EXTREMA_FOLD` rows laid
    side by side (numpy's column reduction walks 18-wide rows: ~0.25 ms a 6,000-sample trial each, this ~11 us;
    the dataset generator's writer did both for every trial)."""
    n, ch = taxels.shape
    if n == 0:
        return None
    cut = n - n % EXTREMA_FOLD
    lo: np.ndarray | None = None
    hi: np.ndarray | None = None
    if cut:
        head = taxels[:cut].reshape(-1, EXTREMA_FOLD * ch)
        lo = head.min(axis=0).reshape(EXTREMA_FOLD, ch).min(axis=0)
        hi = head.max(axis=0).reshape(EXTREMA_FOLD, ch).max(axis=0)
    if cut < n:
        tail = taxels[cut:]
        lo = tail.min(axis=0) if lo is None else np.minimum(lo, tail.min(axis=0))
        hi = tail.max(axis=0) if hi is None else np.maximum(hi, tail.max(axis=0))
    assert lo is not None and hi is not None  # (n > 0: the head or the tail has rows)
    return lo, hi


def model_layout(config: RigConfig | None = None, sensor: SensorModel | None = None) -> SensorLayout:
    """The sensor the model renders: the model's own ``layout`` when it declares one (``sensor.layout`` or
    ``config.sensor.layout``), else the paper's 3x3x2 at 1 kHz, 10-bit (:data:`rigctl.core.sensor.PAPER_SENSOR`)."""
    for obj in (sensor, (config or RigConfig()).sensor):
        layout = getattr(obj, "layout", None)
        if isinstance(layout, SensorLayout):
            return layout
    return PAPER_SENSOR


def _as_texture_set(textures: TextureSet | Mapping | None) -> TextureSet | None:
    """A TextureSet from a set, its ``to_dict`` form (what worker processes receive) or None; the paper's set is
    returned as :data:`PAPER_TEXTURES` itself (the renderer's built-in plates)."""
    if textures is None or textures is PAPER_TEXTURES:  # no comparison (~0.27 ms: every trial's render asks)
        return textures
    ts = textures if isinstance(textures, TextureSet) else TextureSet.from_dict(textures)
    return PAPER_TEXTURES if ts == PAPER_TEXTURES else ts


@dataclasses.dataclass(frozen=True)
class RampProfile:
    """A linear speed ramp from ``start_mm_s`` to ``end_mm_s`` over ``ramp_s`` seconds, then held.

    ``ramp_s=None`` means the ramp lasts the whole trial (the paper's slow-to-fast / fast-to-slow profiles).
    """

    start_mm_s: float
    end_mm_s: float
    ramp_s: float | None = None

    def speed(self, t_s: np.ndarray, duration_s: float) -> np.ndarray:
        """Surface speed (mm/s) at times ``t_s`` (s from the trial start)."""
        ramp = duration_s if self.ramp_s is None else self.ramp_s
        frac = np.clip(t_s / ramp, 0.0, 1.0) if ramp > 0 else np.ones_like(t_s)
        return self.start_mm_s + (self.end_mm_s - self.start_mm_s) * frac

    def duration_for_travel(self, travel_mm: float) -> float:
        """Trial length that covers ``travel_mm`` (s)."""
        a, b = self.start_mm_s, self.end_mm_s
        if self.ramp_s is None:
            return travel_mm / (0.5 * (a + b))
        ramp_travel = 0.5 * (a + b) * self.ramp_s
        if ramp_travel >= travel_mm:  # solve a*t + (b-a)/(2R) t^2 = travel
            k = (b - a) / (2 * self.ramp_s)
            return travel_mm / a if k == 0 else (-a + math.sqrt(a * a + 4 * k * travel_mm)) / (2 * k)
        return self.ramp_s + (travel_mm - ramp_travel) / b


def _as_profile(profile: Any) -> RampProfile | None:
    if profile is None or isinstance(profile, RampProfile):
        return profile
    if isinstance(profile, Mapping):
        get = profile.get
    else:
        def get(k, default=None):
            return getattr(profile, k, default)
    kind = str(get("kind", "") or "").lower()
    if kind in ("constant", "0"):
        return None
    start = get("start_mm_s", get("ramp_start_mm_s"))
    end = get("end_mm_s", get("ramp_end_mm_s"))
    if start is None or end is None or math.isnan(float(start)) or math.isnan(float(end)):
        if kind in ("ramp", "1"):
            raise ValueError(f"a ramp profile needs start_mm_s and end_mm_s, got {profile!r}")
        return None  # e.g. a constant-speed PlannedTrial (NaN ramp speeds)
    ramp = get("ramp_s", get("duration_s", None))
    return RampProfile(float(start), float(end), None if ramp is None else float(ramp))


def render_trial(texture: Texture | str, speed_mm_s: float, force_g: float, *, config: RigConfig | None = None,
                 rng: np.random.Generator, duration_s: float | None = None, profile: Any = None,
                 sensor: SensorModel | None = None, textures: TextureSet | None = None) -> TrialData:
    """Render one trial from the physical model (no real-time pacing).

    Parameters
    ----------
    texture : Texture or str
        Plate on the drum: a label of ``textures`` (the paper's A-P by default).
    speed_mm_s : float
        Constant drum surface speed, mm/s (ignored when ``profile`` is a ramp).
    force_g : float
        Contact force setpoint, g.
    config : RigConfig, optional
        Rig model (defaults to ``RigConfig()``).
    rng : numpy.random.Generator
        All randomness of the trial (start jitter, speed and force errors, drift, noise) comes from it.
    duration_s : float, optional
        Trial length; default: the time to cover 240 mm (6/4/3/2.4/2 s at 40/60/80/100/120 mm/s).
    profile : RampProfile, mapping or object with ``start_mm_s``/``end_mm_s`` (optional ``ramp_s``), optional
        A speed ramp (the paper's slow-to-fast / fast-to-slow real-time experiment); None = constant speed.
    sensor : SensorModel, optional
        Reuse a sensor model (its lookup tables) across trials; must be built from ``config.sensor``.
    textures : TextureSet, optional
        The set ``texture`` belongs to; its geometry is rendered (:func:`rigctl.simulation.textures.get_texture`).
        None: the paper's A-P plates.

    Returns
    -------
    TrialData
        With the model's sensor (:func:`model_layout`, rate R: 1 kHz for the paper's): ``taxels``
        (n, layout.n_channels) uint16 with n = round(duration_s * R); ``seq`` 0..n-1; ``flags`` with SYNC_IN set
        where the drum's index mark passed; ``host_time_s`` = arange(n) / R; ``force_g``/``force_time_s`` and
        ``speed_mm_s``/``speed_time_s`` at 50 Hz, quantised like the Mega's input registers (1 g, 0.1 mm/s);
        ``attrs``: ``start_phase_mm`` (drum surface position at the first sample relative to the index mark: the
        start jitter; with ``DrumConfig.start_at_index`` False the drum angle at the first sample, 0..circumference),
        ``aligned_to_index`` (``DrumConfig.start_at_index``), ``sensitivity`` (the trial's fabric sensitivity factor),
        ``source="simulated"``. The setpoints travel in the session's plan row.

    Raises
    ------
    ValueError
        On a non-positive speed, force or duration, or an unknown texture (KeyError).
    """
    cfg = config or RigConfig()
    tex = get_texture(texture, _as_texture_set(textures))
    prof = _as_profile(profile)
    if prof is None and not speed_mm_s > 0:
        raise ValueError(f"speed_mm_s must be > 0, got {speed_mm_s}")
    if not force_g > 0:
        raise ValueError(f"force_g must be > 0, got {force_g}")
    if duration_s is None:
        duration_s = TRIAL_TRAVEL_MM / speed_mm_s if prof is None else prof.duration_for_travel(TRIAL_TRAVEL_MM)
    if not duration_s > 0:
        raise ValueError(f"duration_s must be > 0, got {duration_s}")
    sensor = sensor or SensorModel(cfg.sensor)
    layout = model_layout(cfg, sensor)
    rate_hz = layout.sample_rate_hz
    n = int(round(duration_s * rate_hz))
    drum, mech = cfg.drum, cfg.mechanics
    circ = drum.circumference_mm
    dt = 1.0 / rate_hz

    t = np.arange(n) * dt
    if prof is None:
        speed = np.full(n, float(speed_mm_s))
    else:
        speed = prof.speed(t, duration_s)
    # stepper speed error: static + slow wobble (Ornstein-Uhlenbeck)
    aw = math.exp(-dt / SPEED_WOBBLE_TAU_S)
    wobble = one_pole(math.sqrt(1 - aw * aw), aw, rng.standard_normal(n)) * SPEED_WOBBLE
    speed = speed * (1.0 + SPEED_ERROR * rng.standard_normal() + wobble)
    if drum.start_at_index:
        # start at the index mark: the first frame is the one flagged SYNC_IN, latched up to 1 ms after the mark
        # passed; the plate under row 0 is then at the index position + the jitter of index sensor and mounting
        latch = float(speed[0]) * dt * rng.uniform(0.0, 1.0)
        phase = latch + drum.start_jitter_mm * rng.standard_normal()
    else:
        # the recorder starts at an arbitrary drum angle: no index frame first (DrumConfig.start_at_index)
        latch = phase = float(rng.uniform(0.0, circ))
    # drum travel since the index mark (the speed of sample k moves the drum during (k-1, k] ms)
    travel = latch + np.cumsum(speed) * dt
    pos = travel + (phase - latch)  # plate coordinate under row 0

    # contact force: setpoint with a static error, a slow force-loop residual, the drum's runout ripple, and the
    # texture ripple under the contact line
    static = 1.0 + 0.01 * rng.standard_normal()
    a = math.exp(-dt / 0.2)
    ou = one_pole(math.sqrt(1 - a * a), a, rng.standard_normal(n)) * 0.005
    runout = mech.contact_stiffness_g_per_mm * drum.runout_mm * np.sin(2 * np.pi * pos / circ + RUNOUT_PHASE_RAD)
    force = force_g * (static + ou) + runout
    force *= 1.0 + mech.texture_ripple * sensor.contact_height(tex, pos, wrap_mm=circ)
    np.maximum(force, 0.0, out=force)

    sensitivity = 1.0 + cfg.sensor.sensitivity_drift * rng.standard_normal()
    # re-pressing the sensor at each trial loads each taxel a little differently (SensorConfig.contact_level_spread)
    contact = np.exp(cfg.sensor.contact_level_spread * rng.standard_normal(sensor.gain.size))
    taxels = sensor.render(tex, pos, force, rng, sensitivity=sensitivity * contact, wrap_mm=circ)

    rev = np.floor(np.concatenate(([latch], travel)) / circ)
    flags = (np.diff(rev) != 0).astype(np.uint8)  # FrameFlag.SYNC_IN = bit 0 (later passes of the index mark)
    if drum.start_at_index:
        flags[0] = 1  # the capture starts at the index frame

    step = max(1, int(round(rate_hz / POLL_RATE_HZ)))
    idx = np.arange(0, n, step)
    force_trace = np.round(force[idx] + mech.loadcell_noise_g * rng.standard_normal(idx.size))
    speed_trace = np.round(speed[idx] * 10.0) / 10.0
    # the setpoints (texture, speed, force, profile, ramp) are in the plan row, which the writer copies to the
    # trial's attributes; here only what the plan does not hold
    attrs = {
        "start_phase_mm": float(phase),
        "aligned_to_index": bool(drum.start_at_index),
        "sensitivity": float(sensitivity),
        "source": "simulated",
    }
    return TrialData(taxels=taxels, seq=(np.arange(n) % 65536).astype(np.uint16), flags=flags,
                     host_time_s=t.copy(), force_g=force_trace, force_time_s=t[idx].copy(),
                     speed_mm_s=speed_trace, speed_time_s=t[idx].copy(), attrs=attrs, layout=layout)


# ----------------------------------------------------------------------------------------------------------------
# whole datasets
# ----------------------------------------------------------------------------------------------------------------
_WORKER: dict[str, Any] = {}


def _init_worker(config_dict: dict, seed: int, textures: dict | None = None) -> None:
    cfg = RigConfig.from_dict(config_dict)
    _WORKER["config"] = cfg
    _WORKER["sensor"] = SensorModel(cfg.sensor)
    _WORKER["seed"] = int(seed)
    _WORKER["textures"] = _as_texture_set(textures)


def _render_planned(row: tuple) -> tuple[int, TrialData]:
    trial_id, texture, speed, force, duration, ramp_start, ramp_end = row
    rng = np.random.default_rng(np.random.SeedSequence([_WORKER["seed"], int(trial_id)]))
    profile = None
    if not (math.isnan(ramp_start) or math.isnan(ramp_end)):
        profile = RampProfile(ramp_start, ramp_end, None)
    data = render_trial(texture, speed, force, config=_WORKER["config"], rng=rng, duration_s=duration,
                        profile=profile, sensor=_WORKER["sensor"], textures=_WORKER.get("textures"))
    return int(trial_id), data


def _prepare(data: TrialData) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray] | None]:
    """What the writer needs of a trial that needs no file, computed where the trial was rendered (the render worker,
    from its slot's bytes): its trial facts (storage's :func:`rigctl.storage.trial_facts.sample_facts`: SHA-256,
    extremes (from the per-taxel ones), fingerprint, seq gaps, non-finite counts) and its per-taxel extremes
    (:func:`taxel_extrema`)."""
    extrema = taxel_extrema(data.taxels)
    return trial_facts.sample_facts(data, data.layout.n_channels, extrema), extrema


def _render_prepared(row: tuple) -> tuple[int, TrialData, Any]:
    """:func:`_render_planned` and :func:`_prepare` of the trial in this process (0 workers)."""
    trial_id, data = _render_planned(row)
    return trial_id, data, _prepare(data)


def _pool_context() -> Any:
    """The render workers' start: ``fork`` where the platform has it and this process runs one thread (the worker
    inherits numpy, numba and the model already imported: ~1.2-1.5 CPU-s and 2-3 s less before its first trial
    than ``spawn``, which imports them again), ``spawn`` otherwise (forking a process whose other threads may hold a
    lock can leave the child waiting on it forever)."""
    if threading.active_count() == 1 and "fork" in mp.get_all_start_methods():
        return mp.get_context("fork")
    return mp.get_context("spawn")


def _field(row: Any, key: str) -> Any:
    return getattr(row, key, None)


def _plan_rows(plan: Iterable[Any]) -> list[tuple]:
    rows = []
    for p in plan:
        get: Callable[[str], Any] = p.get if isinstance(p, Mapping) else functools.partial(_field, p)
        rows.append((int(get("trial_id")), str(get("texture")), float(get("speed_mm_s")), float(get("force_g")),
                     float(get("duration_s")),
                     math.nan if get("ramp_start_mm_s") is None else float(get("ramp_start_mm_s")),
                     math.nan if get("ramp_end_mm_s") is None else float(get("ramp_end_mm_s"))))
    return rows


def generate_dataset(protocol: Any, out_path: str | os.PathLike, *, trials_per_condition: int | None = None,
                     seed: int = 0, workers: int | None = None, progress: ProgressCallback | None = None,
                     config: RigConfig | None = None,
                     compression: str | None = None, overwrite: bool = False, resume: bool = False,
                     durable: bool = False) -> dict:
    """Render a whole protocol into a session file, straight from the model (>= 1000x real time).

    Parameters
    ----------
    protocol : Protocol
        A loaded TOML protocol (:func:`rigctl.acquisition.protocol.load_protocol` of e.g.
        ``protocols/paper_dataset.toml``; the simulator sits below the acquisition layer and never loads one).
    out_path : path
        Session file to write (layout: ``docs/session-format.md``; kind ``"simulated-dataset"``, schema 5: the
        trials' groups hold no views of their rows, read through :class:`rigctl.storage.session.Session`), with the
        model's sensor (:func:`model_layout`) and the protocol's texture set (``protocol.texture_set``; the
        plan's labels when the protocol has none).
    trials_per_condition : int, optional
        Override the protocol's trials per condition (e.g. 10 for a reduced paper dataset).
    seed : int
        Dataset seed; trial ``i`` draws from ``SeedSequence([seed, i])`` (reproducible for any ``workers``).
    workers : int, optional
        Worker processes that render trials while this process writes what they return, in plan order (blocks of
        :data:`WORKER_CHUNK` trials, passed through shared memory: :mod:`rigctl.simulation.trial_slots`); 0
        renders and writes in this process. Default: one per core but one (the writer needs a core of its own:
        on 2 cores at load 8, 960 trials, 1 worker wrote 96 trials/s, 2 workers 26-37), or 0 below 64 trials
        (starting a worker costs about 1.5 s).
    progress : callable, optional
        Receives :class:`rigctl.core.progress.ProgressEvent` s: stage ``"dataset <file name>"``, done/total = trials
        written in this run (the CLI draws a tqdm bar from them).
    config : RigConfig, optional
        Rig model; stored as the session's ``rig_config``. On ``resume`` the stored one is used (like the stored
        dataset seed), so the missing trials come from the model that rendered the others.
    compression : {None, "lzf", "gzip"}
        HDF5 compression of the taxels (None: fastest; the paper-sized set is then ~3 GB).
    overwrite : bool
        Replace an existing file.
    resume : bool
        Continue an existing file of the same protocol: render only the trials not yet complete, with the file's
        dataset seed and rig model.
    durable : bool
        fsync at each batch commit (:class:`SessionWriter`'s ``durable``). Off by default: a generated dataset is
        reproducible, and a killed run loses at most the batch in progress (``resume=True`` continues it).

    Returns
    -------
    dict
        ``path``, ``n_trials`` (written now), ``samples``, ``trial_seconds`` (simulated time), ``wall_s``,
        ``realtime_factor`` (= trial_seconds / wall_s), ``bytes`` (file size).

    Raises
    ------
    TypeError
        If the protocol is a path (load it first) or a Python script (it has no plan to render).
    FileExistsError
        If ``out_path`` exists and neither ``overwrite`` nor ``resume`` is set.
    """
    t_start = time.perf_counter()
    if isinstance(protocol, (str, os.PathLike)):
        raise TypeError(f"generate_dataset takes a loaded protocol, not the path {protocol} "
                        "(rigctl.acquisition.protocol.load_protocol)")
    if getattr(protocol, "format", "toml") == "python":
        raise TypeError("a Python-script protocol has no plan to render; use a TOML protocol")
    if trials_per_condition is not None:
        if int(trials_per_condition) < 1:
            raise ValueError("trials_per_condition must be >= 1")
        protocol = dataclasses.replace(protocol, trials_per_condition=int(trials_per_condition))
    cfg = config or RigConfig()
    layout = model_layout(cfg)
    rate_hz = layout.sample_rate_hz
    texture_set = getattr(protocol, "texture_set", None)
    out_path = Path(out_path)
    plan = protocol.plan()

    if resume and out_path.exists():
        writer = SessionWriter.open(out_path, protocol_source=protocol.source, compression=compression,
                                    durable=durable)
        stored = writer.plan
        if len(stored) != len(plan):
            raise ValueError(f"{out_path} holds a plan of {len(stored)} trials, this protocol has {len(plan)}; "
                             "pass the same --trials-per-condition")
        seed = int(writer.attrs.get("dataset_seed", seed))
        # the stored model wins too: the missing trials are rendered like the ones already written
        stored_cfg = writer.rig_config
        if stored_cfg:
            cfg = RigConfig.from_dict(stored_cfg)
            layout = model_layout(cfg)
            rate_hz = layout.sample_rate_hz
        done = set(writer.completed_ids())
        if len(done) < len(plan):  # the missing trials are this run's (its software beside the creating run's)
            writer.note_resume(software_provenance(kind="simulated-dataset"))
    else:
        writer = SessionWriter.create(
            out_path, plan=plan, protocol_source=protocol.source, protocol_name=protocol.name,
            layout=layout, textures=texture_set, protocol_format="toml", rig_config=cfg.to_dict(),
            kind="simulated-dataset",
            attrs={"dataset_seed": int(seed), "generator": "rigctl.simulation.dataset.generate_dataset",
                   "trials_per_condition": int(protocol.trials_per_condition)},
            overwrite=overwrite, compression=compression, durable=durable, schema_version=SCHEMA_VERSION)
        done = set()
    textures_arg = writer.textures.to_dict()  # what the workers render (the session's set)
    rows = [r for r in _plan_rows(plan) if r[0] not in done]

    if workers is None:  # small jobs: starting worker processes costs more than it saves
        workers = 0 if len(rows) < 64 else max(1, (os.cpu_count() or 1) - 1)
    if int(workers) < 0:
        raise ValueError(f"workers must be >= 0, got {workers}")
    n_workers = min(int(workers), len(rows))
    lo = np.full(layout.n_channels, np.inf)
    hi = np.full(layout.n_channels, -np.inf)
    stats = {"n_trials": 0, "samples": 0}

    def consume(results: Iterator[tuple[int, TrialData, Any]], bar) -> None:
        """Write the trials as they come, committing every 256 trials or 2 s (a crash loses one batch). The
        trials stream through write_trials one at a time: a worker's slot is reused once its trial is written."""
        it = iter(results)
        exhausted = False

        def batch():
            nonlocal exhausted
            t0 = time.monotonic()
            for count, (tid, data, (facts, extrema)) in enumerate(it, 1):
                if extrema is not None:
                    np.minimum(lo, extrema[0], out=lo)
                    np.maximum(hi, extrema[1], out=hi)
                stats["n_trials"] += 1
                stats["samples"] += data.n_samples
                bar.advance(1)
                yield tid, data, facts
                if count >= COMMIT_TRIALS or time.monotonic() - t0 > 2.0:
                    return
            exhausted = True

        while not exhausted:
            writer.write_trials(batch())

    if n_workers == 0:
        bar = Stage(progress, f"dataset {out_path.name}", len(rows))
        _init_worker(cfg.to_dict(), seed, textures_arg)
        consume(map(_render_prepared, rows), bar)
    else:
        # the workers render (the model) into shared-memory slots, this process writes: both run at once
        max_samples = max(int(round(r[4] * rate_hz)) for r in rows) + 2
        ctx = _pool_context()  # (before the progress bar, whose tqdm starts a thread)
        with TrialSlots(max_samples, n_blocks=max(3 * n_workers, SLOT_BLOCKS), block=WORKER_CHUNK,
                        layout=layout) as slots, contextlib.ExitStack() as stack:
            with ctrl_c_held():  # a Ctrl-C while the workers start is this process's, not a worker's traceback
                pool = stack.enter_context(ctx.Pool(n_workers, initializer=init_worker_slots,
                                                    initargs=(*slots.initargs, _render_planned, _init_worker,
                                                              (cfg.to_dict(), seed, textures_arg), _prepare)))
            bar = Stage(progress, f"dataset {out_path.name}", len(rows))
            consume(slots.results(pool, rows), bar)

    # per-taxel min/max over the whole file (the paper's normalisation, Materials and Methods) once it is complete
    if not writer.pending_ids() and (stats["n_trials"] or done):
        if done:  # resumed: add the extremes of the trials written by the earlier run
            from rigctl.storage.session import open_session

            with open_session(out_path) as s:
                for tid in done:
                    extrema = taxel_extrema(s.trial(tid).taxels)
                    if extrema is not None:
                        np.minimum(lo, extrema[0], out=lo)
                        np.maximum(hi, extrema[1], out=hi)
        writer.set_calibration({"taxel_min": lo, "taxel_max": hi, "source": "min/max over all trials",
                                "unit": "ADC counts"})
    wall = time.perf_counter() - t_start
    seconds = stats["samples"] / rate_hz
    return {"path": str(out_path), "n_trials": stats["n_trials"], "samples": stats["samples"],
            "trial_seconds": seconds, "wall_s": wall, "realtime_factor": seconds / wall if wall > 0 else math.inf,
            "bytes": out_path.stat().st_size, "workers": n_workers}
