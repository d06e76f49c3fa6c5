"""Hardware in the loop: the rig's real firmware images running in the AVR simulator simavr.

:class:`HilRig` has the interface of :class:`rigctl.simulation.rig.SimulatedRig` (context manager, ``drum_port``,
``taxel_port``, ``set_texture``, ``place_mass``), so :class:`rigctl.devices.drum.DrumClient`,
:class:`rigctl.devices.taxel_stream.TaxelStream` and ``rigctl.rigs.open_rig("hil")`` talk to it unchanged. It builds
the firmware and the harness if needed from the sources shipped in the package (:func:`rigctl.firmware.build`:
``rigctl/arduino``, the repo's ``arduino/``) and starts two harness processes (``arduino/simavr/rigctl_simavr.c``),
one per board, each raised above the host code (:mod:`rigctl.simulation.priority`):

- the Mega image (drum controller, Modbus RTU) with the HX711 and actuator spring emulated in C from the rig
  model's mechanics constants (:class:`rigctl.simulation.model.MechanicsConfig`), its drum STEP pin and index
  output watched (``TEL``/``IDX`` lines, see :attr:`HilRig.telemetry`);
- the Uno image (taxel streamer) with its ADC fed through the emulated multiplexers from waveforms rendered here by
  :class:`rigctl.simulation.model.SensorModel` (one physics model, in Python): a feeder thread renders the next
  two seconds of taxel readings from the drum travel and contact force the Mega harness reports, twice a second
  (``live`` mode), or a fixed waveform is played in a loop (:meth:`HilRig.play_waveform`, for exact-value tests).
  Each index pulse of the Mega is forwarded to the Uno's sync-in pin.

Both harnesses run in lock step on simulated time (``--clock-lock``) within the host's grant (:attr:`HilRig.clock`),
paced or not (``paced``), and exit when this object closes their stdin, or when this process dies.
"""

from __future__ import annotations

import collections
import logging
import os
import re
import tempfile
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from rigctl import firmware
from rigctl.core.faults import FaultSchedule, FaultSpec
from rigctl.core.shared_clock import SharedClock
from rigctl.devices import wire
from rigctl.simulation.hil_clock import HilClockFile
from rigctl.simulation.hil_faults import HilFaults
from rigctl.simulation.hil_harness import HilError, _Harness
from rigctl.simulation.mega_eeprom import (
    EepromError,
    default_record,
    eeprom_offset,
    factory_stiffness,
    state_address,
)
from rigctl.simulation.priority import board_thread
from rigctl.simulation.truth import TruthLog

if TYPE_CHECKING:
    from rigctl.simulation.textures import Texture

log = logging.getLogger(__name__)

_KV = re.compile(r"(\w+)=([-+0-9.eE]+)")


#: live rendering: rows (ms of the Uno's simulated time) of a new waveform that continue the playing one before
#: converging to the drum's reported travel and force, and rows of the force's convergence
_BLEND_START = 250
_BLEND_ROWS = 500
#: live rendering: largest change of the texture's speed under the taxels while the travel converges (fraction)
_MAX_CORRECTION = 0.2
#: live rendering: drum speed (mm per ms) below which the travel's correction is limited as at this speed
_MIN_SPEED = 0.01


#: wall time the Mega's core may stand still, alive and granted time, before a wait calls its harness hung, s: a
#: liveness guard against a hung process, far beyond any starvation seen (a pty hop's 30 s, KERNEL_HOP_MAX_S)
HARNESS_HANG_S = 300.0


def _parse_kv(line: str) -> dict[str, float]:
    return {k: float(v) for k, v in _KV.findall(line)}


@dataclass
class Telemetry:
    """One ``TEL`` line of the Mega harness (simulated time ``t_s``; pins and the spring model)."""

    t_s: float
    cycle: int
    drum_steps: int
    act_steps: int
    act_mm: float
    force_g: float
    index: int
    received: float = 0.0  #: host time.monotonic() when the line arrived
    drivers_enabled: bool = True  #: the stepper drivers' EN pin is active (low) now
    steps_disabled: int = 0  #: STEP pulses so far while the drivers were disabled (they moved nothing)
    ee_writes: int = 0  #: EEPROM byte writes the MCU made so far (EECR's EEPE), for the wear tests
    force_max_g: float = 0.0  #: the largest true force since the harness's previous report, g
    act_max_mm: float = 0.0  #: the actuator's furthest position towards the sensor since that report, mm
    drum_turn: float = 0.0  #: the real drum's revolutions (slip, a stall, a reversed motor included)
    #: the actuator motor's furthest position towards the sensor since that report, as the screw travel it turns, mm
    #: (the screw's plus a slipping coupling's wind-up: moved only by the motor's real steps)
    motor_max_mm: float = 0.0


@dataclass(frozen=True)
class LiveSwap:
    """One swap of live rendering's waveform (:attr:`HilRig.live_swaps`): ``loaded_s`` (host time.monotonic() when the
    load was sent; the swap comes after), ``done_s`` (when it was confirmed and measured; the swap came before),
    ``delay_rows`` (scans between the one the new waveform's row 0 stands for and the one after the swap: at most the
    rows it skipped; None when it could not continue the waveform playing: that one had run out, a starved feeder).
    ``late``: the swap skipped past the rows that continue the old waveform (:data:`_BLEND_START`), or could not
    continue it: the stream may jump there, the feeder's lateness."""

    loaded_s: float
    done_s: float
    delay_rows: int | None

    @property
    def late(self) -> bool:
        return self.delay_rows is None or self.delay_rows >= _BLEND_START


