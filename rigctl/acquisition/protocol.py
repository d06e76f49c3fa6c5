"""Acquisition protocols: TOML files (validated, with the line at fault) and Python-script protocols.

A TOML protocol names the textures (labels of its texture set: the paper's A-P by default, or a ``[texture_set]``
the file declares, with optional groups and geometry), the speed/force conditions, how many trials per condition, how long a trial
lasts (a fixed travel of the drum surface, 240 mm in the paper's dataset, or a fixed duration), the trial order and
the settle timeouts, and the trial quality policy: ``max_dropped_frames`` (default 0: a trial may lose no frame) and
``retries`` (default 2: a trial that fails or loses more frames than that is recorded again up to twice, then marked
failed; :func:`rigctl.acquisition.runner.run_protocol`) and, for the replay rig, ``replay`` ("trials": each
trial starts at the replayed recording's next trial; "continuous"); :meth:`Protocol.plan` expands it into one
:class:`PlannedTrial` per trial. Velocity profiles
(constant, or a linear ramp from a start to an end speed) cover the paper's real-time experiment (Fig. 4: slow,
medium, fast, slow-to-fast, fast-to-slow). The format is documented in ``protocols/paper_dataset.toml`` and
``docs/session-format.md``.

A ``.py`` file is a Python protocol: it defines ``plan(ctx)``, a generator that yields the trials it wants and
receives their recordings (:mod:`rigctl.acquisition.plans`), run by the same engine as a TOML protocol; see
``protocols/example_script.py`` and docs/protocols.md.
"""

from __future__ import annotations

import importlib.util
import math
import re
import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

# the rig's protocol range every setpoint is checked against (mm/s, g): one home, rigctl.core.drum
from rigctl.acquisition.plans import PlanFunction
from rigctl.core.drum import MAX_FORCE_G as MAX_FORCE_G, MAX_SPEED_MM_S as MAX_SPEED_MM_S
from rigctl.core.textures import GEOMETRY_KEYS, KINDS as TEXTURE_KINDS, PAPER_TEXTURES, TextureSet, TextureSetError
from rigctl.core.trial import PlannedTrial  # noqa: F401 (re-exported: the trial record lives in rigctl.core)

#: longest trial the runner accepts, and the RAMP_DURATION_MS register's limit (s)
MAX_DURATION_S = 600.0
MAX_RAMP_DURATION_S = 60.0
#: most trials one plan may hold (the paper's dataset: 24,000), so a typo cannot plan billions
MAX_PLAN_TRIALS = 1_000_000
#: most re-recordings of one trial the ``retries`` key may ask for
MAX_RETRIES = 10
#: the paper's plate labels (the default texture set, :data:`rigctl.core.textures.PAPER_TEXTURES`)
TEXTURE_LETTERS = "".join(PAPER_TEXTURES.labels)
ORDERS = ("blocked", "interleaved", "random")
#: what the replay rig does between trials (the protocol's ``replay``): start each at the source's next trial, or
#: play the source on
REPLAY_MODES = ("trials", "continuous")
#: the rigs a protocol is recorded on (its ``rig``): the drum, or an operator's hand (the paper's real-time system)
PROTOCOL_RIGS = ("drum", "handheld")


class ProtocolError(ValueError):
    """A protocol file is invalid. ``str(err)`` is ``"<path>:<line>: <key>: <problem>"``.

    Attributes
    ----------
    path : str or None
    line : int or None (1-based)
    key : str or None (dotted key path, e.g. ``profiles[1].start_mm_s``)
    """

    def __init__(self, message: str, *, path: str | None = None, line: int | None = None, key: str | None = None):
        self.path, self.line, self.key, self.problem = path, line, key, message
        where = f"{path or '<protocol>'}:{line if line is not None else '?'}"
        super().__init__(f"{where}: {key}: {message}" if key else f"{where}: {message}")


