"""The simulated rig: physical model + virtual Mega + virtual Uno on real ptys, on one physics clock shared with the
host (:attr:`SimulatedRig.clock`, docs/architecture.md "Time on a simulated rig").

A client uses exactly the code paths it uses with hardware: :class:`rigctl.devices.drum.DrumClient` on
:attr:`SimulatedRig.drum_port` (Modbus RTU via pymodbus) and :class:`rigctl.devices.taxel_stream.TaxelStream` on
:attr:`SimulatedRig.taxel_port` (pyserial). One thread owns the clock: every few ms it hands the elapsed
milliseconds to the Mega (which advances :class:`rigctl.simulation.model.RigModel` under its drum and actuator
commands, then runs its control logic) and the resulting taxel samples and index pulses to the Uno (which frames
and sends them if streaming). Paced, millisecond k is simulated no earlier than ``t0 + k`` ms, so the stream's
long-run rate is 1000 frames/s of wall time while the host keeps up; no millisecond is simulated more than 50 ms
past the host's last sign of life (a starved host pauses the rig, which then goes on without a burst). While the
Uno does not stream, the thread wakes every :data:`IDLE_TICK_S` instead
(the same milliseconds in longer steps, as a starved thread takes them; the Mega's control logic still acts at each
HX711 reading and at least every ``max_step_ms``).

With a replay source (``source=``, e.g. :class:`rigctl.simulation.replay.SessionReplay` of any session file) the
Uno streams the source's samples at the source's own layout and rate (``source.layout``: the board's banner
announces it, frames carry its channel count, and sample j goes out no earlier than ``t0 + j / rate``); the drum
and the force loop still run on the model. Mounting a plate (:meth:`SimulatedRig.set_texture`) tells a source that
follows plates (``source.mount(label)``) which texture's recordings to stream next.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Sequence
from functools import partial

import numpy as np

from rigctl.core.drum import ResetCause
from rigctl.core.faults import FaultSchedule, FaultSpec
from rigctl.core.port_clock import ClockFile
from rigctl.core.sensor import SensorLayout
from rigctl.core.shared_clock import SharedClock
from rigctl.simulation.faults import ModelFaults
from rigctl.simulation.model import RigConfig, RigModel
from rigctl.simulation.priority import board_thread
from rigctl.simulation.pty import PortDir
from rigctl.simulation.source_pacer import SourcePacer, source_layout
from rigctl.simulation.truth import TruthLog
from rigctl.simulation.virtual_mega import VirtualMega
from rigctl.simulation.virtual_uno import READER_LEAD_PACED_S, READER_LEAD_S, VirtualUno
from rigctl.simulation.world_loop import WorldLoop

log = logging.getLogger(__name__)

#: the physics thread's period while the Uno streams, s: frames go out in batches of about 5 (the host's reader takes
#: them every 25 ms). Each wake-up costs a fixed share (the thread's caches are cold after its sleep) besides the
#: milliseconds it simulates: in one process, alternating, a 3 ms tick cost 75-107 us of CPU a simulated ms, a 5 ms
#: tick 66-76 us
STREAM_TICK_S = 0.005
#: the physics thread's period while the Uno does not stream, s (``tick_s`` while it streams): the Mega's longest
#: control step (:attr:`rigctl.simulation.controller.MegaController.max_step_ms`); a rig nobody streams from (the
#: drum controller's conformance suite, a rig between its opening and START) costs a third of the wake-ups
IDLE_TICK_S = 0.010
#: the longest physics step between two rows of the truth log (``--truth-log``), ms: >= 100 rows a second
TRUTH_STEP_MS = 10
#: how often the rig looks whether the faces holding its clock file are stopped processes, s of wall time (while
#: their grant holds the world)
STOPPED_LOOK_S = 0.1
#: the world counts as held by the faces' grant when it is within this of it, s (the world steps in whole ms)
HELD_AT_S = 0.002


class SimulatedRig:
    """The whole simulated rig (context manager).

    Parameters
    ----------
    config : RigConfig or None
        Rig configuration (drum, sensor, mechanics); default :class:`RigConfig`.
    seed : int
        Seeds the model's noise and the start angle of the drum.
    source : object with ``read(n) -> (n, ch) uint16`` and ``layout`` (a SensorLayout), a callable, or None
        Replay source (:class:`rigctl.simulation.replay.SessionReplay`, ``FabricSlideReplay``): the Uno streams
        its samples at ``source.layout``'s channel count and rate (a source without ``layout``: the paper's 18
        channels at 1 kHz) instead of the model's sensor (the drum and force loop still run on the model).
    port_dir : path or None
        Directory for the two port links ``drum`` and ``taxel``, owned by this rig until :meth:`close` (a
        :class:`rigctl.simulation.pty.PortDir`: another live simulated rig's folder raises
        :class:`rigctl.simulation.pty.PortDirBusy`); a fresh temporary directory if None (the temporary directories of
        simulated rigs that were killed are removed first).
    tick_s : float
        Period of the physics thread while the Uno streams, s (frames go out in batches of about this length;
        :data:`STREAM_TICK_S`); :data:`IDLE_TICK_S` while it does not.
    uno_reset_delay_s : float
        Boot time of the virtual Uno after a client opens its port (simulated s).
    paced : bool
        Run the boards no faster than the wall clock (True: a person watching, live views, LSL) or as fast as the
        CPU and the host allow (False). Either way the host and the boards share :attr:`clock`. Paced with a
        ``source``, the world catches up the wall time a starved host lost (a live source's samples come on the wall
        clock: :class:`rigctl.simulation.world_loop.WorldLoop`'s ``keep_wall``).

    Attributes
    ----------
    drum_port, taxel_port : str
        Paths to open (Modbus RTU 500000 8N1 device 1; taxel stream 1,000,000 baud).
    model : RigModel
    mega : VirtualMega
    uno : VirtualUno
    clock : SharedClock
        The rig's one clock (the model's simulated time; docs/architecture.md "Time on a simulated rig"): the host's
        drum client and taxel stream time their waits and timeouts on it and grant the boards how far they may run;
        the Mega's watchdog and the Uno's boot judge it. A starved host pauses the whole rig.
    """

    def __init__(self, config: RigConfig | None = None, *, seed: int = 0, source=None, port_dir=None,
                 tick_s: float = STREAM_TICK_S, uno_reset_delay_s: float = 0.25, truth_log=None,
                 paced: bool = True):
        self.config = config or RigConfig()
        #: the ground truth as CSV (``truth_log``: a path; rigctl.simulation.truth), from :meth:`truth_start` on
        self.truth = TruthLog(truth_log) if truth_log is not None else None
        self.seed = seed
        self._port_dir = PortDir(port_dir, links=("drum", "taxel"))
        self.port_dir = self._port_dir.path
        try:
            # a face of another process on these ports shares the rig's time through this file (its grants)
            self._clock_file = ClockFile(self.port_dir)
            self._stopped_looked_at, self._stopped = -1.0, False
            try:
                self._build(source, uno_reset_delay_s)
                # the world's time from the start: a face that attaches before the first step grants from there (on
                # 0 it granted up to 50 ms, short of the model's 75 ms, and rig and face waited on each other forever)
                self._clock_file.publish(self.model_time_s())
            except BaseException:
                self._clock_file.close()
                raise
        except BaseException:
            self._port_dir.release(("drum", "taxel"))
            raise
        self.tick_s = tick_s
        self._stop = threading.Event()
        # a write to the Mega wakes the physics thread (paced_loop's wake_fd): its control logic acts on a command at
        # the next millisecond, also in an idle tick
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_w, False)
        self.mega.on_write = self._wake
        self.paced = bool(paced)
        self.clock = SharedClock(self.model_time_s, on_grant=self._granted, world_notifies=True)
        self._loop = WorldLoop(self.clock, self._now_ms, self._step, paced=self.paced, tick_s=self.tick_s,
                               idle=self._idle, idle_tick_s=max(self.tick_s, IDLE_TICK_S), wake_fd=self._wake_r,
                               board_busy=self._board_busy, horizon=self._horizon_s,
                               keep_wall=self.source is not None)  # a source's samples come on the wall clock
        self.mega.use_clock(self.model_time_s)
        self.mega.host_clock = self.clock  # the host's writes to the drum port are stamped on it (on their way)
        self.clock.in_flight = self._in_flight  # and its answer waits go on while one is
        self.mega.remote_stamp = partial(self._clock_file.stamp_s, "drum")  # and those of a face of another process
        self.uno.host_clock = self.clock  # the taxel reader's finds (a banner on its way: its wait goes on)
        self.uno.remote_stamp = partial(self._clock_file.stamp_s, "taxel")
        self.uno.use_clock(self.model_time_s)
        self._thread: threading.Thread | None = None
        self.step_errors = 0

    def _build(self, source, uno_reset_delay_s: float) -> None:
        self.source = source
        #: the sensor the taxel board streams (the source's, else the paper's 3x3x2 at 1 kHz)
        self.layout: SensorLayout = source_layout(source)
        self._pacer = None if source is None else SourcePacer(source, self.layout)
        self.model = RigModel(self.config, seed=self.seed)
        self.mega = VirtualMega(self.model, self.port_dir / "drum", factory_calibrated=True)
        self.uno = VirtualUno(self.port_dir / "taxel", reset_delay_s=uno_reset_delay_s, seed=self.seed,
                              layout=self.layout)
        #: the injected faults (:meth:`inject_faults`) and what applies them, on the physics clock
        self.faults = ModelFaults(self.mega, self.model, drum_link=self._drum_link, taxel_link=self._taxel_link)
        self.schedule: FaultSchedule | None = None
        self._added: list[FaultSchedule] = []  # add_faults'

    def model_time_s(self) -> float:
        """The rig's simulated time, s (the model's; :attr:`clock`)."""
        return self.model.time_s

    def _now_ms(self) -> int:
        return int(round(self.model.time_s * 1000.0))

    def _drum_link(self, up: bool) -> None:
        (self.mega.bridge.replug if up else self.mega.bridge.unplug)()

    def _taxel_link(self, up: bool) -> None:
        (self.replug_taxel if up else self.unplug_taxel)()

    def fault_refusal(self, spec: FaultSpec) -> str | None:
        """Why this rig cannot model ``spec`` (None when it can; :mod:`rigctl.core.faults`)."""
        return self.faults.fault_refusal(spec)

    def inject_faults(self, specs: Sequence[FaultSpec], *, power_on: bool = False) -> FaultSchedule:
        """Arm ``specs`` on the physics clock from now (replacing the schedule armed before by this method); the
        physics thread applies each as its time comes. ``power_on``: the ``FAULT@0`` ones are applied now and the
        drum controller powers on again with them."""
        self.schedule = self._arm(specs)
        if power_on:
            self.schedule.due(self.model.time_s)
            self.mega.reset(ResetCause.POWER_ON)
        return self.schedule

    def add_faults(self, specs: Sequence[FaultSpec]) -> FaultSchedule:
        """Arm ``specs`` on the physics clock from now beside every schedule armed before (``rigctl sim inject``:
        each call's faults start and end as given, whatever later calls arm)."""
        schedule = self._arm(specs)
        self._added = [s for s in self._added if s.pending] + [schedule]
        return schedule

    def _arm(self, specs: Sequence[FaultSpec]) -> FaultSchedule:
        schedule = FaultSchedule(specs, self.faults.apply_fault)
        schedule.start(self.model.time_s)
        return schedule

    @property
    def drum_port(self) -> str:
        return self.mega.path

    @property
    def taxel_port(self) -> str:
        return self.uno.path

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> "SimulatedRig":
        """Start the Modbus server and the physics thread (idempotent)."""
        if self._thread is None:
            self.mega.start(clock=False)
            self._stop.clear()
            self.clock.start()
            self.clock.own_port(self.drum_port)
            self.clock.own_port(self.taxel_port)
            self._thread = threading.Thread(target=board_thread(self._loop.run), args=(self._stop,),
                                            name="sim-physics", daemon=True)
            self._thread.start()
        return self

    def _wake(self) -> None:
        try:
            os.write(self._wake_w, b"w")
        except OSError:  # full: the thread is waking anyway
            pass

    def _in_flight(self, path: str) -> bool:
        """The host clock's ``in_flight``: a request to the drum port or its answer, or the taxel board's banner or
        reply, on its way (``VirtualMega.answer_in_flight``, ``VirtualUno.answer_in_flight``)."""
        return self.mega.answer_in_flight(path) or self.uno.answer_in_flight(path)

    def _granted(self, _horizon_s: float) -> None:
        """The host granted more time: a world held back for it wakes (one that is not costs no wake-up)."""
        loop = getattr(self, "_loop", None)
        if loop is not None and loop.held:
            self._wake()

    def _board_busy(self) -> bool:
        """The world stands still (:class:`rigctl.simulation.world_loop.WorldLoop`'s ``board_busy``): the drum
        controller is at a request of the host (bytes counted on the way). Unpaced also while a request or its reply
        is in the kernel's hands (``request_on_its_way``, ``reply_on_its_way``: an unpaced world ran the 2 s answer
        timeout out in the 0.5 s of wall time a starved server thread took, and a rig did not open: "no answer from
        the drum controller"), and while the host's taxel reader is more than :data:`READER_LEAD_S` of frames behind
        the stream (a starved reader is a starved host); paced, while it is more than :data:`READER_LEAD_PACED_S`
        behind (a reader starved while the heartbeat of its process ran the world on: the board's output queue ran
        over; never for a reader of a stopped face: :meth:`_reader_stopped`). Paced too while a request of the host is
        on its way (``request_on_its_way``: beside two CPU hogs a
        HOME the kernel or a starved server thread held let a paced world run 2 s on, and the conformance test saw no
        HOMING; once a paced world that stood lagged a live sample source for good, which it now catches up). A reply
        on its way is judged by the watchdog and the host's answer wait, not waited for, paced: a reply handed on in two
        chunks after the host's last find held a paced world whose face of another process polled every 50 ms nearly
        for good (a CI run)."""
        mega = self.mega
        if mega.at_request() or mega.request_on_its_way():
            return True
        uno = self.uno
        lead_s = READER_LEAD_PACED_S if self.paced else READER_LEAD_S
        if uno.streaming and uno.frames_unread() > lead_s * self.layout.sample_rate_hz and not self._reader_stopped():
            return True
        if self.paced:
            return False
        return mega.reply_on_its_way()

    def _reader_stopped(self) -> bool:
        """The taxel reader behind is a face of another process that is stopped (SIGSTOP: :meth:`_faces_stopped`), not
        a starved one: the world does not wait for it (a stopped reader never reads until it is continued; the world
        held for it 1.0 s of frames after the face stopped, READER_LEAD_PACED_S, short of the back-off the watchdog
        began, and for BUSY_MAX_S of wall time: the actuator left pressing ~209 g, issue 76). Its bytes meanwhile fill
        the board's output as a stopped host's fill a real board's USB-serial chip."""
        return self._clock_file.host_attached() and self._faces_stopped()

    def _idle(self) -> bool:
        """Nothing to send at the next tick: the Uno does not stream."""
        return not self.uno.streaming

    def _horizon_s(self) -> float:
        """How far the world may run, s: the grant of the hosts of this process (:attr:`clock`) and, while a face of
        another process holds the rig's clock file, the lower of that and its grant (rigctl.core.port_clock); the
        world loop asks at each step and look, and the face is told then whether its answer is on its way."""
        own = self.clock.horizon_s
        if self._clock_file.host_attached():
            # the face's answer waits go on while its request or the answer is on its way (HostSide.in_flight)
            mega = self.mega
            self._clock_file.publish_in_flight(mega.request_on_its_way() or mega.reply_on_its_way(),
                                               self.uno.output_on_its_way())
            grant = self._clock_file.grant_s()
            if grant < own and grant < self.model.time_s + HELD_AT_S and self._faces_stopped():
                return own  # a stopped face holds nothing: the rig keeps a real controller's time (its watchdog)
            return min(own, grant)
        return own

    def _faces_stopped(self) -> bool:
        """Whether the faces that hold the rig's clock file are all stopped processes
        (:meth:`rigctl.core.port_clock.ClockFile.hosts_stopped`), looked at most every :data:`STOPPED_LOOK_S` of
        wall time. A starved face still holds the world (its grant comes when it gets the CPU); a stopped one never
        grants until it is continued, and the world does not wait for it: WATCHDOG_MS of the rig's time later its
        controller's watchdog stops the rig, as a real controller's does while its host is frozen."""
        now = time.monotonic()
        if now - self._stopped_looked_at >= STOPPED_LOOK_S:
            self._stopped_looked_at = now
            self._stopped = self._clock_file.hosts_stopped()
        return self._stopped

    def _step(self, n_ms: int) -> None:
        if self.schedule is not None:
            self.schedule.due(self.model.time_s)
        for schedule in self._added:
            schedule.due(self.model.time_s)
        # the model's taxel samples only for a streaming board without a replay source (the Uno reads START
        # within its tick: a stream it starts there begins with the next tick, VirtualUno.tick)
        render = self._pacer is None and self.uno.streaming
        if self.truth is None:
            samples, sync_in = self.mega.step(n_ms, render=render)
        else:  # the truth log keeps >= 100 rows a second when a starved physics thread catches up in longer steps
            parts = []
            m = self.model
            for done in range(0, n_ms, TRUTH_STEP_MS):
                parts.append(self.mega.step(min(TRUTH_STEP_MS, n_ms - done), render=render))
                self.truth.row(m.time_s, m.contact_force_g, m.actuator_mm, m.drum_speed_mm_s, m.actuator_motor_mm)
            if len(parts) == 1:
                samples, sync_in = parts[0]
            else:
                samples = None if any(p[0] is None for p in parts) else np.concatenate([p[0] for p in parts])
                sync_in = np.concatenate([p[1] for p in parts])
        unsent = 0
        if self._pacer is not None:
            samples, sync_in, unsent = self._pacer.step(n_ms, sync_in)
        self.uno.tick(n_ms if samples is None else samples, sync_in, unsent)
        self._clock_file.publish(self.model_time_s())

    def truth_start(self) -> None:
        """The run starts now (physics clock): the truth log's time 0 (:mod:`rigctl.simulation.truth`)."""
        if self.truth is not None:
            self.truth.start(self.model.time_s)

    def close(self) -> None:
        """Stop the physics thread (joined), the Modbus server, close every pty and remove the port links."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=3)
            self._thread = None
        self.clock.close()
        self.clock.release_ports()
        if self.truth is not None:
            self.truth.close()
        self.mega.on_write = None
        try:
            self.uno.close()
            self.mega.close()
        finally:
            self._clock_file.close()
            self._port_dir.release(("drum", "taxel"))
            for fd in (self._wake_r, self._wake_w):
                if fd >= 0:
                    os.close(fd)
            self._wake_r = self._wake_w = -1  # (a second close() must not close what now has those numbers)
            close = getattr(self.source, "close", None)  # a live source (an LSL inlet) lets go of its stream
            if close is not None:
                close()

    def __enter__(self) -> "SimulatedRig":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ operator actions
    def set_texture(self, letter: str, textures=None) -> None:
        """Mount texture plate ``letter`` (a label of ``textures``, default the paper's A-P, or of the replay
        source's texture set) on the drum (the operator's action on the real rig).

        A replay source that follows plates (``mount``) streams that texture's recordings next; a label it has
        no recording of is logged and the source keeps streaming what it streamed."""
        mount = getattr(self.source, "mount", None)
        if mount is not None:
            try:
                mount(letter)
            except KeyError as exc:
                log.warning("replay: %s; streaming on", exc)
        own = getattr(self.source, "textures", None)
        if textures is None and own is not None and letter in own.labels:
            textures = own  # the model renders the replayed set's plate (the drum's force loop sees it)
        self.model.set_texture(letter, textures)

    def begin_source_trial(self) -> int | None:
        """A recorded trial starts: a replay source that follows its trials (``begin_trial``) goes on at the first
        sample of its next trial (:mod:`rigctl.simulation.replay`). Returns the wire sequence number of the frame
        that carries that sample; None without a replay source, in continuous play or before the stream starts."""
        begin = getattr(self.source, "begin_trial", None)
        start = self.uno.stream_start_sample
        if begin is None:
            return None
        pos = begin()
        if pos is None or start is None:
            return None
        return int(pos - start) & 0xFFFF

    def source_provenance(self, last_seq: int, n: int) -> dict:
        """Which source samples the ``n`` frames up to the one of wire sequence number ``last_seq`` (sent in the
        last 65536 frames) carried: the replay source's labels (``source_file``, ``source_trial_id``,
        ``source_texture``, ``source_speed_mm_s``, ``source_force_g`` or FabricSlide's setpoints) and
        ``source_first_sample`` / ``source_last_sample`` (inclusive, in that source trial); a trial that crosses
        source trials also gets ``source_pieces`` (JSON, one entry per source trial). {} without a replay source."""
        import json

        provenance = getattr(self.source, "provenance", None)
        start = self.uno.stream_start_sample
        if provenance is None or start is None or n < 1:
            return {}
        newest = int(self.source.samples_served) - 1 - start  # the frame number of the newest sample served
        frame = newest - ((newest - int(last_seq)) & 0xFFFF)
        pieces = provenance(start + frame - n + 1, n)
        if not pieces:
            return {}
        out = dict(pieces[0])
        if len(pieces) > 1:
            out["source_pieces"] = json.dumps(pieces)
        return out

    def place_mass(self, mass_g: float) -> None:
        """Rest a calibration mass of ``mass_g`` g on the load cell (0 removes it): see ``RigModel.place_mass``."""
        self.model.place_mass(mass_g)

    def unplug_taxel(self) -> None:
        """Pull the Uno's USB cable: its port vanishes."""
        self.uno.unplug()

    def replug_taxel(self) -> None:
        """Plug the Uno back in: the port reappears under the same path and the board boots."""
        self.uno.replug()
