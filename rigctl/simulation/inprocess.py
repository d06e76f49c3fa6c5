"""The in-process backend: the simulated rig without ptys, threads or real-time pacing, for fast unit tests.

The drum controller is the firmware's own controller.c in :class:`rigctl.simulation.controller.MegaController` (the
same class the virtual Mega serves on a pty) driving :class:`rigctl.simulation.model.RigModel`; the host talks to it through
the ordinary :class:`rigctl.devices.drum.DrumClient` (every range check and wait of the real client) whose Modbus
transport calls the controller directly. The taxel source (:class:`InProcessTaxels`) frames the model's samples
as the Uno would (sequence numbers, SYNC_IN at the drum's index pulse, STREAMING_START on the first frame).

Time is simulated and advances only when the host acts: each Modbus request takes :attr:`InProcessEngine.request_ms`
of bus time (2 ms: a status read at 115200 baud), a ``wait_*`` poll of the drum client sleeps on the simulated
clock, and :meth:`InProcessTaxels.wait_capture` runs the simulation until the frames are there (up to its timeout,
in simulated time). A whole trial takes a fraction of its duration in wall time; the results (force settling,
index alignment, trial frames) are the model's, not a mock's. The host-silence watchdog is simulated only while a
``host-silence`` fault is injected (the host cannot be silent on a clock that only moves when it speaks): then each
request waits :data:`SILENT_ANSWER_MS` of simulated time for no answer, and controller.c's watchdog measures the
silence from the last request it handled (:meth:`MegaController.host_link`).

Faults (``open_rig("inprocess", inject=...)``, :mod:`rigctl.core.faults`) are applied on the simulated clock as it
passes their times (:class:`rigctl.simulation.faults.ModelFaults`).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from pymodbus.exceptions import ModbusIOException
from pymodbus.pdu import ExceptionResponse

from rigctl.core.drum import ResetCause
from rigctl.core.faults import FaultSchedule, FaultSpec
from rigctl.core.sensor import PAPER_SENSOR, SensorLayout
from rigctl.core.textures import PAPER_TEXTURES, TextureSet
from rigctl.devices import wire
from rigctl.devices.capture_parts import first_flagged, first_with_seq
from rigctl.devices.drum import DrumClient
from rigctl.devices.ring import RingBuffer
from rigctl.devices.taxel_stream import Capture, StreamStats
from rigctl.simulation.backend import SimMounter
from rigctl.simulation.controller import MegaController
from rigctl.simulation.faults import ModelFaults
from rigctl.simulation.model import RigConfig, RigModel
from rigctl.simulation.source_pacer import SourcePacer, source_layout

#: how long a request waits for no answer while ``host-silence`` is injected, simulated ms (a real link's answer
#: timeout, :data:`rigctl.rigs.ANSWER_TIMEOUT_S` of the hardware)
SILENT_ANSWER_MS = 500

__all__ = ["InProcessEngine", "InProcessTaxels", "InProcessBackend", "SimulatedClock"]


class SimulatedClock:
    """The engine's clock for :class:`DrumClient`: ``now()`` is simulated time (s), ``sleep(s)`` advances it."""

    #: nothing moves while the host does not sleep (rigctl.acquisition.rig.Rig.while_fed)
    stands_between_sleeps = True

    def __init__(self, engine: "InProcessEngine"):
        self.engine = engine

    def now(self) -> float:
        return self.engine.time_s

    def sleep(self, s: float) -> None:
        self.engine.advance(max(1, int(round(s * 1000.0))))