@dataclass(frozen=True)
class Profile:
    """A named velocity profile: constant ``speed_mm_s``, or a linear ramp ``start_mm_s`` -> ``end_mm_s``."""

    name: str
    kind: str  # "constant" | "ramp"
    speed_mm_s: float = math.nan
    start_mm_s: float = math.nan
    end_mm_s: float = math.nan

    @property
    def mean_speed_mm_s(self) -> float:
        return self.speed_mm_s if self.kind == "constant" else 0.5 * (self.start_mm_s + self.end_mm_s)


@dataclass(frozen=True)
class Settle:
    """How long the runner waits for the force to settle and the drum to reach speed, and the speed band."""

    force_timeout_s: float = 15.0
    speed_timeout_s: float = 10.0
    speed_tolerance_mm_s: float = 2.0
    #: optional controller settings written before the run (holding registers FORCE_TOLERANCE_G, SETTLE_TIME_MS)
    force_tolerance_g: int | None = None
    settle_time_ms: int | None = None


@dataclass
class Protocol:
    """A validated TOML protocol (see :func:`load_protocol`).

    ``textures`` are the labels the plan records, in order; ``texture_set`` (a
    :class:`rigctl.core.textures.TextureSet`) the set they belong to, stored in the session: the file's
    ``[texture_set]``, or the paper's A-P set (:data:`rigctl.core.textures.PAPER_TEXTURES`).
    """

    name: str
    source: str
    path: str | None = None
    description: str = ""
    textures: tuple[str, ...] = ()
    texture_set: TextureSet = field(default_factory=lambda: PAPER_TEXTURES)
    profiles: tuple[Profile, ...] = ()
    forces_g: tuple[float, ...] = ()
    trials_per_condition: int = 1
    travel_mm: float | None = 240.0
    duration_s: float | None = None
    order: str = "blocked"
    seed: int = 0
    settle: Settle = field(default_factory=Settle)
    #: frames a kept trial may have lost (sequence gaps among its frames, ``TrialData.dropped_frames``); a trial
    #: that lost more is recorded again (``retries``), then marked failed, never stored as complete
    max_dropped_frames: int = 0
    #: how many times a failed trial (lost frames, a lost stream, a timeout, a fault) is recorded again at once
    retries: int = 2
    #: on the replay rig: "trials" (each trial starts at the source's next trial of the mounted plate) or
    #: "continuous" (the source plays on across trials)
    replay: str = "trials"
    format: str = "toml"
    #: which rig records it: "drum" (the drum rigs, default) or "handheld" (an operator scans flat plates with the
    #: finger: ``rigctl.rigs.open_handheld``; the profiles are the operator's intended velocity profiles)
    rig: str = "drum"

    @property
    def speeds_mm_s(self) -> tuple[float, ...]:
        """The constant speeds of the plan (profiles of kind "constant")."""
        return tuple(p.speed_mm_s for p in self.profiles if p.kind == "constant")

    def trial_duration_s(self, profile: Profile) -> float:
        """Trial length: ``travel_mm / mean speed`` (a ramp covers the travel at its mean speed), or ``duration_s``."""
        if self.duration_s is not None:
            return float(self.duration_s)
        if self.travel_mm is None:
            raise ValueError(f"protocol {self.name!r} gives neither duration_s nor travel_mm")
        return float(self.travel_mm) / profile.mean_speed_mm_s

    def with_seed(self, seed: int) -> "Protocol":
        """A copy with another random-order seed."""
        return replace(self, seed=int(seed))

    def plan(self) -> list[PlannedTrial]:
        """Expand into planned trials, in recording order.

        Orders: ``blocked`` = texture by texture (one plate change per texture), then force, then speed/profile,
        repeats consecutive; ``interleaved`` = every condition once per round, ``trials_per_condition`` rounds;
        ``random`` = a permutation of the blocked list drawn with ``seed`` (numpy default_rng).
        """
        rows: list[tuple] = []
        if self.order == "interleaved":
            for rep in range(self.trials_per_condition):
                for tex in self.textures:
                    for force in self.forces_g:
                        for prof in self.profiles:
                            rows.append((tex, force, prof, rep))
        else:
            for tex in self.textures:
                for force in self.forces_g:
                    for prof in self.profiles:
                        for rep in range(self.trials_per_condition):
                            rows.append((tex, force, prof, rep))
            if self.order == "random":
                perm = np.random.default_rng(self.seed).permutation(len(rows))
                rows = [rows[i] for i in perm]
        plan = []
        for i, (tex, force, prof, rep) in enumerate(rows):
            ramp = prof.kind == "ramp"
            plan.append(
                PlannedTrial(
                    trial_id=i, texture=tex, speed_mm_s=float(prof.mean_speed_mm_s), force_g=float(force),
                    duration_s=self.trial_duration_s(prof), profile=prof.name,
                    ramp_start_mm_s=prof.start_mm_s if ramp else math.nan,
                    ramp_end_mm_s=prof.end_mm_s if ramp else math.nan, repeat=rep,
                )
            )
        return plan

    def estimated_duration_s(self, *, overhead_s: float = 1.5, plate_change_s: float = 3.0) -> float:
        """Rough wall time of the whole plan: trial durations + a per-trial overhead (settling, stopping) + one
        plate change (release, mount, press) whenever the texture changes."""
        plan = self.plan()
        changes = sum(1 for a, b in zip(plan, plan[1:]) if a.texture != b.texture) + 1
        return sum(p.duration_s for p in plan) + overhead_s * len(plan) + plate_change_s * changes


