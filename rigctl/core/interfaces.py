"""The typed seams between the rig's parts: runtime-checkable :class:`typing.Protocol` interfaces.

The acquisition layer (``rigctl.acquisition``: the ``Rig`` facade, the trial runner, calibration) is written against
these, never against a concrete backend. Implementations:

- :class:`DrumController`: ``rigctl.devices.drum.DrumClient`` (Modbus RTU to the Mega: real board, the virtual Mega,
  or the firmware under simavr; the in-process backend gives it a transport that calls the controller logic,
  ``rigctl.simulation.controller.MegaController``, directly, and a simulated clock).
- :class:`TaxelSource`: ``rigctl.devices.taxel_stream.TaxelStream`` (pyserial, the Uno's frames) and
  ``rigctl.simulation.inprocess.InProcessTaxels``.
- :class:`PlateMounter`: how a texture plate gets on the drum: the simulated rigs render the set's geometry
  (``rigctl.simulation.backend.SimMounter``), on hardware an operator is asked
  (``rigctl.devices.backend.OperatorMounter``).
- :class:`MassPlacer` (optional): a backend that rests a calibration mass on the load cell (simulation).
- :class:`RigBackend`: what opens the boards: ``rigctl.simulation.backend.PtyRigBackend`` (simulated rig on ptys,
  replay, firmware under simavr), ``rigctl.devices.backend.SerialBackend`` (hardware),
  ``rigctl.simulation.inprocess.InProcessBackend``; only the composition root ``rigctl.rigs`` knows them all.

Bluesky's ``protocols.py`` is the model (duck typing, no inheritance chains). Imports nothing else of rigctl's but
:mod:`rigctl.core.sensor` and :mod:`rigctl.core.textures`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any, Protocol, runtime_checkable

from rigctl.core.sensor import SensorLayout
from rigctl.core.textures import TextureSet

__all__ = ["DrumController", "TaxelSource", "PlateMounter", "MassPlacer", "RigBackend", "Prompt"]


@runtime_checkable
class DrumController(Protocol):
    """The drum controller (Mega): speed and force setpoints in physical units, commands, status.

    Setters raise ``rigctl.devices.errors.SetpointRangeError`` (a ValueError) before anything is sent when a value is
    outside the controller's range; communication failures raise ``DrumError`` subclasses (``DrumTimeout``, ...).
    ``clock`` (``now() -> s``, ``sleep(s)``) is the host clock its waits run on and the taxel source's
    ``host_time_s`` uses: the wall clock (``time.monotonic``), or the in-process backend's simulated clock.
    """

    clock: Any

    def set_speed(self, mm_s: float) -> None: ...
    def set_force(self, g: float) -> None: ...
    def set_ramp(self, start_mm_s: float, end_mm_s: float, duration_s: float) -> None: ...
    def set_profile(self, profile: Any) -> None: ...
    def run(self) -> None: ...
    def stop(self) -> None: ...
    def stop_drum(self) -> None: ...
    def press(self) -> None: ...
    def tare(self) -> None: ...
    def home(self) -> None: ...
    def clear_fault(self) -> None: ...
    def read_status(self) -> Any: ...
    def read_holding(self, reg: Any) -> int: ...
    def write_holding(self, reg: Any, value: int) -> None: ...
    def wait_state(self, states: Iterable[Any], timeout_s: float) -> Any: ...
    def wait_released(self, timeout_s: float, home_mm: float = ...) -> Any: ...
    def wait_force_settled(self, timeout_s: float) -> Any: ...
    def wait_speed_steady(self, timeout_s: float, tol_mm_s: float = ..., n_polls: int = ...) -> Any: ...
    def close(self) -> None: ...


@runtime_checkable
class TaxelSource(Protocol):
    """A stream of taxel frames: open, start/stop, captures of whole trials, a ring buffer for live views.

    ``layout`` is the sensor the frames come from (the board's identify reply decides it); ``banner`` the parsed
    identify reply (None before :meth:`open`).
    """

    banner: dict | None

    @property
    def layout(self) -> SensorLayout: ...
    @property
    def stats(self) -> Any: ...
    def open(self) -> dict: ...
    def start(self) -> None: ...
    def stop(self) -> None: ...
    def close(self) -> None: ...
    def begin_capture(self) -> None: ...
    def wait_capture(self, n_frames: int, timeout_s: float) -> bool: ...
    def capture_flag_index(self, mask: int) -> int | None: ...
    def end_capture(self) -> Any: ...


@runtime_checkable
class PlateMounter(Protocol):
    """Puts a texture plate on the drum. Called with the sensor released; returns when the plate is on.

    ``label`` is a label of ``textures`` (the set the session records): a simulated mounter renders the set's
    geometry for it, an operator mounter asks for the plate by name (with ``prompt`` if given, else its own).
    Raises KeyError / ValueError for a label it cannot mount.
    """

    def mount(self, label: str, textures: TextureSet, prompt: Callable[[str], Any] | None = None) -> None: ...


@runtime_checkable
class MassPlacer(Protocol):
    """Optional: a backend that can rest a calibration mass on the load cell (the simulated rigs); used by the
    load-cell calibration instead of asking an operator. ``place_mass(0)`` removes it."""

    def place_mass(self, mass_g: float) -> None: ...


@runtime_checkable
class RigBackend(Protocol):
    """What a ``Rig`` is opened on: it starts its boards and says where they are and how plates get mounted.

    ``__enter__`` starts the backend (virtual boards, simavr, nothing on hardware), ``__exit__`` stops it.
    ``drum()`` and ``taxels()`` return new clients of the two boards; ``mounter`` mounts plates; ``mode`` is
    "sim" | "hil" | "hardware" | "replay" | "inprocess"; ``textures`` is the texture set the backend mounts by
    default (the rig's :attr:`Rig.textures` until a protocol brings its own); ``describe()`` a JSON-able dict
    (mode, ports, seed, the simulated model's configuration) for the session's ``rig_config``. Backends that can
    place a calibration mass also implement :class:`MassPlacer`.
    """

    mode: str

    def __enter__(self) -> Any: ...
    def __exit__(self, *exc: Any) -> Any: ...
    def drum(self) -> DrumController: ...
    def taxels(self) -> TaxelSource: ...
    @property
    def mounter(self) -> PlateMounter: ...
    @property
    def textures(self) -> TextureSet: ...
    def describe(self) -> dict: ...


#: the operator prompt used by mounters on hardware: ``prompt(message)`` blocks until the operator confirms
Prompt = Callable[[str], Any]
