"""The typed seams between the rig's parts: runtime-checkable :class:`typing.Protocol` interfaces.

The acquisition layer (``rigctl.acquisition``: the ``Rig`` facade, the trial runner, calibration) is written against
these, never against a concrete backend. Implementations:

- :class:`DrumController` (the roles :class:`DrumSetpoints`, :class:`DrumCommands`, :class:`DrumMonitor`,
  :class:`DrumCalibration`): ``rigctl.devices.drum.DrumClient`` (Modbus RTU to the Mega: real board, the virtual Mega,
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
:mod:`rigctl.core.drum` (the drum controller's typed values), :mod:`rigctl.core.sensor` and
:mod:`rigctl.core.textures`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any, Protocol, runtime_checkable

from rigctl.core.drum import Clock, DrumLimits, DrumState, DrumStatus, ForceLoopConfig, SettleBand, SpeedProfile
from rigctl.core.sensor import SensorLayout
from rigctl.core.textures import TextureSet

#: the kinds of rig backend (:attr:`RigBackend.mode`): the one list; :func:`rigctl.rigs.open_rig` builds each
RIG_KINDS = ("sim", "hil", "hardware", "replay", "inprocess", "handheld")

__all__ = ["RIG_KINDS", "DrumController", "DrumSetpoints", "DrumCommands", "DrumMonitor", "DrumCalibration",
           "TaxelSource", "PlateMounter", "MassPlacer", "RigBackend", "Prompt"]


@runtime_checkable
class DrumSetpoints(Protocol):
    """Setting the drum controller: speed and force setpoints (mm/s, g), the speed profile, the settle band and the
    force loop; reading its limits. Setters raise :class:`rigctl.core.drum.SetpointRangeError` (a ValueError)
    before anything is sent when a value is outside the controller's range."""

    def set_speed(self, mm_s: float) -> None:
        """Drum surface speed for the CONSTANT profile, mm/s (0 to the controller's speed limit)."""
        ...

    def set_force(self, g: float) -> None:
        """Contact-force setpoint the force loop holds, g (0 to the controller's force limit)."""
        ...

    def set_ramp(self, start_mm_s: float, end_mm_s: float, duration_s: float) -> None:
        """RAMP profile: linear from ``start_mm_s`` to ``end_mm_s`` (mm/s) over ``duration_s`` (0.001-60 s), then
        held; all three or none are set. Does not select the profile (:meth:`set_profile`)."""
        ...

    def set_profile(self, profile: SpeedProfile) -> None:
        """Select the speed profile the next RUN follows: CONSTANT or RAMP."""
        ...

    def limits(self) -> DrumLimits:
        """The controller's hard limits: speed, mm/s, and force, g (its SPEED_LIMIT / FORCE_LIMIT)."""
        ...

    def settle_band(self) -> SettleBand:
        """When the force loop counts as on target: force tolerance, g, held for settle time, ms."""
        ...

    def set_settle_band(self, *, force_tolerance_g: float | None = None, settle_time_ms: int | None = None) -> None:
        """Set the force tolerance (g, 1-500) and / or the settle time (ms, 0-10000); None keeps a value."""
        ...

    def force_loop(self) -> ForceLoopConfig:
        """The force loop's HX711 rate and PI gains (spec 2.9)."""
        ...

    def set_force_loop(self, config: ForceLoopConfig) -> None:
        """Set the force loop's HX711 rate and PI gains (all at once; range-checked before anything is sent)."""
        ...


@runtime_checkable
class DrumCommands(Protocol):
    """Commanding the drum controller (spec table 2.3); a command the state does not allow is refused
    (:class:`rigctl.core.drum.DrumError`)."""

    def run(self) -> None:
        """Start the drum on the selected profile (the force loop keeps holding; PRESS first if it is not)."""
        ...

    def stop(self) -> None:
        """Safe stop: drum decelerates to rest, actuator backs off home, state IDLE. Allowed in every state."""
        ...

    def stop_drum(self) -> None:
        """Decelerate the drum to rest, keep holding the force (FORCE_SETTLED)."""
        ...

    def press(self) -> None:
        """Engage the force loop: seek the force setpoint (SEEKING_FORCE), then hold it (FORCE_SETTLED)."""
        ...

    def tare(self) -> None:
        """Zero the load cell; only with the actuator released (IDLE)."""
        ...

    def home(self) -> None:
        """Drive the actuator to its home switch and zero its position (HOMING, then IDLE)."""
        ...

    def clear_fault(self) -> None:
        """Clear the latched faults and leave FAULT for IDLE; refused while the fault condition persists."""
        ...