@dataclass
class ScriptProtocol:
    """A Python protocol: a ``.py`` file defining ``plan(ctx)``, a generator function run by the same engine as a
    TOML protocol (:mod:`rigctl.acquisition.plans`: it yields trials and receives their recordings). Optional
    module-level ``NAME`` (the protocol's name) and ``MAX_TRIALS`` (how many trials it yields at most: the progress
    bar's total)."""

    name: str
    source: str
    path: str
    plan_function: PlanFunction
    description: str = ""
    format: str = "python"
    max_trials: int | None = None

    def plan(self) -> list[PlannedTrial]:
        """A Python protocol decides its trials as it runs: the plan is empty until then."""
        return []


# ----------------------------------------------------------------------------------------------------------------
# Loading
# ----------------------------------------------------------------------------------------------------------------
def load_protocol(path: str | Path) -> Protocol | ScriptProtocol:
    """Load and validate a protocol file (``.toml``) or a Python-script protocol (``.py``).

    Raises
    ------
    FileNotFoundError
        If the file does not exist.
    ProtocolError
        With the file, the line and the key at fault, for a TOML syntax error, an unknown or missing key, a value
        of the wrong type, a texture outside the protocol's texture set (A-P unless it declares a
        ``[texture_set]``), a malformed ``[texture_set]``, or a setpoint outside the rig limits (0 < speed <= 150 mm/s,
        0 < force <= 1500 g); for a Python protocol, a syntax error or a missing ``plan(ctx)``.
    """
    path = Path(path)
    source = path.read_text(encoding="utf-8")
    if path.suffix == ".py":
        return _load_script(path, source)
    return parse_protocol(source, path=str(path))


def parse_protocol(source: str, *, path: str | None = None) -> Protocol:
    """Validate TOML protocol text; see :func:`load_protocol`."""
    try:
        doc = tomllib.loads(source)
    except tomllib.TOMLDecodeError as exc:
        m = re.search(r"line (\d+)", str(exc))
        line = int(m.group(1)) if m else (len(source.splitlines()) if "end of document" in str(exc) else None)
        raise ProtocolError(f"TOML syntax error: {exc}", path=path, line=line) from None
    return _Validator(source, path).protocol(doc)


