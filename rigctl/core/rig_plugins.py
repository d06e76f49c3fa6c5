"""Rig backends as plugins: the entry-point group ``rigctl.rigs``, what a plugin's factory is given and returns, and
how the installed ones are found.

Every rig rigctl can open, its own included, is an entry point of the group :data:`RIG_GROUP` in some
distribution's metadata (rigctl's ``pyproject.toml``: ``[project.entry-points."rigctl.rigs"]``)::

    [project.entry-points."rigctl.rigs"]
    csvboard = "rigctl_csvboard:open_board"

The entry point names a :class:`RigFactory`: ``factory(request) -> parts``, called with a :class:`RigRequest` (the
rig's name, its options, the seed, the operator prompt, the texture set) when that rig is opened, never before: a
plugin's module is imported only when its rig is chosen (or listed by ``rigctl rigs``). What it returns:

- a :class:`rigctl.core.interfaces.RigBackend`: a whole rig (a drum controller and a taxel source, how plates get
  mounted); the built-in ``sim``, ``replay``, ``hil``, ``hardware`` and ``inprocess`` rigs are these;
- a :class:`SampleSource`: a sensor without a drum (``read(n)`` of its samples at its own layout and rate): rigctl
  streams it through the simulated rig's taxel board, the drum simulated (option ``drum``: ``sim``, real time on
  ptys, the default; ``inprocess``, the fast in-process rig on a simulated clock), as a replay is;
- a :class:`rigctl.core.handheld.ScanSource`: a handheld rig (a sensor and a tracker, no drum); the built-in
  ``handheld`` rig is one.

:func:`rigctl.rigs.open_rig` (the composition root) builds the rig from it; the operator layer
(:class:`rigctl.operations.RigControl`) holds it. Imports nothing of rigctl's but :mod:`rigctl.core`.
"""

from __future__ import annotations

import functools
import importlib.metadata as metadata
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt

from rigctl.core.errors import describe_error
from rigctl.core.handheld import ScanSource
from rigctl.core.interfaces import Prompt, RigBackend
from rigctl.core.sensor import SensorLayout
from rigctl.core.textures import TextureSet

__all__ = ["RIG_GROUP", "BUILTIN_RIGS", "RigRequest", "RigFactory", "RigParts", "SampleSource", "RigEntry",
           "RigPluginError", "RigOptionError", "RigPluginInfo", "rig_entries", "rig_names", "load_rig_factory",
           "describe_rigs", "SENSOR_DRUMS"]

#: the entry-point group rig backends are registered in
RIG_GROUP = "rigctl.rigs"

#: rigctl's own rigs: name -> entry point (``module:factory``), as its ``pyproject.toml`` registers them. Used only
#: when the installed metadata lacks one (an editable install made before the group existed: reinstall to refresh)
BUILTIN_RIGS: dict[str, str] = {
    "sim": "rigctl.rigs:sim_rig",
    "replay": "rigctl.rigs:replay_rig",
    "hil": "rigctl.rigs:hil_rig",
    "hardware": "rigctl.rigs:hardware_rig",
    "inprocess": "rigctl.rigs:inprocess_rig",
    "handheld": "rigctl.rigs:handheld_rig",
}

#: the simulated drums a sensor-only plugin (:class:`SampleSource`) can be streamed with (option ``drum``)
SENSOR_DRUMS = ("sim", "inprocess")


class RigPluginError(RuntimeError):
    """A rig that is not installed, or whose plugin cannot be loaded (the message is one line)."""


class RigOptionError(ValueError):
    """A rig option that is missing, unknown, or not of its kind (the message names the option)."""