@runtime_checkable
class DrumMonitor(Protocol):
    """Watching the drum controller: its status now, its settings, and waits polled on ``clock``
    (:class:`rigctl.core.drum.Clock`: the wall clock, or the in-process backend's simulated clock). A wait raises
    :class:`rigctl.core.drum.DrumTimeout` when not reached within ``timeout_s`` and
    :class:`rigctl.core.drum.DrumFault` when the controller latches a fault."""

    clock: Clock

    def read_status(self) -> DrumStatus:
        """The controller's state now: force, speed, angle, actuator position, state, faults, firmware."""
        ...

    def settings(self) -> dict[str, int]:
        """The controller's settings by name, raw (for the record: a session's ``rig_config``)."""
        ...

    def wait_state(self, states: Iterable[DrumState], timeout_s: float) -> DrumStatus:
        """Until the state is one of ``states`` (FAULT among them: a fault ends the wait instead of raising)."""
        ...

    def wait_released(self, timeout_s: float, home_mm: float = ...) -> DrumStatus:
        """Until IDLE with the actuator within ``home_mm`` (mm) of home, or its home switch closed: the sensor is free."""
        ...

    def wait_force_settled(self, timeout_s: float) -> DrumStatus:
        """Until the force loop is on target (FORCE_SETTLED, or RUNNING within the settle band)."""
        ...

    def wait_speed_steady(self, timeout_s: float, tol_mm_s: float = ..., n_polls: int = ...) -> DrumStatus:
        """Until the drum speed is within ``tol_mm_s`` (mm/s) of the profile's target for ``n_polls`` polls."""
        ...



@runtime_checkable
class DrumCalibration(Protocol):
    """Calibrating the drum controller's load cell (spec 2.1: LOADCELL_SCALE_X100_HI/_LO, SAVE_CALIBRATION)."""

    def set_loadcell_scale(self, counts_per_g: float) -> None:
        """Load-cell calibration: HX711 counts per g, signed (absolute value 1-100,000);
        :meth:`save_calibration` keeps it."""
        ...

    def loadcell_scale(self) -> float:
        """The controller's load-cell scale now, HX711 counts per g (signed)."""
        ...

    def calibration_stiffness(self) -> int:
        """The contact's stiffness stored with the calibration, g/mm (0: none stored; spec 2.12: every probe's
        stiffness is checked against it)."""
        ...

    def set_calibration_stiffness(self, g_per_mm: float) -> None:
        """Set the contact's stiffness stored with the calibration, g/mm (0-5000; 0: none, no check);
        :meth:`save_calibration` keeps it."""
        ...

    def save_calibration(self) -> None:
        """Write the calibration (load-cell scale, actuator steps per mm, the contact's stiffness) to the
        controller's EEPROM."""
        ...


@runtime_checkable
class DrumController(DrumSetpoints, DrumCommands, DrumMonitor, DrumCalibration, Protocol):
    """The drum controller (Mega) in the rig's terms, no registers (those stay inside ``rigctl.devices``): the
    roles :class:`DrumSetpoints`, :class:`DrumCommands`, :class:`DrumMonitor` and :class:`DrumCalibration` (one job
    each, as bluesky's protocols; a part that needs one role is typed against it), plus the link's life.

    Errors (all :mod:`rigctl.core.drum`): every call raises :class:`DrumError` when the controller does not answer
    or refuses (:class:`DrumTimeout`: no answer; a Modbus client adds ``ModbusExceptionError``); each role names
    its own. ``clock`` is also the clock the taxel source's ``host_time_s`` uses. A context manager: ``__enter__``
    opens the link (DrumError if it cannot), ``__exit__`` closes it.
    """

    def __enter__(self) -> Any:
        """Open the link to the controller; returns the controller. DrumError if it cannot be opened."""
        ...

    def __exit__(self, *exc: object) -> Any:
        """Close the link (:meth:`close`)."""
        ...

    def close(self) -> None:
        """Close the link; the controller keeps running on its own (its watchdog stops a drum left turning)."""
        ...