class _KeyLines:
    """Finds the line of a key in TOML source (tomllib gives no positions for values).

    Tracks table headers (``[settle]``, ``[[profiles]]`` with their array index) and records the first line of each
    ``key =`` assignment under its table.
    """

    _header = re.compile(r"^\s*(\[\[?)\s*([A-Za-z0-9_.\-\" ]+?)\s*\]\]?\s*(#.*)?$")
    _assign = re.compile(r"^\s*([A-Za-z0-9_\-]+|\"[^\"]*\")\s*(\.\s*[A-Za-z0-9_\-]+\s*)*=")

    def __init__(self, source: str):
        self.lines: dict[tuple, int] = {}
        table: tuple = ()
        counts: dict[str, int] = {}
        in_multiline = False
        for lineno, text in enumerate(source.splitlines(), start=1):
            if in_multiline:
                if text.count('"""') % 2 == 1 or text.count("'''") % 2 == 1:
                    in_multiline = False
                continue
            h = self._header.match(text)
            if h:
                name = h.group(2).strip().strip('"')
                if h.group(1) == "[[":
                    counts[name] = counts.get(name, -1) + 1
                    table = (name, counts[name])
                else:
                    table = tuple(part.strip().strip('"') for part in name.split("."))  # [texture_set.geometry]
                self.lines.setdefault(table, lineno)
                continue
            a = self._assign.match(text)
            if a:
                key = a.group(1).strip('"')
                self.lines.setdefault(table + (key,), lineno)
                if text.count('"""') % 2 == 1 or text.count("'''") % 2 == 1:
                    in_multiline = True

    def find(self, *key) -> int | None:
        while key:
            if key in self.lines:
                return self.lines[key]
            key = key[:-1]
        return None


def _key_text(key: tuple) -> str:
    out = ""
    for k in key:
        out += f"[{k}]" if isinstance(k, int) else (f".{k}" if out else str(k))
    return out