class InProcessEngine:
    """The rig's physics and controller on a simulated millisecond clock.

    Parameters
    ----------
    config : RigConfig or None; seed : int (model noise, drum start angle).
    request_ms : simulated bus time of one Modbus request, ms.
    factory_calibrated : the controller starts with its calibration in EEPROM (``MegaController``); False: an
        erased EEPROM (the controller runs on its defaults, flagged, and the rig warns).

    Attributes
    ----------
    model : RigModel; controller : MegaController; time_s : simulated time, s.
    """

    def __init__(self, config: RigConfig | None = None, *, seed: int = 0, request_ms: int = 2,
                 factory_calibrated: bool = True):
        self.config = config or RigConfig()
        self.model = RigModel(self.config, seed=seed)
        self.controller = MegaController(self.model, factory_calibrated=factory_calibrated)
        self.request_ms = int(request_ms)
        self._t_ms = 0
        self._lock = threading.RLock()
        self._listeners: list[Callable[[np.ndarray | None, np.ndarray, int], Any]] = []
        self._wanted: list[Callable[[], bool]] = []
        #: the injected faults (:meth:`InProcessBackend.inject_faults`) and what applies them
        self.faults = ModelFaults(self.controller, self.model, drum_link=self.controller.host_link,
                                  taxel_link=self._taxel_link)
        self.schedule: FaultSchedule | None = None
        self.taxel_link_up = True

    def _taxel_link(self, up: bool) -> None:
        self.taxel_link_up = bool(up)

    @property
    def time_s(self) -> float:
        with self._lock:
            return self._t_ms / 1000.0

    def listen(self, fn: Callable[[np.ndarray | None, np.ndarray, int], Any],
               wants_samples: Callable[[], bool] | None = None) -> None:
        """``fn(samples (n, 18) uint16, sync_in (n,) bool, t0_ms)`` after every advance (the taxel source).

        ``wants_samples()``: whether ``fn`` takes the next advance's samples (asked under the engine's lock, before
        it); when no listener does, they are not rendered and ``fn`` gets None (None: ``fn`` always takes them)."""
        self._listeners.append(fn)
        self._wanted.append(wants_samples or (lambda: True))

    def advance(self, n_ms: int) -> None:
        """Run the rig ``n_ms`` simulated milliseconds (physics + controller), then feed the listeners."""
        n_ms = int(n_ms)
        if n_ms <= 0:
            return
        with self._lock:
            if self.schedule is not None:
                self.schedule.due(self._t_ms / 1000.0)  # what is due by now acts from this step on
            samples, sync = self.controller.step(n_ms, render=any(wants() for wants in self._wanted))
            t0 = self._t_ms
            self._t_ms += n_ms
            for fn in self._listeners:
                fn(samples, sync, t0)

    def note_request(self) -> bool:
        """A request reaches the controller now (False: the host is cut off, ``host-silence``; nothing arrives)."""
        if self.faults.host_silent:
            return False
        self.controller.note_request()
        return True


class _Response:
    def __init__(self, registers=None):
        self.registers = list(registers or [])

    @staticmethod
    def isError() -> bool:
        return False


class _Transport:
    """pymodbus-client-shaped transport that calls :class:`MegaController` directly (one bus time per request)."""

    def __init__(self, engine: InProcessEngine):
        self.engine = engine

    def connect(self) -> bool:
        return True

    def close(self) -> None:
        pass

    def _request(self, fc: int, call):
        eng = self.engine
        with eng._lock:
            eng.advance(eng.request_ms)
            if not eng.note_request():  # the link is cut: the client waits out its answer timeout for nothing
                eng.advance(SILENT_ANSWER_MS)
                raise ModbusIOException("no answer (host-silence injected)")
            result = call()
        if result is None:
            return _Response()
        if isinstance(result, list):
            return _Response(result)
        return ExceptionResponse(fc, int(result))

    def read_holding_registers(self, address: int, *, count: int = 1, device_id: int = 1):
        return self._request(3, lambda: self.engine.controller.read_registers(3, address, count))

    def read_input_registers(self, address: int, *, count: int = 1, device_id: int = 1):
        return self._request(4, lambda: self.engine.controller.read_registers(4, address, count))

    def write_register(self, address: int, value: int, *, device_id: int = 1):
        return self._request(6, lambda: self.engine.controller.write_registers(6, address, [int(value)]))

    def write_registers(self, address: int, values: list[int], *, device_id: int = 1):
        return self._request(16, lambda: self.engine.controller.write_registers(16, address, [int(v) for v in values]))