class HilRig:
    """Both boards' firmware under simavr, behind the :class:`~rigctl.simulation.rig.SimulatedRig` interface.

    Parameters
    ----------
    config : RigConfig or None
        Rig model configuration (sensor, mechanics: contact gap and stiffness, load-cell counts per g and offset);
        default :class:`rigctl.simulation.model.RigConfig`. The drum geometry must match the firmware's
        ``arduino/mega_drum/drum_config.h`` (100 mm, 200 steps/rev, 16 microsteps).
    seed : int
        Seeds the sensor noise of the rendered taxel readings.
    live : bool
        Render the taxel readings from the Mega's drum travel and force (True) or play a fixed waveform (False;
        :meth:`play_waveform`).
    firmware_sources : path, optional
        The firmware source folder (default :func:`rigctl.firmware.sources`, the installed package's); built on
        start into :func:`rigctl.firmware.build_dir`.
    uno_boot_ms : float
        Bootloader wait after a host opens the Uno's port (the DTR auto-reset).
    with_uno : bool
        Run the Uno too (default). False runs the Mega alone (no taxel port, no feeder): half the CPU for tests
        of the drum controller only.
    index_frames : bool
        With ``with_uno=False``: the backend's taxel source gives frames from the rig's clock marked at the Mega's
        index pulses (:class:`rigctl.simulation.hil_index_taxels.IndexFrames`: mid-scale counts, no measurement) so
        that the host records trials with the Mega alone (the fault campaign's Mega faults, issue 80 item 4).
    bootloaders : bool
        Load the boards' real bootloaders beside the sketches (the Mega's stk500v2, the Uno's optiboot: harness
        ``--bootloader``, docs/firmware.md) and reset each board when a host opens its port (the DTR auto-reset):
        the boot windows play out in simulated time. Hosts must then wait them out: :attr:`drum_boot_wait_s`,
        :attr:`drum_boot_quiet_s` for :class:`rigctl.devices.drum.DrumClient` (a pty has no DTR, so its defaults
        are 0). False (default): the Uno is held ``uno_boot_ms`` on open, the Mega never resets on open.
    taxel_ohm : float
        Source impedance of every taxel, Ohm (default 47 kOhm, docs/firmware.md "Multiplexer settling"): the Uno
        harness charges each 74HC4051 common node and the ADC's sample-and-hold capacitor through it, so a firmware
        that converts before the node settles reads part of the previous input. :meth:`set_taxel_ohm` changes one.
    tel_ms : float
        Period of the Mega harness's ``TEL`` reports (actuator, spring force, step counts), ms of simulated time.
    index_bounce : int
        Extra 0.1 ms pulses the drum index sensor gives after each mark (a bouncing contact; the firmware debounces).
    mega_image : str
        The Mega's image in the build folder: ``"mega_drum"`` (the shipped one) or ``"mega_drum_test"`` (the same
        with a hang input for the watchdog test, :meth:`hang_loop`; built by ``make harness``, never flashed).
    uno_image : str
        The Uno's image: ``"uno_taxel"`` (the taxel streamer) or ``"uno_encoder"`` (the same with the on-board SA
        encoder, docs/firmware.md "The encoder in the Uno image").
    factory_calibrated : bool
        Start the Mega's EEPROM calibrated (the defaults, as the simulated rigs); False: a freshly flashed board's.
    paced : bool
        Run the cores no faster than the wall clock (True) or as fast as the CPU and the host allow (False).

    Attributes
    ----------
    drum_port, taxel_port : str
        ``/dev/pts/N`` of the Mega (Modbus RTU 500000 8N1, device 1) and of the Uno (1,000,000 baud).
    clock, clock_file : SharedClock, HilClockFile
        The rig's one clock, the slower core's time: a starved host pauses both (docs/architecture.md); its file.
    telemetry : Telemetry or None
        Latest report of the Mega harness (every 50 ms of simulated time).
    isr : dict
        Latest ``ISR`` report of the Uno harness: ``sampler_cycles_per_tick``, ``sampler_max_per_tick``,
        ``tx_cycles_per_tick``, ``tx_max_per_tick`` (CPU cycles per 1 ms tick, timed on probe pins).
    boot_times_s, uno_boot_times_s : deque of float
        With ``bootloaders``: how long each bootloader run held the Mega / the Uno before the sketch started, s of
        simulated time (the harness's ``APP`` lines).
    mux : dict
        Latest ``MUX`` report of the Uno harness (every simulated second): ``settle_err_window_lsb`` (largest
        difference, in LSB, between the voltage a conversion sampled and the settled value of the taxel it converted,
        over the last second), ``settle_err_max_lsb`` (since start), ``conversions``, ``scan_us_window`` /
        ``scan_us_max`` (longest scan, first ADSC to the end of the last conversion, us, over the last second / since
        start).
    """

    def __init__(self, config=None, *, seed: int = 0, live: bool = True, firmware_sources: Path | str | None = None,
                 uno_boot_ms: float = 250.0, with_uno: bool = True, taxel_ohm: float = 47_000.0,
                 tel_ms: float = 50.0, bootloaders: bool = False, index_bounce: int = 0,
                 mega_image: str = "mega_drum", truth_log=None, factory_calibrated: bool = True,
                 uno_image: str = "uno_taxel", paced: bool = True, index_frames: bool = False):
        from rigctl.simulation.model import RigConfig

        if index_frames and with_uno:
            raise ValueError("index_frames stands in for the Uno: with with_uno=False only")
        self.index_frames = bool(index_frames)

        self.config = config or RigConfig()
        self.seed = seed
        self.live = live
        self.firmware_sources = Path(firmware_sources) if firmware_sources is not None else firmware.sources()
        self.uno_boot_ms = uno_boot_ms
        self.with_uno = with_uno
        self.taxel_ohm = float(taxel_ohm)
        self.tel_ms = float(tel_ms) if truth_log is None else min(float(tel_ms), 10.0)  # the truth log's 100 Hz
        self.truth = TruthLog(truth_log) if truth_log is not None else None  #: rigctl.simulation.truth, or None
        self.index_bounce = int(index_bounce)
        self.bootloaders = bool(bootloaders)
        self.boot_times_s: collections.deque[float] = collections.deque(maxlen=1000)
        self.uno_boot_times_s: collections.deque[float] = collections.deque(maxlen=1000)
        self.mux: dict[str, float] = {}
        self.mega_image = mega_image
        self.uno_image = uno_image
        self.factory_calibrated = bool(factory_calibrated)
        #: resets of the Mega the harness reported (the reset commands and the MCU's own, e.g. its watchdog)
        self.mega_resets = 0
        self._eeprom_ack: bool | None = None
        self.schedule: FaultSchedule | None = None  #: the injected faults (:meth:`inject_faults`)
        self._power_on_pending = False  # inject_faults(power_on=True) before start(): applied as the Mega starts
        #: the controller's own latches, from its RAM (the harness's ``STATE`` lines): [start_s, end_s or None] of
        #: the Mega's simulated time, each span its state was FAULT (:attr:`latch_spans`)
        self.latches: list[list[float | None]] = []
        #: commands for the Uno's harness given before it started (a fault wired so from power-on: the Mega's
        #: harness starts first and applies the schedule's FAULT@0 ones), sent once it runs
        self._uno_pending: list[str] = []
        self.faults = HilFaults(lambda c: self._running(self._mega, "Mega").send(c),
                                None if not with_uno else self._to_uno, taxel_ohm,
                                calibration_offset=self._calibration_offset,
                                calibration_record=self._calibration_record)
        self.telemetry: Telemetry | None = None
        self.telemetry_history: collections.deque[Telemetry] = collections.deque(maxlen=400)
        #: the actuator's reversals as the motor turned (``AREV``): (t_s of the new direction's first step, dir 1 =
        #: towards the sensor, t_s of the old direction's last step)
        self.actuator_reversals: collections.deque[tuple[float, int, float]] = collections.deque(maxlen=1000)
        #: simulated times host bytes reached the Mega (``RX``) and the actuator's steps that moved it (``ASTEP``: t_s,
        #: dir 1 = towards the sensor), after :meth:`log_requests`
        self.request_times: collections.deque[float] = collections.deque(maxlen=1000)
        self.actuator_steps: collections.deque[tuple[float, int]] = collections.deque(maxlen=50_000)
        self.index_pulses = 0
        #: the Mega's index pulses (its harness's IDX lines), s of the rig's clock
        self.index_times_s: collections.deque[float] = collections.deque(maxlen=100_000)
        self.isr: dict[str, float] = {}
        #: latest ``LOAD`` report of the Uno harness (every simulated second): ``busy_cycles_per_tick`` (mean over the
        #: second) and ``busy_max_per_tick`` (its largest tick; ``busy_max_since_start``): CPU cycles per 1 ms tick
        #: with interrupts off (an ISR, entry and exit included) or the encoder's probe (D10) high;
        #: ``encoder_cycles_per_tick`` / ``encoder_max_per_tick``: that probe alone (since start)
        self.load: dict[str, float] = {}
        #: every ``LOAD`` report, in order (a reader that looks now and then misses none)
        self.loads: list[dict[str, float]] = []
        #: the encoder image's scans: the waveform row of each one's first sample (the harness's ``ENCSTART``, from
        #: the image's marker pin D11; -1 before a waveform plays), in order
        self.encoder_start_rows: list[int] = []
        #: the Uno's simulated time at each of those scans' first sample (s), in the same order
        self.encoder_start_times_s: list[float] = []
        #: live rendering's waveform swaps (:class:`LiveSwap`), in order
        self.live_swaps: collections.deque[LiveSwap] = collections.deque(maxlen=10_000)
        #: host bytes reaching the Uno after :meth:`log_uno_requests`: (simulated time s, bytes), in order
        self.uno_requests: collections.deque[tuple[float, int]] = collections.deque(maxlen=100_000)
        self._texture: str | Texture = "A"  # a label of the paper's set, or a Texture (set_texture)
        self._mega: _Harness | None = None
        self._uno: _Harness | None = None
        self._tmp = Path(tempfile.mkdtemp(prefix="rigctl-hil-"))
        self.paced = bool(paced)
        self.clock_file = HilClockFile(self._tmp / "clock")
        self.clock: SharedClock = self.clock_file.shared_clock()
        self._stop = threading.Event()
        self._feeder: threading.Thread | None = None
        self._cond = threading.Condition()
        self._wave_acks = 0
        #: the last waveform loaded plays from the Uno's next scan (no scan since its reset), not from the next row
        #: boundary of a scan under way
        self.last_wave_playing = False
        self._ohm_acks = 0
        self._rxlog_acks = 0
        self._render_lock = threading.Lock()
        self._scan_reply: tuple[int, int] | None = None
        self._wave_pos: np.ndarray | None = None  # drum travel (mm) of each row of the waveform playing now
        self._wave_forces: np.ndarray | None = None  # its contact force (g) per row
        self._wave_force = 0.0  # contact force (g) the waveform playing now ends at

    @staticmethod
    def _running(harness: _Harness | None, board: str) -> _Harness:
        """``harness``, started; raises HilError before :meth:`start` (or after :meth:`close`)."""
        if harness is None:
            raise HilError(f"the {board} harness is not running (HilRig.start() first)")
        return harness

    # ------------------------------------------------------------------ properties
    @property
    def drum_port(self) -> str:
        return self._running(self._mega, "Mega").port

    @property
    def taxel_port(self) -> str:
        """The Uno's port. Raises HilError if this rig runs the Mega alone (``with_uno=False``)."""
        if not self.with_uno:
            raise HilError("this HilRig runs the Mega alone (with_uno=False): no taxel port")
        return self._running(self._uno, "Uno").port

    def index_frame_source(self):
        """The taxel source of a rig built with ``index_frames`` (:class:`rigctl.simulation.hil_index_taxels.
        IndexFrames` on :attr:`clock`); None otherwise."""
        if not self.index_frames:
            return None
        from rigctl.simulation.hil_index_taxels import IndexFrames

        return IndexFrames(self.clock, lambda: list(self.index_times_s))

    @property
    def drum_boot_wait_s(self) -> float:
        """``boot_wait_s`` a :class:`~rigctl.devices.drum.DrumClient` of this rig needs (0 without bootloaders): the
        simulated stk500v2 window plus 0.25 s (it is exact here: no clone's clock error, no USB latency, which
        :data:`~rigctl.devices.drum.MEGA_BOOT_WAIT_S` allows for on hardware), in the Mega's simulated time."""
        from rigctl.devices.drum import MEGA_BOOT_WINDOW_S

        return MEGA_BOOT_WINDOW_S + 0.25 if self.bootloaders else 0.0

    @property
    def taxel_banner_timeout_s(self) -> float | None:
        """``banner_timeout_s`` a :class:`~rigctl.devices.taxel_stream.TaxelStream` of this rig needs, s of host time
        (None: its default): with bootloaders the Uno's optiboot holds the sketch about 1 s of simulated time after
        the open's reset (its watchdog timeout), several seconds of host time on a loaded machine (the boot tests
        wait 60 s)."""
        return 60.0 if self.bootloaders and self.with_uno else None

    @property
    def drum_boot_quiet_s(self) -> float:
        """``boot_quiet_s`` a :class:`~rigctl.devices.drum.DrumClient` of this rig needs (0 without bootloaders)."""
        from rigctl.devices.drum import MEGA_BOOT_QUIET_S

        return MEGA_BOOT_QUIET_S if self.bootloaders else 0.0

    @property
    def mm_per_step(self) -> float:
        """Real drum surface travel per STEP pulse, mm (the driver's real microstep setting)."""
        d = self.config.drum
        return float(np.pi * d.diameter_mm / (d.steps_per_rev * d.true_microsteps))

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> "HilRig":
        """Build (if needed) and start both harnesses and, in live mode, the taxel feeder thread.

        Raises
        ------
        HilError if the build or a harness fails.
        """
        if self._mega is not None:
            return self
        try:
            build_dir = firmware.build(self.firmware_sources)
        except firmware.FirmwareBuildError as exc:
            raise HilError(str(exc)) from None
        exe = build_dir / "rigctl_simavr"
        m = self.config.mechanics
        # both cores in lock step on simulated time (on a starved host each falls behind the wall clock at its own
        # rate: the drum travel rendered for the Uno would play too fast or too slow)
        lock = self.clock_file.harness_args(paced=self.paced)
        self.clock.start()
        # calibrated and tared on the unloaded cell, its plate's stiffness stored (spec 2.12)
        record = default_record(int(m.loadcell_offset_counts),
                                factory_stiffness(m.contact_stiffness_g_per_mm, m.loadcell_counts_per_g))
        calibrated = ["--eeprom-write", f"{self._calibration_offset()}:{record.hex()}"] if self.factory_calibrated else []
        try:  # the controller's state byte: the harness reports each change (its latches, on the Mega's own clock)
            calibrated += ["--state-addr", str(state_address(build_dir / f"{self.mega_image}.elf"))]
        except EepromError:
            log.warning("HIL: no controller state in %s: latches are not reported", self.mega_image)
        mega_boot = (["--reset-on-open", "--bootloader", str(build_dir / "stk500v2_mega.hex")] if self.bootloaders
                     else [])
        uno_boot = ["--bootloader", str(build_dir / "optiboot_uno.hex")] if self.bootloaders else []
        self._mega = _Harness(exe, "mega", build_dir / f"{self.mega_image}.elf", [*mega_boot,
            "--spring-k", str(m.contact_stiffness_g_per_mm), "--contact-mm", str(m.contact_gap_mm),
            "--counts-per-g", str(m.loadcell_counts_per_g), "--loadcell-offset", str(int(m.loadcell_offset_counts)),
            *self._hardware_args(), *lock, *calibrated], self._on_mega_line, self.clock)
        self.clock_file.board_port("mega", self._mega.port)  # on self.clock, its writes stamped
        if self.schedule is not None and not self.schedule.armed:  # faults injected before the rig started
            self.faults.start(self.schedule, self.clock.now(), power_on=self._power_on_pending)
            if self._power_on_pending and self.truth is not None:  # a rig wired so from power-on: its truth from
                self.truth.start(0.0)  # the harness's time 0 (an open the fault refuses is judged on it too)
        if not self.with_uno:
            return self
        try:
            self._uno = _Harness(exe, "uno", build_dir / f"{self.uno_image}.elf",
                                 ["--reset-on-open", "--boot-ms", str(self.uno_boot_ms), *uno_boot,
                                  "--taxel-ohm", str(self.taxel_ohm), *lock], self._on_uno_line, self.clock)
        except BaseException:
            self._mega.close()
            self._mega = None
            raise
        self.clock_file.board_port("uno", self._uno.port)
        pending, self._uno_pending = self._uno_pending, []
        for command in pending:  # (a taxel-link-drop wired from power-on, fresh campaign seed 734043)
            self._uno.send(command)
        if self.live:
            self._render_and_load()
            self._stop.clear()
            self._feeder = threading.Thread(target=board_thread(self._feed), name="hil-feeder", daemon=True)
            self._feeder.start()
        return self

    def _to_uno(self, command: str) -> None:
        """Send ``command`` to the Uno's harness; before it started (the power-on faults, applied as the Mega's harness
        starts), once it runs."""
        if self._uno is None and self._mega is not None:
            self._uno_pending.append(command)
            return
        self._running(self._uno, "Uno").send(command)

    def _hardware_args(self) -> list[str]:
        """The harness options of the telemetry period (``tel_ms``), the HX711 (rate, oscillator error), the drum
        driver's microstep setting, the index sensor and the actuator driver's stall (off unless set), from the rig
        config (``MechanicsConfig.hx711_*``, ``.actuator_stall_g``, ``DrumConfig.driver_microsteps``,
        ``DrumConfig.index_sensor``)."""
        m, d = self.config.mechanics, self.config.drum
        args = ["--tel-ms", str(self.tel_ms), "--hx711-sps", str(int(m.hx711_rate_sps)),
                "--hx711-clock-error", str(m.hx711_clock_error),
                "--drum-driver-microsteps", str(d.true_microsteps), "--index-bounce", str(self.index_bounce)]
        args += ["--actuator-reversed"] if m.actuator_reversed else []
        args += ["--actuator-stall-g", str(m.actuator_stall_g)] if m.actuator_stall_g > 0 else []
        return args if d.index_sensor else [*args, "--no-index-sensor"]

    def close(self) -> None:
        """Stop the feeder and both harnesses (their processes exit when stdin closes)."""
        self._stop.set()
        if self._feeder is not None:
            self._feeder.join(timeout=3)
            self._feeder = None
        for h in (self._uno, self._mega):
            if h is not None:
                h.close()
        if self.truth is not None:
            self.truth.close()
        self.clock.close()
        self.clock.release_ports()
        self._uno = self._mega = None
        for f in self._tmp.glob("*"):
            f.unlink(missing_ok=True)
        try:
            self._tmp.rmdir()
        except OSError:
            pass

    def __enter__(self) -> "HilRig":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ operator actions and test hooks
    def set_texture(self, letter, textures=None) -> None:
        """Mount a texture plate: a label of ``textures`` (default the paper's A-P) or a
        :class:`rigctl.simulation.textures.Texture`; the taxel readings are rendered for it from now on.

        Raises
        ------
        KeyError for a label outside the set.
        """
        from rigctl.simulation.textures import get_texture

        self._texture = get_texture(letter, textures)
        if self.live and self._uno is not None:
            self._render_and_load()

    def play_waveform(self, samples: np.ndarray, timeout_s: float = 5.0) -> None:
        """Feed the Uno's ADC from ``samples`` ((n, 18) ADC counts 0-1023) in a loop, one row per scan (1 ms).

        Stops live rendering. The row after loading is the first row played.

        Raises
        ------
        ValueError for a bad shape or values; HilError if the harness does not confirm the load.
        """
        if not self.with_uno:
            raise HilError("this HilRig runs the Mega alone (with_uno=False): no taxel stream to feed")
        samples = np.asarray(samples)
        if samples.ndim != 2 or samples.shape[1] != wire.N_TAXELS or samples.shape[0] < 1:
            raise ValueError(f"samples must be (n, {wire.N_TAXELS}), got {samples.shape}")
        if samples.min() < 0 or samples.max() > wire.ADC_MAX:
            raise ValueError(f"samples must be ADC counts 0-{wire.ADC_MAX}")
        self.live = False
        self._stop.set()
        if self._feeder is not None:
            self._feeder.join(timeout=3)
            self._feeder = None
        # a live render already under way (a starved machine) finishes its load first and none follows: no live
        # waveform (and no ack of one) can land after this one
        with self._render_lock:
            self._wave_pos = None
            self._load(samples.astype("<u2"), timeout_s)

    def set_taxel_ohm(self, ohm: float, taxel: int | None = None, timeout_s: float = 5.0) -> None:
        """Set the source impedance (Ohm) of one taxel (0-17), or of every taxel (``taxel`` None), e.g. a
        high-impedance taxel whose reading lags behind its neighbours'.

        Raises ValueError for a bad taxel or a negative impedance; HilError if the harness does not confirm."""
        if taxel is not None and not 0 <= taxel < wire.N_TAXELS:
            raise ValueError(f"taxel must be 0-{wire.N_TAXELS - 1}, got {taxel}")
        if not ohm >= 0:
            raise ValueError(f"source impedance must be >= 0 Ohm, got {ohm}")
        if not self.with_uno:
            raise HilError("this HilRig runs the Mega alone (with_uno=False): no taxels")
        with self._cond:
            acks = self._ohm_acks
            self._running(self._uno, "Uno").send(f"taxel_ohm {-1 if taxel is None else int(taxel)} {float(ohm)}")
            if not self._cond.wait_for(lambda: self._ohm_acks != acks, timeout_s):
                raise HilError("the Uno harness did not confirm the source impedance")

    def bump(self, force_g: float) -> None:
        """Add an external force of ``force_g`` g on the load cell (0 removes it), e.g. to trip FORCE_LIMIT."""
        self._running(self._mega, "Mega").send(f"bump {float(force_g)}")

    def reset_mega(self, cause: str = "external") -> None:
        """Reset the Mega while the mechanics stay as they are (a reset under load): ``"external"`` (the reset button
        or a DTR pulse: MCUSR EXTRF), ``"brownout"`` (BORF) or ``"poweron"`` (PORF). The firmware restarts (RAM
        kept, except at a power-on; EEPROM kept)."""
        commands = {"external": "reset", "brownout": "brownout", "poweron": "poweron"}
        if cause not in commands:
            raise ValueError(f"cause must be one of {sorted(commands)}, got {cause!r}")
        self._running(self._mega, "Mega").send(commands[cause])

    def set_estop(self, opened: bool) -> None:
        """Open (``True``: pressed, or a broken wire) or close the normally-closed e-stop contact on the Mega's D2."""
        self._running(self._mega, "Mega").send("estop open" if opened else "estop close")

    def reverse_actuator(self, reversed_: bool = True) -> None:
        """Swap the actuator motor's coil pair (``True``: the firmware's "towards the sensor" moves it away and back
        again) or mend it; returns once the harness has it (a request sent after sees it: a bench action on the rig's
        clock, rigctl.simulation.hil_harness). HilError if it does not confirm."""
        if not self._running(self._mega, "Mega").send("actuator reversed" if reversed_ else "actuator ok"):
            raise HilError("the Mega harness did not confirm the actuator's wiring")

    def fault_refusal(self, spec: FaultSpec) -> str | None:
        """Why the harness cannot model ``spec`` (None when it can; :mod:`rigctl.core.faults`)."""
        return self.faults.fault_refusal(spec)

    def inject_faults(self, specs: Sequence[FaultSpec], *, power_on: bool = False) -> FaultSchedule:
        """Arm ``specs`` on the Mega's simulated time from now (:meth:`HilFaults.arm`; ``power_on``: FAULT@0). Before
        :meth:`start` (a rig wired so from power-on: :func:`rigctl.rigs.open_rig`), the schedule is armed when the
        Mega's harness starts, at its time 0, and the ``FAULT@0`` ones applied before its first instruction runs
        on the host's grant: no wait at all."""
        if self._mega is None:
            self.schedule = self.faults.schedule(specs)
            self._power_on_pending = power_on
            return self.schedule
        self.schedule = self.faults.arm(specs, self.clock.now(), power_on=power_on)
        return self.schedule

    def truth_start(self) -> None:
        """The run starts now (the Mega's simulated time): the truth log's time 0 (:mod:`rigctl.simulation.truth`)."""
        if self.truth is not None:
            self.truth.start(self.next_telemetry().t_s)

    @property
    def latch_spans(self) -> list[tuple[float, float | None]]:
        """Each span the controller held a latched fault (its state FAULT, read from its RAM by the harness: the
        instant it latched, to 0.1 ms, not when a host saw it), ``(start_s, end_s or None)``, on the truth log's clock
        (s from its start; the Mega's simulated time without a truth log)."""
        t0 = self.truth.t0_s if self.truth is not None and self.truth.t0_s is not None else 0.0
        with self._cond:
            return [(float(a or 0.0) - t0, None if b is None else float(b) - t0) for a, b in self.latches]

    def log_requests(self, on: bool = True) -> None:
        """Record the simulated time host bytes reach the Mega (:attr:`request_times`) and each actuator step
        (:attr:`actuator_steps`)."""
        self._running(self._mega, "Mega").send(f"rxlog {int(bool(on))}")

    def log_uno_requests(self, on: bool = True, timeout_s: float = 10.0) -> None:
        """Record the simulated time and size of each chunk of host bytes that reaches the Uno
        (:attr:`uno_requests`): when a host's command arrived on the board's clock. Returns once the harness
        confirms (bytes a host writes after the call are all recorded); HilError if it does not."""
        with self._cond:
            acks = self._rxlog_acks
            self._running(self._uno, "Uno").send(f"rxlog {int(bool(on))}")
            if not self._cond.wait_for(lambda: self._rxlog_acks != acks, timeout_s):
                raise HilError("the Uno harness did not confirm the request log")

    def set_loadcell_polarity(self, sign: int) -> None:
        """Mount the load cell the right way (``+1``) or reversed (``-1``: it reads negative under load)."""
        self._running(self._mega, "Mega").send(f"polarity {-1 if sign < 0 else 1}")

    def break_home_switch(self, broken: bool = True) -> None:
        """Break the home switch's wire (it never closes) or mend it."""
        self._running(self._mega, "Mega").send("homeswitch broken" if broken else "homeswitch ok")

    def corrupt_eeprom(self) -> None:
        """Flip a bit of the Mega's EEPROM calibration record (its checksum fails at the next boot); HilError if none."""
        offset = self._calibration_offset()
        with self._cond:
            self._eeprom_ack = None
            self._running(self._mega, "Mega").send(f"eeprom-flip {offset + 2}")  # a byte of the scale, past the magic word
            if not self._cond.wait_for(lambda: self._eeprom_ack is not None, timeout=10.0) or not self._eeprom_ack:
                raise HilError("the Mega harness did not confirm the EEPROM change (or could not make it)")

    def _calibration_offset(self) -> int:  # the record's EEPROM address in the Mega's image; HilError if not found
        try:
            return eeprom_offset(firmware.build_dir(self.firmware_sources) / f"{self.mega_image}.elf")
        except EepromError as exc:
            raise HilError(str(exc)) from None

    def _calibration_record(self, scale: float) -> bytes:
        """The calibration record of this rig's true calibration with its scale ``scale`` times the true one (a wrong
        calibration saved, its checksum valid: ``calibration-scale``)."""
        from rigctl.devices.wire import HoldingRegister as HR
        from rigctl.simulation.mega_eeprom import calibration_record

        true_scale = wire.join_s32(*(wire.holding_range(r)[2] for r in (HR.LOADCELL_SCALE_X100_HI,
                                                                          HR.LOADCELL_SCALE_X100_LO)))
        m = self.config.mechanics
        return calibration_record(int(round(true_scale * scale)), wire.holding_range(HR.ACTUATOR_STEPS_PER_MM)[2],
                                  int(m.loadcell_offset_counts),
                                  factory_stiffness(m.contact_stiffness_g_per_mm, m.loadcell_counts_per_g))

    def hang_loop(self) -> None:
        """Make the Mega's ``loop()`` hang until the MCU resets (only the test image ``mega_drum_test`` reacts: a
        hang input on D22, absent from the shipped image); its AVR watchdog must then reset it."""
        self._running(self._mega, "Mega").send("hang")

    def place_mass(self, mass_g: float) -> None:
        """A calibration mass on the load cell: the same external force as :meth:`bump`."""
        self.bump(mass_g)

    def step_rate_hz(self, window_s: float = 1.0, timeout_s: float = 5.0) -> float:
        """Drum STEP pulse rate measured on the pin over the last ``window_s`` of simulated time, steps/s.

        Waits until the harness has reported that much time after the call, however long it takes while reports
        keep coming (simavr falls behind real time on a starved machine); HilError if none comes for ``timeout_s``.
        """
        first = self._wait_telemetry(None, timeout_s)
        last = self._wait_telemetry(first.t_s + window_s, timeout_s)
        return (last.drum_steps - first.drum_steps) / ((last.cycle - first.cycle) / 16e6)

    def next_telemetry(self, timeout_s: float = 5.0) -> Telemetry:
        """The Mega harness's first report at the rig's time now or later (pins and spring now, not up to 50 ms ago):
        every line the harness printed before it has been read (a boot's ``APP``, a reset). HilError: none in ``timeout_s``."""
        return self._wait_telemetry(self.clock.now(), timeout_s)

    def _wait_telemetry(self, t_min: float | None, timeout_s: float) -> Telemetry:
        """The next report (``t_min`` None) or the first at simulated time ``t_min`` or later; HilError if no report
        comes for ``timeout_s`` of the rig's clock (while reports come, the wait goes on: the harness runs, however
        slowly), or the Mega's harness has exited. Judged on the rig's clock only: a loaded machine slows the cores,
        it never ends the wait (a harness that stands still while alive is waited for, as a starved one is; only
        :data:`HARNESS_HANG_S` of wall time with the cores standing still although this host grants them time ends
        it, as a hung process, never a verdict on the firmware)."""
        clock = self.clock
        deadline = clock.now() + timeout_s
        stuck_since, stuck_at = time.monotonic(), clock.now()
        mega = self._running(self._mega, "Mega")
        with self._cond:
            start = seen = self.telemetry
            while True:
                tel = self.telemetry
                if tel is not None and ((t_min is None and tel is not start) or (t_min is not None and tel.t_s >= t_min)):
                    return tel
                now = clock.now()
                if tel is not seen:  # reports keep coming: the harness runs, however slowly
                    seen = tel
                    deadline = now + timeout_s
                if now != stuck_at:
                    stuck_since, stuck_at = time.monotonic(), now
                if now >= deadline:
                    raise HilError(f"no telemetry from the Mega harness in {timeout_s:g} s of its clock")
                if mega.proc.poll() is not None:
                    raise HilError(f"the Mega harness exited (status {mega.proc.returncode})")
                if time.monotonic() - stuck_since > HARNESS_HANG_S:
                    raise HilError(f"the Mega harness's core stood still {HARNESS_HANG_S:g} s of wall time while "
                                   "granted time (a hung harness)")
                clock.touch()  # a waiting host lives: the cores may run on
                self._cond.wait(0.005)

    # ------------------------------------------------------------------ harness output
    def _on_mega_line(self, line: str) -> None:
        if line.startswith("TEL "):
            kv = _parse_kv(line)
            tel = Telemetry(kv["t"], int(kv["cycle"]), int(kv["drum_steps"]), int(kv["act_steps"]), kv["act_mm"],
                            kv["force_g"], int(kv["index"]), time.monotonic(), bool(kv.get("en", 1)),
                            int(kv.get("steps_disabled", 0)), int(kv.get("ee_writes", 0)),
                            kv.get("force_max_g", kv["force_g"]), kv.get("act_max_mm", kv["act_mm"]),
                            kv.get("drum_turn", 0.0), kv.get("motor_max_mm", kv.get("act_max_mm", kv["act_mm"])))
            with self._cond:
                self.telemetry = tel
                self.telemetry_history.append(tel)
                self._cond.notify_all()
            if self.schedule is not None:
                self.schedule.due(tel.t_s)
            if self.truth is not None and len(self.telemetry_history) > 1:
                # the largest true force and the furthest actuator position since the previous report (a peak between
                # reports is not lost), and the real drum's speed (its revolutions: a slip, a reversed motor)
                prev = self.telemetry_history[-2]
                dt = max((tel.cycle - prev.cycle) / 16e6, 1e-6)
                circ = float(np.pi * self.config.drum.diameter_mm)
                self.truth.row(tel.t_s, tel.force_max_g, tel.act_max_mm, (tel.drum_turn - prev.drum_turn) * circ / dt,
                               tel.motor_max_mm)
        elif line.startswith("STATE "):
            kv = _parse_kv(line)
            faulted = int(kv["state"]) == int(wire.DrumState.FAULT)
            with self._cond:
                if faulted and (not self.latches or self.latches[-1][1] is not None):
                    self.latches.append([kv["t"], None])
                elif not faulted and self.latches and self.latches[-1][1] is None:
                    self.latches[-1][1] = kv["t"]
        elif line.startswith("RX "):
            self.request_times.append(_parse_kv(line)["t"])
        elif line.startswith("ASTEP "):
            kv = _parse_kv(line)
            self.actuator_steps.append((kv["t"], int(kv["dir"])))
        elif line.startswith("AREV "):
            kv = _parse_kv(line)
            self.actuator_reversals.append((kv["t"], int(kv["dir"]), kv["last_t"]))
        elif line.startswith("APP "):
            self.boot_times_s.append(_parse_kv(line)["boot_s"])
        elif line.startswith("RESET "):
            self.mega_resets += 1
        elif line.startswith(("OK eeprom-flip", "ERR eeprom-flip")):
            with self._cond:
                self._eeprom_ack = line.startswith("OK")
                self._cond.notify_all()
        elif line.startswith("IDX "):
            self.index_pulses += 1
            # on the rig's one clock (its world time as the line is read: the harness's own t= is the core's cycle
            # count, which a reset or a held core sets apart from the clock's), a few ms late at most
            self.index_times_s.append(self.clock.now() if self.clock is not None else _parse_kv(line)["t"])
            if self._uno is not None:
                self._uno.send("sync")  # the index output is wired to the Uno's sync-in

    def _on_uno_line(self, line: str) -> None:
        if line.startswith("ISR "):
            self.isr = _parse_kv(line)
        elif line.startswith("LOAD "):
            self.load = _parse_kv(line)
            self.loads.append(self.load)
        elif line.startswith("ENCSTART "):
            kv = _parse_kv(line)
            with self._cond:
                self.encoder_start_times_s.append(kv["t"])
                self.encoder_start_rows.append(int(kv["row"]))
                self._cond.notify_all()
        elif line.startswith("RX "):
            kv = _parse_kv(line)
            self.uno_requests.append((kv["t"], int(kv["n"])))
        elif line == "OK rxlog":
            with self._cond:
                self._rxlog_acks += 1
                self._cond.notify_all()
        elif line.startswith("APP "):
            self.uno_boot_times_s.append(_parse_kv(line)["boot_s"])
        elif line.startswith("MUX "):
            self.mux = _parse_kv(line)
        elif line.startswith("OK taxel_ohm") or line.startswith("ERR taxel_ohm"):
            with self._cond:
                self._ohm_acks += 1
                self._cond.notify_all()
        elif line.startswith("SCAN "):
            kv = _parse_kv(line)
            with self._cond:
                self._scan_reply = (int(kv["n"]), int(kv["start"]))
                self._cond.notify_all()
        elif line.startswith("OK wave") or line.startswith("ERR wave"):
            with self._cond:
                self._wave_acks += 1
                self.last_wave_playing = line == "OK wave playing"
                self._cond.notify_all()
            if line.startswith("ERR"):
                log.error("HIL Uno harness: %s", line)

    # ------------------------------------------------------------------ taxel waveforms
    def _load(self, samples: np.ndarray, timeout_s: float = 5.0, base: int | None = None) -> None:
        path = self._tmp / "wave.u16"
        tmp = self._tmp / "wave.u16.tmp"
        samples.astype("<u2").tofile(tmp)
        os.replace(tmp, path)
        with self._cond:
            acks = self._wave_acks
            self._running(self._uno, "Uno").send(f"wave {path}" if base is None else f"wave {path} {int(base)}")
            deadline = time.monotonic() + timeout_s
            while self._wave_acks == acks:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise HilError("the Uno harness did not confirm the waveform")
                self._cond.wait(left)

    def playing_row(self, timeout_s: float = 2.0) -> int | None:
        """Row of the current waveform the Uno harness plays now (None if unknown): the board's clock in ms since the
        waveform began, however fast simavr runs."""
        scan = self._scan(timeout_s)
        return None if scan is None else scan[0] - scan[1]

    def _scan(self, timeout_s: float = 2.0) -> tuple[int, int] | None:
        """(scans so far, scan of the playing waveform's row 0) from the Uno harness (None if no reply)."""
        with self._cond:
            self._scan_reply = None
            self._running(self._uno, "Uno").send("scan?")
            deadline = time.monotonic() + timeout_s
            while self._scan_reply is None:
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._cond.wait(left)
            return self._scan_reply

    def _render_and_load(self, horizon_s: float = 2.0) -> None:
        """Render the next ``horizon_s`` of taxel readings from the latest drum travel, speed and force.

        The new waveform continues the drum travel and the force of the one playing now (the row playing is asked
        from the harness: no jump in the texture's phase or amplitude at the swap) and converges to the travel and
        force the Mega harness reports (:meth:`_drum_now`). Both boards' simulators fall behind real time on a
        starved machine (to a fifth of it and less), each at its own pace, so every prediction is made on the
        Mega's simulated time, and the travel converges no faster than :data:`_MAX_CORRECTION` of the drum's speed:
        a correction changes the texture's speed under the taxels by that fraction at most, never its phase.
        """
        with self._render_lock:
            if self._stop.is_set() or not self.live:  # play_waveform took over while this render waited
                return
            self._render_and_load_locked(horizon_s)

    def _drum_now(self, at: float) -> tuple[float, float, float]:
        """(travel mm, speed mm per ms of simulated time, contact force g) of the drum at host time ``at``.

        From the Mega harness's reports: the speed over the last 0.2 s of its simulated time (step counts over
        cycle counts), the travel extrapolated from the latest report by the simulated time elapsed since it arrived:
        the host time since then times the rate at which the Mega's simulated time has advanced per host second
        over the last second of reports (below 1 on a starved machine; a host-time extrapolation overshoots
        there by several mm at 40 mm/s)."""
        hist = list(self.telemetry_history)[-21:]
        if not hist:
            return 0.0, 0.0, 0.0
        tel = hist[-1]
        recent = hist[-5:]
        speed = 0.0
        if len(recent) >= 2 and recent[-1].cycle > recent[0].cycle:
            speed = ((recent[-1].drum_steps - recent[0].drum_steps) * self.mm_per_step
                     / ((recent[-1].cycle - recent[0].cycle) / 16e3))
        rate = 1.0  # simulated s per host s
        if len(hist) >= 2 and hist[-1].received > hist[0].received:
            rate = np.clip((hist[-1].t_s - hist[0].t_s) / (hist[-1].received - hist[0].received), 0.0, 1.0)
        elapsed_ms = max(0.0, at - tel.received) * rate * 1e3
        return tel.drum_steps * self.mm_per_step + speed * elapsed_ms, speed, max(tel.force_g, 0.0)

    def _render_and_load_locked(self, horizon_s: float) -> None:
        from rigctl.simulation.model import SensorModel

        if not hasattr(self, "_sensor"):
            self._sensor = SensorModel(self.config.sensor)
            self._rng = np.random.default_rng(self.seed)
        n = int(horizon_s * 1000)
        k = np.arange(n)  # rows = scans = ms of the Uno's simulated time
        wave_pos, wave_forces = self._wave_pos, self._wave_forces  # the waveform playing now (None: none yet)
        scan = self._scan() if wave_pos is not None else None
        target, speed, force = self._drum_now(time.monotonic())
        # the new waveform's target trajectory: the reported travel (at the scan just asked) and force
        new_pos = target + speed * k
        new_force = np.full(n, force)
        base = None
        old_pos, old_force = new_pos, new_force
        if scan is not None and wave_pos is not None and wave_forces is not None:
            # row 0 of the new waveform stands for scan n (the harness skips the rows already due when it swaps,
            # so the swap keeps the phase however long the render and the load take); it first continues the
            # waveform playing now (its travel and force, row for row, extrapolated past its end), then converges
            # to the target from _BLEND_START rows on: a swap within that many scans of the query is seamless
            row = scan[0] - scan[1]
            if 0 <= row < len(wave_pos) and abs(wave_pos[row] - target) < 50.0:
                base = scan[0]
                kk = row + k
                last = len(wave_pos) - 1
                tail = (wave_pos[-1] - wave_pos[-2]) if last >= 1 else 0.0
                old_pos = np.where(kk <= last, wave_pos[np.minimum(kk, last)], wave_pos[last] + tail * (kk - last))
                old_force = wave_forces[np.minimum(kk, last)]
        # from row _BLEND_START on, the travel moves at the drum's speed plus a correction that closes the gap to
        # the target within _BLEND_ROWS rows, but changes the texture's speed under the taxels by at most
        # _MAX_CORRECTION (a faster correction steepens the signal's edges like a seam would; the drum stopped: by
        # that fraction of _MIN_SPEED); the force converges linearly over _BLEND_ROWS rows
        c0 = min(_BLEND_START, n - 1)
        gap = new_pos[c0] - old_pos[c0]
        limit = _MAX_CORRECTION * max(abs(speed), _MIN_SPEED)
        slope = float(np.clip(gap / _BLEND_ROWS, -limit, limit))
        after = np.maximum(k - c0, 0)
        corrected = old_pos[c0] + speed * after + slope * np.minimum(after, abs(gap / slope) if slope else 0.0)
        position = np.where(k < c0, old_pos, corrected)
        forces = old_force + (new_force - old_force) * np.clip((k - c0) / _BLEND_ROWS, 0.0, 1.0)
        # the model's contact shape is that of a render call's mean force (non-linear in the force): render in
        # 25 ms chunks while the force changes, so each chunk's shape follows its force
        samples = np.empty((n, wire.N_TAXELS), dtype=np.uint16)
        edges = [0]
        while edges[-1] < n:
            a0 = edges[-1]
            steady = np.ptp(forces[a0:]) < 1e-3 * max(1.0, abs(forces[a0]))
            edges.append(n if steady else min(n, a0 + 25))
        for a0, b0 in zip(edges[:-1], edges[1:]):
            self._sensor.render(self._texture, position[a0:b0], forces[a0:b0], self._rng, out=samples[a0:b0])
        loaded_s = time.monotonic()
        self._load(np.clip(samples, 0, wire.ADC_MAX).astype("<u2"), base=base)
        if wave_pos is not None:  # a swap, not the first waveform: how late it came
            swapped = self._scan() if base is not None else None
            delay = None if swapped is None or base is None else swapped[0] - base
            self.live_swaps.append(LiveSwap(loaded_s, time.monotonic(), delay))
        self._wave_pos = position
        self._wave_forces = forces
        self._wave_force = force

    def _feed(self) -> None:
        while not self._stop.wait(0.5):
            try:
                self._render_and_load()
            except Exception:
                if not self._stop.is_set():
                    log.exception("HIL taxel feeder")
