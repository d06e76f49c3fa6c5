"""The simulated drum controller (Arduino Mega 2560): a Modbus RTU server on a pty with the Mega's control logic.

Implements ``docs/wire-protocol.md`` section 2 from the board's side: every holding and input register, the range
column and the speed/force limits (illegal value -> exception 03, unknown address -> 02, other functions -> 01; a
function-16 write is checked as a whole before any register changes), the commands and states, the CONSTANT and
RAMP speed profiles, a PI force loop on actuator velocity against the load cell, settle detection
(FORCE_TOLERANCE_G for SETTLE_TIME_MS), the force-limit fault (actuator backs off at once), the host-silence
watchdog (any valid request to device 1 feeds it), the 10 ms heartbeat, tare, home, clear fault, and the calibration
registers kept in an emulated EEPROM (in memory, or a JSON file).

The logic is the firmware's controller.c in :class:`rigctl.simulation.controller.MegaController` (shared with the
in-process backend); the
Modbus side is pymodbus' own :class:`pymodbus.server.ModbusSerialServer` (RTU framer, device id 1, 500000 8N1)
on one end of a :class:`rigctl.simulation.pty.PtyBridge`; the client opens :attr:`VirtualMega.path`. The physics is
:class:`rigctl.simulation.model.RigModel` (drum step rate and actuator velocity in, load cell and drum state out);
whoever owns the simulation clock calls :meth:`VirtualMega.step` (the rig's physics thread), or
:meth:`VirtualMega.start` runs its own real-time control loop.

The host-silence watchdog is checked in the Modbus server's own thread (its asyncio loop), as the firmware checks it
in the same main loop that handles frames (``arduino/mega_drum/mega_drum.cpp``: a frame is handled, and feeds the
watchdog, within about a millisecond of its last byte; ``ctl_tick`` never sees a request that has arrived but is not
handled). A Python thread, unlike the Mega, can be starved for hundreds of ms on a loaded machine (GIL, CPU), so
the check also refuses to call the host silent while request bytes wait anywhere between the client's port and the
server (:meth:`rigctl.simulation.pty.PtyBridge.bytes_to_board`): the silence the watchdog measures is the host's,
not the simulator's. (The price under such starvation: a host that really was silent for just over the timeout
and then spoke again before the simulator got to check may go unnoticed.)
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections.abc import Callable

from pymodbus.constants import ExcCodes
from pymodbus.datastore import ModbusBaseDeviceContext, ModbusServerContext
from pymodbus.framer import FramerType
from pymodbus.pdu import DecodePDU, ExceptionResponse, ModbusPDU

from rigctl.core.shared_clock import SharedClock, host_stamp, on_a_kernel_hop, port_keys
from rigctl.devices import wire
from rigctl.devices.wire import HoldingRegister as HR
from rigctl.simulation.controller import MegaController
from rigctl.simulation.model import RigModel
from rigctl.simulation.priority import board_thread
from rigctl.simulation.pty import PtyBridge
from rigctl.simulation.world_loop import WorldLoop

log = logging.getLogger(__name__)

#: period of the watchdog check in the Modbus server's loop once the host may be overdue, s
WATCHDOG_CHECK_S = 0.01
#: the longest wait between two checks while the host cannot be overdue yet, s: the shortest WATCHDOG_MS
WATCHDOG_IDLE_CHECK_S = wire.holding_range(HR.WATCHDOG_MS)[0] / 1000.0


class _Refusal(ModbusPDU):
    """A request refused with a Modbus exception before it reaches the register map (see :class:`_SpecDecoder`)."""

    def __init__(self, function_code: int, exception_code: int):
        super().__init__()
        self.function_code = function_code
        self.refusal = exception_code

    def decode(self, data: bytes) -> None:  # pragma: no cover - built by _SpecDecoder, never decoded
        pass

    def encode(self) -> bytes:  # pragma: no cover - a request, never sent: update_datastore answers for it
        return b""

    async def update_datastore(self, context) -> ModbusPDU:
        return ExceptionResponse(self.function_code, self.refusal)


#: the function codes of the spec (section 2): read holding, read input, write single, write multiple
_FUNCTIONS = (3, 4, 6, 16)


class _SpecDecoder(DecodePDU):
    """pymodbus' request decoder held to the spec, as the firmware's ``modbus_slave.c``: a function pymodbus knows
    but the spec does not (07 read exception status, 43 device identification...) gets exception 01 instead of
    pymodbus' own answer; a request whose length does not fit its function (a function-16 byte count that does not
    match its register count, a read of 0 or more than 125 registers) gets exception 03. pymodbus' decoder raised
    on the function-16 case and kept the frame in its receive buffer: the server answered nothing ever after."""

    def decode(self, frame: bytes) -> ModbusPDU | None:
        fc, body = frame[0], frame[1:]
        if fc not in _FUNCTIONS:
            return _Refusal(fc, ExcCodes.ILLEGAL_FUNCTION)
        count = int.from_bytes(body[2:4], "big") if len(body) >= 4 else 0
        if fc in (3, 4):
            bad = len(body) != 4 or not 1 <= count <= 125
        elif fc == 6:
            bad = len(body) != 4
        else:
            bad = len(body) < 5 or not 1 <= count <= 123 or body[4] != 2 * count or len(body) != 5 + body[4]
        if bad:
            return _Refusal(fc, ExcCodes.ILLEGAL_VALUE)
        return super().decode(frame)


class _MegaContext(ModbusBaseDeviceContext):
    """pymodbus device context that hands every register access to the :class:`VirtualMega`."""

    def __init__(self, mega: "VirtualMega"):
        self.mega = mega

    def reset(self):  # pragma: no cover - pymodbus API
        pass

    def getValues(self, func_code, address, count=1):
        return self.mega._read(func_code, address, count)

    def setValues(self, func_code, address, values):
        result = self.mega._write(func_code, address, values)
        if self.mega.on_write is not None:  # the clock's owner acts on it at its next millisecond
            self.mega.on_write()
        return result


class VirtualMega(MegaController):
    """Virtual drum controller: the :class:`MegaController` logic served as Modbus RTU on a pty.

    Parameters
    ----------
    model : RigModel
        The physics it drives (shared with the virtual Uno in :class:`rigctl.simulation.rig.SimulatedRig`).
    link : path or None
        Stable path the client opens (symlink to the pty).
    eeprom_path : path or None
        JSON file emulating the EEPROM (calibration registers); None keeps it in memory.

    Attributes
    ----------
    requests : int
        Valid requests addressed to device 1 so far.
    write_requests : int
        Write requests that reached the register map, accepted or refused (for tests: "nothing was sent").
    writes : deque of (function_code, address, values)
        The last 1000 of them.
    """

    def __init__(self, model: RigModel, link=None, *, eeprom_path=None, factory_calibrated: bool = False):
        super().__init__(model, eeprom_path=eeprom_path, factory_calibrated=factory_calibrated)
        self.bridge = PtyBridge(link)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server = None
        self._server_thread: threading.Thread | None = None
        self._clock_thread: threading.Thread | None = None
        #: the board's own shared clock when it runs its own control loop (``start(clock=True)``), else None
        self.clock: SharedClock | None = None
        self._stop = threading.Event()
        #: the request count when a check last found the host overdue with nothing on the way (check_watchdog)
        self._overdue_at_requests: int | None = None
        #: when the Modbus server last received bytes from its port (time.monotonic, its own loop's clock)
        self._received_at = 0.0
        #: when the Modbus server last began to write a reply to its port (time.monotonic)
        self._sent_at = 0.0
        #: when the Modbus server last decoded a request to its device (time.monotonic): until it begins to write the
        #: answer, the board is at the request (:meth:`at_request`)
        self._request_at = 0.0
        #: the shared clock of the host that talks to this board in this process (its writes' stamps:
        #: :meth:`request_on_its_way`), or None
        self.host_clock: SharedClock | None = None
        #: a face of another process's stamps of this port, ``remote_stamp(written)`` (``time.monotonic``, 0.0: none;
        #: ``SimulatedRig``: its clock file's, :meth:`rigctl.core.port_clock.ClockFile.stamp_s`), or None
        self.remote_stamp: Callable[[bool], float] | None = None
        #: called after every write request (``SimulatedRig``: wakes its physics thread, so the control logic acts on a
        #: command within a millisecond, as the firmware's loop does, not at the end of an idle tick)
        self.on_write: Callable[[], None] | None = None

    def use_clock(self, now: Callable[[], float]) -> None:
        """Judge the host-silence watchdog on ``now()`` (s; the simulated rig's shared clock, on which a starved host
        is never silent: docs/architecture.md "Time on a simulated rig"), from now on."""
        with self._lock:
            self._now = now
            self._last_request = now()

    def at_request(self) -> bool:
        """A request of the host is on its way in or its answer on its way out, counted between the host's port and the
        Modbus server (in the ptys or the bridge's hands: its threads are the board's, outside the physics clock; a
        world on the shared clock waits for them, as the firmware answers within a millisecond of its own time), or
        the server has decoded a request and not yet begun its answer (its thread decodes, executes and answers two
        event-loop hops after it takes the bytes in, when the GIL and the CPU let it: a world that ran on meanwhile
        ran the host's 2 s answer timeout out, DrumTimeout "no answer" in four conformance modules of a CI run beside
        two CPU hogs). Not the bytes the kernel holds (:meth:`request_on_its_way`, :meth:`reply_on_its_way`): on a
        loaded machine that took up to seconds, and a held paced world lags a live sample source for good (a
        wall-paced CSV board beside the CI's load: samples repeated or skipped); the watchdog and the host's answer
        wait (:meth:`answer_in_flight`) judge those instead. (An answer never begun: the world loop's ``BUSY_MAX_S``
        bounds the wait, and the next request's answer ends it.) Lock-free."""
        bridge = self.bridge
        return bool(bridge.bytes_to_board() or bridge.bytes_from_board() or self._request_at > self._sent_at)

    def request_on_its_way(self) -> bool:
        """Bytes the host wrote to the board's port that the Modbus server has not received yet, wherever they are:
        counted in the ptys (:meth:`rigctl.simulation.pty.PtyBridge.bytes_to_board`), or in the kernel's hands,
        where no count sees them (a pty's writer hands its bytes to the reader's side through a kernel worker, which a
        loaded machine holds back for up to hundreds of ms: a request held there for 0.76 s while the world ran on
        tripped the watchdog of a host that had spoken): written by the host (:attr:`host_clock`'s
        :meth:`~rigctl.core.shared_clock.SharedClock.written_at`) after the bridge last took any from the client's
        pty, or handed to the board's pty after the server last received any. Lock-free."""
        bridge = self.bridge
        if bridge.bytes_to_board() or bridge.to_board_at > self._received_at:
            return True
        if not bridge.client.plugged:
            return False
        return on_a_kernel_hop(self._host_stamp(True), bridge.from_client_at)

    def reply_on_its_way(self) -> bool:
        """Bytes of a reply the Modbus server wrote that have not reached the host's side of the port yet: counted
        (:meth:`rigctl.simulation.pty.PtyBridge.bytes_from_board`), or in the kernel's hands: on the board's side
        (written after the bridge last took any from it), or on the host's (handed to the client's pty after a host of
        this process last found bytes there (:attr:`host_clock`'s
        :meth:`~rigctl.core.shared_clock.SharedClock.read_at`), and none there now). Lock-free."""
        bridge = self.bridge
        if bridge.bytes_from_board() or self._request_at > self._sent_at:
            return True
        if on_a_kernel_hop(self._sent_at, bridge.from_board_at):
            return True
        read_at = self._host_stamp(False)  # 0.0: no host that stamps reads the port
        return read_at > 0.0 and on_a_kernel_hop(bridge.to_client_at, read_at) and not bridge.client.unread_by_board()

    def answer_in_flight(self, path: str) -> bool:
        """Whether ``path`` is this board's port and a request the host wrote there or its answer is on its way
        (:meth:`request_on_its_way`, :meth:`reply_on_its_way`): the host clock's ``in_flight``
        (:meth:`rigctl.core.shared_clock.SharedClock.wait_for`), so a host's answer wait does not give up on an answer
        the board or the kernel still holds. Lock-free."""
        return bool(port_keys(path) & port_keys(self.path)) and (self.request_on_its_way() or self.reply_on_its_way())

    def _host_stamp(self, written: bool) -> float:
        """When a host last began to write to this port (``written``) or last found bytes there to read
        (``time.monotonic``, 0.0: never): of this process (:attr:`host_clock`) or of another (:attr:`remote_stamp`),
        the later."""
        return host_stamp(self.host_clock, self.path, self.remote_stamp, written)

    # ------------------------------------------------------------------ lifecycle
    @property
    def path(self) -> str:
        """The path a Modbus master opens (500000 8N1, RTU, device id 1)."""
        return self.bridge.client_path

    def start(self, *, clock: bool = True, control_period_s: float = 0.005) -> "VirtualMega":
        """Start the Modbus server thread and, with ``clock=True``, a control loop paced to real time (200 Hz default)
        on a clock of its own shared with the host (:attr:`clock`: its port's clients in this process time themselves
        on it, and a starved host pauses the board)."""
        # imported here, not with the module: pymodbus.server imports aiohttp for its HTTP simulator (~0.5 s of CPU)
        from pymodbus.server import ModbusSerialServer

        ready = threading.Event()
        errors: list[BaseException] = []

        def serve():
            loop = asyncio.new_event_loop()
            asyncio.set_event_loop(loop)
            self._loop = loop

            async def main():
                try:
                    self._server = ModbusSerialServer(
                        ModbusServerContext(devices={wire.DRUM_DEVICE_ID: _MegaContext(self)}, single=False),
                        framer=FramerType.RTU, port=self.bridge.board_path, baudrate=wire.DRUM_BAUD, bytesize=8,
                        parity="N", stopbits=1, ignore_missing_devices=True, trace_pdu=self._trace_pdu,
                        trace_packet=self._trace_packet,
                        broadcast_enable=True,  # device id 0: writes executed, no reply (as the firmware)
                    )
                    self._server.decoder = _SpecDecoder(True)  # before serving: each connection's framer takes it
                    await self._server.serve_forever(background=True)
                except BaseException as exc:  # reported to start()
                    errors.append(exc)
                    ready.set()
                    return
                watchdog = asyncio.ensure_future(self._watchdog_loop())
                ready.set()
                try:
                    await self._server.serving
                finally:
                    watchdog.cancel()

            loop.run_until_complete(main())
            loop.close()

        self._server_thread = threading.Thread(target=board_thread(serve), name="virtual-mega-modbus", daemon=True)
        self._server_thread.start()
        ready.wait(5)
        if errors:
            raise RuntimeError(f"virtual Mega's Modbus server failed to start: {errors[0]}") from errors[0]
        if clock:  # a board of its own: on a clock shared with the host of this process (docs/architecture.md)
            self._stop.clear()
            self.clock = self.host_clock = SharedClock(lambda: self.model.time_s, world_notifies=True).start()
            self.clock.in_flight = self.answer_in_flight
            self.clock.own_port(self.path)
            self.use_clock(self.clock.now)
            # the board stands while a request or its reply is on its way, counted or in the kernel's hands, as a
            # SimulatedRig's world does (a reply the pty's kernel worker held past the host's answer timeout while
            # the board ran on: DrumTimeout, 'stale responses discarded', beside two CPU hogs)
            loop = WorldLoop(self.clock, lambda: int(round(self.model.time_s * 1000.0)), self.step,
                             tick_s=control_period_s,
                             board_busy=lambda: self.at_request() or self.request_on_its_way() or self.reply_on_its_way())
            self._clock_thread = threading.Thread(
                target=board_thread(loop.run), args=(self._stop,), name="virtual-mega-control",
                daemon=True)
            self._clock_thread.start()
        return self

    def close(self) -> None:
        """Stop the control loop and the server, close the ptys."""
        self._stop.set()
        if self._clock_thread is not None:
            self._clock_thread.join(timeout=2)
            self._clock_thread = None
        if self.clock is not None:
            self.clock.close()
            self.clock.release_ports()
        if self._server is not None and self._loop is not None:
            try:
                asyncio.run_coroutine_threadsafe(self._server.shutdown(), self._loop).result(timeout=3)
            except Exception:  # noqa: BLE001 - best effort at shutdown
                log.debug("server shutdown", exc_info=True)
        if self._server_thread is not None:
            self._server_thread.join(timeout=3)
            self._server_thread = None
        self.bridge.close()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.close()

    # ------------------------------------------------------------------ Modbus server and the watchdog
    def _trace_pdu(self, sending: bool, pdu):
        if not sending and pdu is not None and getattr(pdu, "dev_id", None) == wire.DRUM_DEVICE_ID:
            self._request_at = time.monotonic()  # answered (or refused) next: the board is at it (at_request)
            self.note_request()
        return pdu

    def _trace_packet(self, sending: bool, data: bytes) -> bytes:
        if sending:  # stamped before the server writes it: the bridge's take of it is later
            self._sent_at = time.monotonic()
        else:
            self._received_at = time.monotonic()
        return data

    async def _watchdog_loop(self) -> None:
        wait_s = WATCHDOG_CHECK_S
        while True:
            await asyncio.sleep(wait_s)
            try:
                self.check_watchdog()
                wait_s = self._next_check_s()
            except Exception:  # noqa: BLE001 - keep checking; the error is logged
                log.exception("watchdog check failed")
                wait_s = WATCHDOG_CHECK_S

    def _watchdog_due(self) -> bool:
        """The host has been silent for longer than WATCHDOG_MS on the board's clock (whether that is a fault, the rig
        at rest or not, is controller.c's to say)."""
        return self._host_heard and self._now() - self._last_request > self.holding_register(HR.WATCHDOG_MS) / 1000.0

    def _next_check_s(self) -> float:
        """The wait before the next :meth:`check_watchdog`, s: :data:`WATCHDOG_CHECK_S` from the time the host could
        be overdue (its last request + WATCHDOG_MS) on and while a check waits for its confirmation; until then no
        check can trip, and the loop sleeps up to that time, at most :data:`WATCHDOG_IDLE_CHECK_S` (the shortest
        WATCHDOG_MS: a request that shortens the timeout feeds the watchdog too, so the new deadline is never before
        the next check). Once the host is found silent, also that long: only a request makes it heard again. A check
        costs the server's loop a wake-up; one every 10 ms was most of its CPU."""
        with self._lock:
            if self._overdue_at_requests is not None:
                return WATCHDOG_CHECK_S
            if not self._host_heard:
                return WATCHDOG_IDLE_CHECK_S
            left_s = self._last_request + self.holding_register(HR.WATCHDOG_MS) / 1000.0 - self._now()
        return min(WATCHDOG_IDLE_CHECK_S, max(WATCHDOG_CHECK_S, left_s))

    def _reply_grace(self) -> bool:
        """Whether a reply on its way to the host restarts the watchdog's count now: only to a host whose port is
        plugged. A pulled cable (``host-silence``: the client's side unplugged) delivers nothing, so a reply the
        simulator held when the cable was pulled is on its way to nobody (issue 76: a ``host-silence`` cut held the
        drum at 100 mm/s and 300 g through the whole cut in 2 of 3 cuts, such a reply re-feeding the watchdog at
        every check)."""
        return self.bridge.client.plugged and self.reply_on_its_way()

    def check_watchdog(self) -> bool:
        """Tell the controller the host is silent (:meth:`host_link`; controller.c's watchdog then latches WATCHDOG if
        it guards the rig, spec 2.5) once the silence is longer than WATCHDOG_MS; returns True if it said so.

        Called from the Modbus server's loop (every :data:`WATCHDOG_CHECK_S` once the host may be overdue:
        :meth:`_next_check_s`), so a request the server has read is always handled (and has fed the watchdog) before
        the check. Not due while request bytes that the server has not read yet are on their way (the host spoke; the
        firmware would have handled them by now: :meth:`request_on_its_way`, also those in the kernel's hands), and
        restarted while a reply is still on its way to the host (:meth:`reply_on_its_way`: the host waits on the
        simulator, and the firmware's reply would have reached it by now). And it trips only when two checks in a row
        find the host overdue with nothing on the way and no request handled between them: the loop runs between two
        checks, so bytes the server had already taken from its port (a frame still being decoded or handled, which no
        count above sees) have fed the watchdog by the second (the firmware handles a frame within about a
        millisecond; this costs a silent host one check period, 10 ms, on top of WATCHDOG_MS).
        """
        with self._lock:
            overdue = self._watchdog_due()
        if overdue and self.request_on_its_way():
            overdue = False  # request bytes on their way (also those the kernel has yet to hand on)
        if overdue and self._reply_grace():  # a reply the simulator still holds: the host is waiting on it, and its
            with self._lock:  # silence starts once the reply is out (the firmware's goes out within ms)
                self._last_request = self._now()
            overdue = False
        with self._lock:
            if not (overdue and self._watchdog_due()):
                self._overdue_at_requests = None
                return False
            if self._overdue_at_requests != self.requests:  # the first check to find it overdue: confirm at the next
                self._overdue_at_requests = self.requests
                return False
            self._overdue_at_requests = None
            self.host_link(False)
            return True