class _Validator:
    TOP = {
        "name", "description", "textures", "speeds_mm_s", "forces_g", "trials_per_condition", "travel_mm",
        "duration_s", "order", "seed", "settle", "profiles", "texture_set", "max_dropped_frames", "retries",
        "replay", "rig",
    }
    TEXTURE_SET = {"name", "textures", "groups", "geometry"}
    SETTLE = {"force_timeout_s", "speed_timeout_s", "speed_tolerance_mm_s", "force_tolerance_g", "settle_time_ms"}
    PROFILE = {"name", "kind", "speed_mm_s", "start_mm_s", "end_mm_s"}

    def __init__(self, source: str, path: str | None):
        self.source, self.path = source, path
        self.lines = _KeyLines(source)

    def error(self, key: tuple, message: str) -> ProtocolError:
        return ProtocolError(message, path=self.path, line=self.lines.find(*key), key=_key_text(key))

    def _number(self, key: tuple, value: Any, *, lo: float, hi: float, lo_open: bool = True, what: str = "") -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.error(key, f"expected a number{what}, got {value!r}")
        v = float(value)
        if not math.isfinite(v) or (v <= lo if lo_open else v < lo) or v > hi:
            rel = ">" if lo_open else ">="
            raise self.error(key, f"{value!r} is outside the rig limits ({rel} {lo:g} and <= {hi:g}{what})")
        return v

    def _int(self, key: tuple, value: Any, *, lo: int, hi: int | None = None) -> int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.error(key, f"expected an integer, got {value!r}")
        if value < lo or (hi is not None and value > hi):
            raise self.error(key, f"{value} is out of range ({lo}..{hi if hi is not None else ''})")
        return value

    def _list(self, key: tuple, value: Any) -> list:
        if not isinstance(value, list) or not value:
            raise self.error(key, f"expected a non-empty list, got {value!r}")
        return value

    def _unknown(self, doc: dict, allowed: set, prefix: tuple) -> None:
        for k in doc:
            if k not in allowed:
                raise self.error(prefix + (k,), f"unknown key (allowed: {', '.join(sorted(allowed))})")

    def protocol(self, doc: dict) -> Protocol:
        self._unknown(doc, self.TOP, ())
        name = doc.get("name")
        if not isinstance(name, str) or not name.strip():
            raise self.error(("name",), "required: a non-empty string naming the protocol")
        description = doc.get("description", "")
        if not isinstance(description, str):
            raise self.error(("description",), "expected a string")

        texture_set = self._texture_set(doc["texture_set"]) if "texture_set" in doc else PAPER_TEXTURES
        if "textures" not in doc:
            raise self.error(("textures",), 'required: a list of texture labels, e.g. ["A", "B"] (the paper\'s A-P, '
                                            'or labels of a [texture_set])')
        textures = []
        for i, t in enumerate(self._list(("textures",), doc["textures"])):
            if not isinstance(t, str):
                raise self.error(("textures",), f"element {i} = {t!r} is not a texture label (a string)")
            try:
                textures.append(texture_set.resolve(t))
            except TextureSetError:
                hint = ("" if "texture_set" in doc else
                        "; declare a [texture_set] (name, textures, groups) for labels outside the paper's A-P")
                shown = ", ".join(texture_set.labels[:20]) + (" ..." if len(texture_set) > 20 else "")
                raise self.error(("textures",), f"element {i} = {t!r} is not a texture of the set "
                                                f"{texture_set.name!r} ({shown}){hint}") from None
        if len(set(textures)) != len(textures):
            raise self.error(("textures",), "a texture is listed twice")

        if "forces_g" not in doc:
            raise self.error(("forces_g",), "required: a list of force setpoints in g")
        forces = tuple(
            self._number(("forces_g",), f, lo=0, hi=MAX_FORCE_G, what=f" g, element {i}")
            for i, f in enumerate(self._list(("forces_g",), doc["forces_g"]))
        )

        profiles: list[Profile] = []
        keys: list[tuple] = []  # where each profile was written, for errors found later
        if "speeds_mm_s" in doc:
            for i, s in enumerate(self._list(("speeds_mm_s",), doc["speeds_mm_s"])):
                v = self._number(("speeds_mm_s",), s, lo=0, hi=MAX_SPEED_MM_S, what=f" mm/s, element {i}")
                profiles.append(Profile(name="constant", kind="constant", speed_mm_s=v))
                keys.append(("speeds_mm_s",))
        if "profiles" in doc:
            named = doc["profiles"]
            if not isinstance(named, list) or not all(isinstance(p, dict) for p in named) or not named:
                raise self.error(("profiles",), "expected [[profiles]] tables")
            profiles.extend(self._profile(i, p) for i, p in enumerate(named))
            keys.extend(("profiles", i) for i in range(len(named)))
            names = [p.name for p in profiles]
            dup = {n for n in names if names.count(n) > 1 and n != "constant"}
            if dup:
                raise self.error(("profiles",), f"profile name {sorted(dup)[0]!r} is used twice")
        if not profiles:
            raise self.error(("speeds_mm_s",), "required: speeds_mm_s = [...] and/or [[profiles]] tables")

        tpc = self._int(("trials_per_condition",), doc.get("trials_per_condition", 1), lo=1)

        travel = doc.get("travel_mm")
        duration = doc.get("duration_s")
        if travel is not None and duration is not None:
            raise self.error(("duration_s",), "give either travel_mm or duration_s, not both")
        if duration is not None:
            duration = self._number(("duration_s",), duration, lo=0, hi=MAX_DURATION_S, what=" s")
            travel = None
        else:
            travel = self._number(("travel_mm",), 240.0 if travel is None else travel, lo=0, hi=1e5, what=" mm")

        order = doc.get("order", "blocked")
        if order not in ORDERS:
            raise self.error(("order",), f"{order!r} is not one of {', '.join(ORDERS)}")
        seed = self._int(("seed",), doc.get("seed", 0), lo=0)
        max_dropped = self._int(("max_dropped_frames",), doc.get("max_dropped_frames", 0), lo=0)
        retries = self._int(("retries",), doc.get("retries", 2), lo=0, hi=MAX_RETRIES)
        replay = doc.get("replay", "trials")
        if replay not in REPLAY_MODES:
            raise self.error(("replay",), f"{replay!r} is not one of {', '.join(REPLAY_MODES)}")
        rig = doc.get("rig", "drum")
        if rig not in PROTOCOL_RIGS:
            raise self.error(("rig",), f"{rig!r} is not one of {', '.join(PROTOCOL_RIGS)}")
        n_trials = len(textures) * len(forces) * len(profiles) * tpc
        if n_trials > MAX_PLAN_TRIALS:
            raise self.error(("trials_per_condition",), f"the plan would hold {n_trials} trials, more than "
                                                        f"{MAX_PLAN_TRIALS}")

        settle = Settle()
        if "settle" in doc:
            st = doc["settle"]
            if not isinstance(st, dict):
                raise self.error(("settle",), "expected a [settle] table")
            self._unknown(st, self.SETTLE, ("settle",))
            kw: dict[str, Any] = {}
            for k in ("force_timeout_s", "speed_timeout_s"):
                if k in st:
                    kw[k] = self._number(("settle", k), st[k], lo=0, hi=600, what=" s")
            if "speed_tolerance_mm_s" in st:
                kw["speed_tolerance_mm_s"] = self._number(
                    ("settle", "speed_tolerance_mm_s"), st["speed_tolerance_mm_s"], lo=0, hi=50, what=" mm/s")
            if "force_tolerance_g" in st:
                kw["force_tolerance_g"] = self._int(("settle", "force_tolerance_g"), st["force_tolerance_g"], lo=1, hi=500)
            if "settle_time_ms" in st:
                kw["settle_time_ms"] = self._int(("settle", "settle_time_ms"), st["settle_time_ms"], lo=0, hi=10000)
            settle = Settle(**kw)

        proto = Protocol(
            name=name.strip(), source=self.source, path=self.path, description=description,
            textures=tuple(textures), texture_set=texture_set, profiles=tuple(profiles), forces_g=forces, trials_per_condition=tpc,
            travel_mm=travel, duration_s=duration, order=order, seed=seed, settle=settle,
            max_dropped_frames=max_dropped, retries=retries, replay=replay, rig=rig,
        )
        for key, prof in zip(keys, profiles):
            d = proto.trial_duration_s(prof)
            if d > MAX_DURATION_S:
                raise self.error(key, f"a trial would last {d:.1f} s, longer than {MAX_DURATION_S:g} s")
            if prof.kind == "ramp" and d > MAX_RAMP_DURATION_S:
                raise self.error(key, f"the ramp would last {d:.1f} s, longer than {MAX_RAMP_DURATION_S:g} s")
        return proto

    def _texture_set(self, ts: Any) -> TextureSet:
        key = ("texture_set",)
        if not isinstance(ts, dict):
            raise self.error(key, "expected a [texture_set] table (name, textures, groups, geometry)")
        self._unknown(ts, self.TEXTURE_SET, key)
        name = ts.get("name", "")
        if not isinstance(name, str):
            raise self.error(key + ("name",), "expected a string")
        if "textures" not in ts:
            raise self.error(key + ("textures",), 'required: the set\'s labels in order, e.g. ["Linen", "HB3"]')
        labels = self._list(key + ("textures",), ts["textures"])
        for i, t in enumerate(labels):
            if not isinstance(t, str) or not t.strip():
                raise self.error(key + ("textures",), f"element {i} = {t!r} is not a non-empty label")
        groups = ts.get("groups")
        if groups is not None:
            if not isinstance(groups, dict) or not all(isinstance(v, list) for v in groups.values()):
                raise self.error(key + ("groups",), 'expected a table of label lists, e.g. {woven = ["Linen"]}')
            for g, members in groups.items():
                stray = [m for m in members if m not in labels]
                if stray:
                    raise self.error(key + ("groups",), f"group {g!r} names {stray[0]!r}, which is not in textures")
        geometry = ts.get("geometry")
        if geometry is not None:
            if not isinstance(geometry, dict):
                raise self.error(key + ("geometry",), "expected a table {label = {kind = ..., period_mm = ...}}")
            for label, geo in geometry.items():
                gkey = key + ("geometry", label)
                if label not in labels:
                    raise self.error(gkey, f"{label!r} is not in textures")
                if not isinstance(geo, dict):
                    raise self.error(gkey, "expected a table of kind, height_mm, period_mm, width_mm")
                self._unknown(geo, set(GEOMETRY_KEYS), gkey)
                if "kind" in geo and geo["kind"] not in TEXTURE_KINDS:
                    raise self.error(gkey + ("kind",), f"{geo['kind']!r} is not one of {', '.join(TEXTURE_KINDS)}")
                for k in ("height_mm", "period_mm", "width_mm"):
                    if k in geo:
                        self._number(gkey + (k,), geo[k], lo=0, hi=1e4, lo_open=k != "height_mm", what=" mm")
        try:
            return TextureSet.from_dict({"name": name, "textures": labels, "groups": groups, "geometry": geometry})
        except TextureSetError as exc:
            raise self.error(key, str(exc)) from None

    def _profile(self, i: int, p: dict) -> Profile:
        key = ("profiles", i)
        self._unknown(p, self.PROFILE, key)
        name = p.get("name")
        if not isinstance(name, str) or not name.strip():
            raise self.error(key + ("name",), "required: a non-empty string, e.g. \"slow-to-fast\"")
        if len(name.encode()) > 24 or not name.isascii():
            raise self.error(key + ("name",), f"{name!r} must be ASCII, at most 24 characters")
        kind = p.get("kind", "ramp" if "start_mm_s" in p else "constant")
        if kind == "constant":
            for k in ("start_mm_s", "end_mm_s"):
                if k in p:
                    raise self.error(key + (k,), "only a ramp profile has start/end speeds")
            if "speed_mm_s" not in p:
                raise self.error(key + ("speed_mm_s",), "required for a constant profile")
            v = self._number(key + ("speed_mm_s",), p["speed_mm_s"], lo=0, hi=MAX_SPEED_MM_S, what=" mm/s")
            return Profile(name=name, kind="constant", speed_mm_s=v)
        if kind == "ramp":
            if "speed_mm_s" in p:
                raise self.error(key + ("speed_mm_s",), "a ramp profile has start_mm_s and end_mm_s, not speed_mm_s")
            vals = {}
            for k in ("start_mm_s", "end_mm_s"):
                if k not in p:
                    raise self.error(key + (k,), "required for a ramp profile")
                vals[k] = self._number(key + (k,), p[k], lo=0, hi=MAX_SPEED_MM_S, what=" mm/s")
            return Profile(name=name, kind="ramp", start_mm_s=vals["start_mm_s"], end_mm_s=vals["end_mm_s"])
        raise self.error(key + ("kind",), f"{kind!r} is not 'constant' or 'ramp'")