@runtime_checkable
class SampleSource(Protocol):
    """A sensor without a drum: its samples, read as the simulated taxel board sends them.

    ``layout`` is the sensor (channels, rate, ADC bits); ``read(n)`` is asked for the next ``n`` samples, called from
    the board's thread every millisecond or so with the samples due by then at ``layout.sample_rate_hz``, and returns
    an ``(m, layout.n_channels)`` array of ADC counts (uint16, 0 to 2**adc_bits - 1) with ``m <= n``: the samples it
    has, each once. **Fewer rows than asked is how a source says "no sample yet"** (a live device late) **or "these
    samples are lost"** (a gap the device reported): the board sends no frame for the periods left, its sequence
    number steps over them, and the session stores them as dropped frames (``rigctl info`` shows them; a protocol's
    ``max_dropped_frames`` judges the trial). A source never repeats a sample to fill a period: a held sample would be
    stored as a new reading (issue 52: a plugin's late samples counted as good ones). A recording returns its next
    samples. Optional: ``close()`` (called once when the rig closes), ``textures`` (a
    :class:`rigctl.core.textures.TextureSet` the rig takes as its own), ``describe()`` (a JSON-able dict stored, with
    the plugin's distribution and version, in the session's ``rig_config`` and provenance: ``plugin``).
    """

    @property
    def layout(self) -> SensorLayout:
        """The sensor the samples come from."""
        ...

    def read(self, n: int) -> npt.NDArray[np.uint16]:
        """At most the next ``n`` samples, ``(m, layout.n_channels)`` uint16 ADC counts, ``m <= n`` (fewer: no
        sample yet, or lost; never a repeated one)."""
        ...


#: what a factory returns (see the module docstring)
RigParts = RigBackend | SampleSource | ScanSource


@dataclass(frozen=True)
class RigRequest:
    """What a rig's factory is given when the rig is opened.

    Attributes
    ----------
    name : the rig's name (its entry point's).
    options : the rig's options: ``--rig-option KEY=VALUE`` texts from the command line and the GUI, any object from
        Python (``open_rig(name, KEY=VALUE)``); read them with :meth:`text`, :meth:`number`, :meth:`integer`,
        :meth:`flag`, and refuse the rest with :meth:`check_known`.
    seed : seed of anything simulated (the simulated drum, a simulated sensor).
    config : the simulated rig's model configuration (``rigctl.simulation.model.RigConfig``; None: its default).
    prompt : ``prompt(message)`` that blocks until the operator has done what it asks (None: the rig's own).
    textures : the texture set the session records (None: the rig's default).
    host_config_path : the rig config file (calibration), None for the default.
    """

    name: str
    options: Mapping[str, object] = field(default_factory=dict)
    seed: int = 0
    config: object | None = None
    prompt: Prompt | None = None
    textures: TextureSet | None = None
    host_config_path: str | None = None

    def _raw(self, key: str, default: object | None) -> object:
        value = self.options.get(key, default)
        if value is None:
            raise RigOptionError(f"the {self.name} rig needs option {key} (--rig-option {key}=VALUE)")
        return value

    def text(self, key: str, default: str | None = None) -> str:
        """Option ``key`` as text (RigOptionError when it is missing and has no default)."""
        return str(self._raw(key, default))

    def number(self, key: str, default: float | None = None) -> float:
        """Option ``key`` as a float (RigOptionError when missing without a default, or not a number)."""
        value = self._raw(key, default)
        try:
            return float(value)  # type: ignore[arg-type]  # a text or a number: float() tells
        except (TypeError, ValueError):
            raise RigOptionError(f"rig option {key}={value!r}: not a number") from None

    def integer(self, key: str, default: int | None = None) -> int:
        """Option ``key`` as an int (RigOptionError when missing without a default, or not an integer)."""
        value = self._raw(key, default)
        try:
            return int(str(value), 0) if isinstance(value, str) else int(value)  # type: ignore[call-overload]
        except (TypeError, ValueError):
            raise RigOptionError(f"rig option {key}={value!r}: not an integer") from None

    def flag(self, key: str, default: bool = False) -> bool:
        """Option ``key`` as a bool: true/yes/on/1 or false/no/off/0 (RigOptionError otherwise)."""
        value = self.options.get(key, default)
        if isinstance(value, bool):
            return value
        text = str(value).strip().lower()
        if text in ("1", "true", "yes", "on"):
            return True
        if text in ("0", "false", "no", "off"):
            return False
        raise RigOptionError(f"rig option {key}={value!r}: give true or false")

    def check_known(self, known: Iterable[str]) -> None:
        """Raise RigOptionError naming every option not in ``known`` (a typo is refused, never ignored)."""
        unknown = sorted(set(self.options) - set(known))
        if unknown:
            takes = ", ".join(sorted(known)) or "none"
            raise RigOptionError(f"the {self.name} rig has no option {', '.join(unknown)} (its options: {takes})")