class InProcessTaxels:
    """:class:`rigctl.core.interfaces.TaxelSource` on the engine: the model's samples framed as the Uno frames them.

    ``host_time_s`` of a capture is the simulated clock (s), the clock of the drum client's status times.
    """

    def __init__(self, engine: InProcessEngine, layout: SensorLayout = PAPER_SENSOR, *, source: Any = None):
        self.engine = engine
        self.port = "in-process"
        self._layout = source_layout(source) if source is not None else layout
        #: a source streamed instead of the model's sensor (``read(n)`` at its own rate), paced by the engine's steps
        self._pacer = None if source is None else SourcePacer(source, self._layout)
        self.banner: dict | None = None
        self._lock = threading.Lock()
        self._streaming = False
        self._first = False
        self._seq = 0
        self._frames = 0
        self._capture: list | None = None
        self._capture_count = 0
        #: the live ring (:class:`rigctl.devices.ring.RingBuffer`) once a live consumer asked for it
        #: (:meth:`enable_ring`); None before: the in-process tests pay nothing for it
        self.ring: RingBuffer | None = None
        engine.listen(self._feed, self._wants_samples)

    def enable_ring(self, seconds: float = 30.0) -> RingBuffer:
        """Keep the last ``seconds`` of frames in :attr:`ring` from now on, as a serial stream does (live
        consumers: the LSL outlets, a live view); returns it."""
        with self.engine._lock, self._lock:
            if self.ring is None:
                lay = self._layout
                self.ring = RingBuffer(max(1, int(seconds * lay.sample_rate_hz)), lay.n_channels)
            return self.ring

    @property
    def layout(self) -> SensorLayout:
        return self._layout

    @property
    def stats(self) -> StreamStats:
        with self._lock:
            up = self.engine.taxel_link_up
            return StreamStats(frames=self._frames, frames_per_s=self._layout.sample_rate_hz if self._streaming and up
                               else 0.0, connected=up)

    def open(self) -> dict:
        lay = self._layout
        self.banner = {"firmware": wire.UNO_FIRMWARE_VERSION,
                       "channels": lay.n_channels, "ch": lay.n_channels, "rate_hz": lay.sample_rate_hz,
                       "bits": lay.adc_bits, "baud": 0, "line": "in-process taxel source"}
        return self.banner

    def start(self) -> None:
        with self.engine._lock, self._lock:  # (the engine's: not between its question and its samples, _wants_samples)
            self._streaming = True
            self._first = True
            self._seq = 0

    def stop(self) -> None:
        with self._lock:
            self._streaming = False

    def close(self) -> None:
        self.stop()

    def _wants_samples(self) -> bool:
        """The model's samples of the engine's next advance are framed and kept (a capture or the live ring); asked
        under the engine's lock, which :meth:`start`, :meth:`begin_capture` and :meth:`enable_ring` take too."""
        with self._lock:
            return self._streaming and self._pacer is None and (self._capture is not None or self.ring is not None)

    def _feed(self, samples: np.ndarray | None, sync: np.ndarray, t0_ms: int) -> None:
        with self._lock:
            if not self._streaming or not self.engine.taxel_link_up:
                return
            n_ms = len(sync)
            unsent = 0
            if self._pacer is not None:  # the source's samples due in these n_ms ms, spread over them
                samples, pulse, unsent = self._pacer.step(n_ms, sync)
                sync = np.zeros(len(samples), bool) if pulse is None else pulse
            n = n_ms if samples is None else len(samples)
            # the counters step whether or not the frames are kept: the periods the source had no sample for
            # (unsent) are numbered, never sent (the host counts them lost)
            seq0, starts = self._seq, self._first and n > 0
            self._seq = (seq0 + n) % 65536
            self._first = self._first and not n
            self._frames += n - unsent
            if self._capture is None and self.ring is None:
                return
            assert samples is not None  # a capture or the ring asked for them (_wants_samples)
            seq = ((seq0 + np.arange(n)) % 65536).astype(np.uint16)
            flags = np.where(sync, int(wire.FrameFlag.SYNC_IN), 0).astype(np.uint8)
            if starts:
                flags[0] |= int(wire.FrameFlag.STREAMING_START)
            t = (t0_ms + (1 + np.arange(n)) * (n_ms / n if n else 1.0)) / 1000.0
            if unsent:
                n -= unsent
                samples, seq, flags, t = samples[:n], seq[:n], flags[:n], t[:n]
            if self.ring is not None:
                self.ring.write(samples, seq, flags, t)
            if self._capture is not None:
                self._capture.append((np.array(samples, np.uint16), seq, flags, t))
                self._capture_count += n

    def begin_capture(self) -> None:
        with self.engine._lock, self._lock:
            self._capture = []
            self._capture_count = 0

    def wait_capture(self, n_frames: int, timeout_s: float) -> bool:
        """Run the simulation until the capture holds ``n_frames`` frames or ``timeout_s`` simulated s passed."""
        # any positive wait advances at least 1 ms: a caller polling until its clock reaches a deadline a fraction
        # of a millisecond away must see the clock move, or it would spin forever
        left_ms = int(math.ceil(timeout_s * 1000.0)) if timeout_s > 0 else 0
        while True:
            with self._lock:
                if self._capture is None:
                    return False
                need = n_frames - self._capture_count
            if need <= 0:
                return True
            if left_ms <= 0:
                return False
            step = min(need, left_ms)
            self.engine.advance(step)
            left_ms -= step

    def capture_flag_index(self, mask: int) -> int | None:
        """Position of the first frame of the running capture with a bit of ``mask`` in its flags (None: none yet)."""
        with self._lock:
            parts = list(self._capture or ())
        return first_flagged(parts, mask)

    def capture_seq_index(self, seq: int) -> int | None:
        """Position of the first frame of the running capture of wire sequence number ``seq`` (None: none yet)."""
        with self._lock:
            parts = list(self._capture or ())
        return first_with_seq(parts, seq)

    def end_capture(self) -> Capture:
        with self._lock:
            parts, self._capture = self._capture, None
        if not parts:
            n = self._layout.n_channels
            return Capture(np.zeros((0, n), np.uint16), np.zeros(0, np.uint16), np.zeros(0, np.uint8),
                           np.zeros(0, np.float64))
        samples, seq, flags, t = (np.concatenate([p[i] for p in parts]) for i in range(4))
        return Capture(samples, seq, flags, t)