def _load_script(path: Path, source: str) -> ScriptProtocol:
    try:
        compile(source, str(path), "exec")
    except SyntaxError as exc:
        raise ProtocolError(f"Python syntax error: {exc.msg}", path=str(path), line=exc.lineno) from None
    spec = importlib.util.spec_from_file_location(f"rigctl_protocol_{path.stem}", path)
    if spec is None or spec.loader is None:
        raise ProtocolError("cannot be loaded as a Python module", path=str(path), line=None)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    plan = getattr(module, "plan", None)
    if not callable(plan):
        if callable(getattr(module, "run", None)):
            raise ProtocolError("run(rig, session) protocols are gone: write plan(ctx), a generator yielding "
                                "ctx.trial(...) (docs/protocols.md, Python protocols)", path=str(path), line=None,
                                key="plan")
        raise ProtocolError("a Python protocol must define plan(ctx) (docs/protocols.md, Python protocols)",
                            path=str(path), line=None, key="plan")
    name = getattr(module, "NAME", path.stem)
    max_trials = getattr(module, "MAX_TRIALS", None)
    if max_trials is not None and (not isinstance(max_trials, int) or max_trials < 1):
        raise ProtocolError(f"MAX_TRIALS must be a positive int, got {max_trials!r}", path=str(path), line=None,
                            key="MAX_TRIALS")
    return ScriptProtocol(name=str(name), source=source, path=str(path), plan_function=plan,
                          description=(module.__doc__ or "").strip(), max_trials=max_trials)