class RigFactory(Protocol):
    """What an entry point of :data:`RIG_GROUP` names: ``factory(request) -> RigParts`` (module docstring). Its
    docstring's first line is the rig's description in ``rigctl rigs``. Raises :class:`RigOptionError` for a bad
    option and any error (one line) when the rig cannot be made; nothing may be started before ``__enter__`` of a
    returned backend, nor left open when it raises."""

    def __call__(self, request: RigRequest, /) -> RigParts:
        ...


@dataclass(frozen=True)
class RigEntry:
    """An installed rig: ``name``, its entry point ``target`` (``module:attribute``), the ``distribution`` (and
    ``version``) that registers it (None: rigctl's own, missing from the installed metadata)."""

    name: str
    target: str
    distribution: str | None
    version: str | None

    @property
    def builtin(self) -> bool:
        return BUILTIN_RIGS.get(self.name) == self.target


@functools.cache
def rig_entries() -> dict[str, RigEntry]:
    """The installed rigs by name, rigctl's own first (read once per process from the installed metadata; no
    plugin is imported). A name two distributions register goes to the first one found."""
    found: dict[str, RigEntry] = {}
    for ep in metadata.entry_points(group=RIG_GROUP):
        if ep.name in found:
            continue
        dist = getattr(ep, "dist", None)
        found[ep.name] = RigEntry(ep.name, ep.value, None if dist is None else dist.name,
                                  None if dist is None else dist.version)
    out = {name: found.pop(name, RigEntry(name, target, None, None)) for name, target in BUILTIN_RIGS.items()}
    out.update(sorted(found.items()))
    return out


def rig_names() -> tuple[str, ...]:
    """The names of the installed rigs (rigctl's own first)."""
    return tuple(rig_entries())


def load_rig_factory(name: str) -> RigFactory:
    """The factory of rig ``name`` (its plugin's module imported now). Raises RigPluginError (one line) when no rig
    of that name is installed or its plugin cannot be loaded."""
    entry = rig_entries().get(name)
    if entry is None:
        raise RigPluginError(f"unknown rig kind {name!r}; installed: {', '.join(rig_names())} (`rigctl rigs` lists them)")
    try:
        factory = metadata.EntryPoint(name, entry.target, RIG_GROUP).load()
    except Exception as exc:  # noqa: BLE001 - a broken plugin is reported, in one line, never raised as is
        raise RigPluginError(f"the {name} rig's plugin {entry.target} ({entry.distribution or 'rigctl'}) does not "
                             f"load: {' '.join(describe_error(exc).split())}") from None
    if not callable(factory):
        raise RigPluginError(f"the {name} rig's plugin {entry.target} is not callable (a factory(request))")
    return factory


@dataclass(frozen=True)
class RigPluginInfo:
    """One line of ``rigctl rigs``: the rig's ``name``, ``distribution`` and ``version``, ``target``, its
    one-line ``description``, ``error`` (None: it loads) and whether it is rigctl's own."""

    name: str
    distribution: str
    version: str
    target: str
    description: str
    error: str | None
    builtin: bool


def _first_line(text: str | None) -> str:
    lines = [line.strip() for line in (text or "").strip().splitlines()]
    para = " ".join(lines[: lines.index("")] if "" in lines else lines)
    return para.split(". ")[0].rstrip(".")


def describe_rigs() -> list[RigPluginInfo]:
    """Every installed rig, each plugin loaded to tell whether it loads (the error in one line when not)."""
    out = []
    for entry in rig_entries().values():
        dist = entry.distribution or "rigctl"
        version = entry.version or ""
        try:
            factory = load_rig_factory(entry.name)
        except RigPluginError as exc:
            out.append(RigPluginInfo(entry.name, dist, version, entry.target, "", str(exc), entry.builtin))
            continue
        description = _first_line(getattr(factory, "__doc__", None))
        if not description and entry.distribution:
            description = str((metadata.metadata(entry.distribution).get_all("Summary") or [""])[0])
        out.append(RigPluginInfo(entry.name, dist, version, entry.target, description, None, entry.builtin))
    return out