class InProcessBackend:
    """:class:`rigctl.core.interfaces.RigBackend` (and ``MassPlacer``) of the in-process simulated rig.

    ``rigctl.rigs.open_rig("inprocess", config=..., seed=..., factory_calibrated=True)``. Attributes: ``engine`` (:class:`InProcessEngine`),
    ``model``, ``controller``. ``source``: a replay source (``read(n)``, its ``layout``) the taxel source streams
    instead of the model's sensor (a sensor-only plugin's samples, :mod:`rigctl.core.rig_plugins`), read as the
    simulated clock passes its samples' times.
    """

    mode = "inprocess"

    def __init__(self, config: RigConfig | None = None, *, seed: int = 0, request_ms: int = 2,
                 textures: TextureSet | None = None, factory_calibrated: bool = True, source: Any = None):
        self.engine = InProcessEngine(config, seed=seed, request_ms=request_ms, factory_calibrated=factory_calibrated)
        self.source = source
        self.seed = seed
        self.textures = textures or PAPER_TEXTURES
        self.mounter = SimMounter(self.engine.model)

    @property
    def model(self) -> RigModel:
        return self.engine.model

    @property
    def controller(self) -> MegaController:
        return self.engine.controller

    def __enter__(self) -> "InProcessBackend":
        return self

    def __exit__(self, *exc) -> None:
        close = getattr(self.source, "close", None)  # a live source lets go of its device
        if callable(close):
            close()

    def drum(self) -> DrumClient:
        return DrumClient("in-process", transport=_Transport(self.engine), clock=SimulatedClock(self.engine),
                          poll_s=0.02)

    def taxels(self) -> InProcessTaxels:
        return InProcessTaxels(self.engine, source=self.source)

    def place_mass(self, mass_g: float) -> None:
        self.engine.model.place_mass(mass_g)

    # ------------------------------------------------------------------ fault injection (rigctl.core.faults)
    def fault_refusal(self, spec: FaultSpec) -> str | None:
        """Why the in-process rig cannot model ``spec`` (None when it can)."""
        return self.engine.faults.fault_refusal(spec)

    def inject_faults(self, specs: Sequence[FaultSpec], *, power_on: bool = False) -> FaultSchedule:
        """Arm ``specs`` on the simulated clock from now; returns the schedule. ``power_on``: the ``FAULT@0`` ones
        are applied now and the drum controller powers on again with them (it boots wired that way)."""
        schedule = FaultSchedule(specs, self.engine.faults.apply_fault)
        with self.engine._lock:
            schedule.start(self.engine.time_s)
            if power_on:
                schedule.due(self.engine.time_s)
                self.engine.controller.reset(ResetCause.POWER_ON)
            self.engine.schedule = schedule
        return schedule

    def describe(self) -> dict:
        out = {"mode": self.mode, "drum_port": None, "taxel_port": None, "seed": self.seed,
               "model": self.engine.config.to_dict()}
        if self.source is not None:
            out["replay_source"] = type(self.source).__name__
        return out