@runtime_checkable
class TaxelSource(Protocol):
    """A stream of taxel frames: open, start/stop, captures of whole trials, a ring buffer for live views.

    ``layout`` is the sensor the frames come from (the board's identify reply decides it); ``banner`` the parsed
    identify reply (None before :meth:`open`).
    """

    banner: dict | None

    @property
    def layout(self) -> SensorLayout:
        """The sensor the frames come from: channels, grid, rate (Hz), ADC bits (the board's identify reply; the
        paper's 3x3x2 at 1 kHz before :meth:`open`)."""
        ...

    @property
    def stats(self) -> Any:
        """A snapshot of the link's counters: ``frames``, ``dropped``, ``crc_errors``, ``frames_per_s``,
        ``connected``, ``reconnects`` (``rigctl.devices.taxel_stream.StreamStats``)."""
        ...

    def open(self) -> dict:
        """Open the link and wait for the board's ready banner; returns it parsed. ``TaxelStreamError`` when the
        board does not answer or answers nonsense."""
        ...

    def start(self) -> None:
        """Start streaming (the board restarts its sequence counter at 0, first frame flagged STREAMING_START)."""
        ...

    def stop(self) -> None:
        """Stop streaming (frames already sent are still taken)."""
        ...

    def close(self) -> None:
        """Stop streaming and close the link (best effort; never raises a link error)."""
        ...

    def begin_capture(self) -> None:
        """Keep every frame received from now on (one trial) until :meth:`end_capture`."""
        ...

    def wait_capture(self, n_frames: int, timeout_s: float) -> bool:
        """Block until the running capture holds ``n_frames`` frames; False after ``timeout_s`` s."""
        ...

    def capture_flag_index(self, mask: int) -> int | None:
        """Position in the running capture of the first frame with a flag bit of ``mask`` (e.g. SYNC_IN, the drum's
        index pulse); None if none yet or no capture runs."""
        ...

    def capture_seq_index(self, seq: int) -> int | None:
        """Position in the running capture of the first frame of wire sequence number ``seq`` (mod 65536; a replayed
        source trial's first frame); None if none yet or no capture runs."""
        ...

    def end_capture(self) -> Any:
        """End the capture; every frame since :meth:`begin_capture`: ``samples (n, n_channels)`` uint16 ADC counts,
        ``seq (n,)``, ``flags (n,)``, ``host_time_s (n,)`` s on the drum client's clock, ``dropped``,
        ``crc_errors``. ``TaxelStreamError`` when no capture runs."""
        ...


@runtime_checkable
class PlateMounter(Protocol):
    """Puts a texture plate on the drum. Called with the sensor released; returns when the plate is on.

    ``label`` is a label of ``textures`` (the set the session records): a simulated mounter renders the set's
    geometry for it, an operator mounter asks for the plate by name (with ``prompt`` if given, else its own).
    Raises KeyError / ValueError for a label it cannot mount.
    """

    def mount(self, label: str, textures: TextureSet, prompt: Callable[[str], Any] | None = None) -> None:
        """Put plate ``label`` of ``textures`` on the drum; returns when it is on (see the class docstring)."""
        ...


@runtime_checkable
class MassPlacer(Protocol):
    """Optional: a backend that can rest a calibration mass on the load cell (the simulated rigs); used by the
    load-cell calibration instead of asking an operator. ``place_mass(0)`` removes it."""

    def place_mass(self, mass_g: float) -> None:
        """Rest ``mass_g`` g on the load cell (0: take it off); returns when it rests there."""
        ...


@runtime_checkable
class ReplayProvenance(Protocol):
    """Optional: a backend streaming recorded trials (the replay rig). The rig calls :meth:`begin_source_trial` as
    each trial's capture starts and stores :meth:`source_provenance` in the trial's attributes, so a replayed trial
    keeps the source's labels and says which of its samples it holds."""

    def begin_source_trial(self) -> int | None:
        """A recorded trial starts: stream from the source's next trial (of the mounted plate) on. Returns the wire
        sequence number of the frame that carries its first sample (the frames before it were in flight), or None
        when the stream does not jump (continuous play, no replay)."""
        ...

    def source_provenance(self, last_seq: int, n: int) -> dict[str, Any]:
        """The source labels (``source_file``, ``source_trial_id``, ``source_texture``, ``source_speed_mm_s``,
        ``source_force_g``, ...) and ``source_first_sample`` / ``source_last_sample`` of the ``n`` frames up to wire
        sequence number ``last_seq``; {} when the backend replays nothing."""
        ...


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

    def __enter__(self) -> Any:
        """Start the backend (virtual boards, simavr; nothing on hardware). Raises when it cannot start."""
        ...

    def __exit__(self, *exc: Any) -> Any:
        """Stop the backend (never raises)."""
        ...

    def drum(self) -> DrumController:
        """A new client of the drum controller (not yet opened)."""
        ...

    def taxels(self) -> TaxelSource:
        """A new client of the taxel board (not yet opened)."""
        ...

    @property
    def mounter(self) -> PlateMounter:
        """How plates get on the drum (the simulation renders them; on hardware an operator is asked)."""
        ...

    @property
    def textures(self) -> TextureSet:
        """The texture set the backend mounts by default."""
        ...

    def describe(self) -> dict:
        """JSON-able: mode, ports, seed, the simulated model's configuration (a session's ``rig_config``)."""
        ...


#: the operator prompt used by mounters on hardware: ``prompt(message)`` blocks until the operator confirms
Prompt = Callable[[str], Any]
