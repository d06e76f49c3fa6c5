"""Host side of the drum controller (Arduino Mega 2560): a Modbus RTU client in physical units (pymodbus).

Register map and semantics: ``docs/wire-protocol.md`` section 2 (numbers in :mod:`rigctl.devices.wire`). Every
setpoint is range-checked here, against the register's range column and the controller's current speed/force
limits, *before* anything is sent, so an out-of-range value never moves the rig. A Modbus exception response
becomes :class:`ModbusExceptionError` naming the register; no answer within ``timeout_s`` after ``retries`` retries
becomes :class:`DrumTimeout`. One lock serialises every use of the pymodbus sync client (pymodbus #1394).

Every response is matched to its request. Modbus RTU has no transaction id (pymodbus gives every RTU request id 0
and takes the first complete frame as the answer, pymodbus PR #2636), so a response that arrives after its request
timed out would be taken as the answer to the next one. Here a response must have the request's function code (or
its exception code), a read the requested number of registers, a function-6 write the echo of its address and
value, a function-16 write the echo of its address and count; anything else is discarded and counted
(:attr:`DrumClient.stale_responses`) and the request retried. After a timeout or a discarded response the link is
*unsettled*: before the next request the client sends a fence, a read of the input registers with a register count
no request still unanswered has, and discards everything that arrives before the fence's answer. A serial link
keeps the order of the bytes and the controller answers in order, so once the fence is answered no answer to an
earlier request can follow, and a later response of the right shape is the answer to the request just sent.
pymodbus is used with ``retries=0``: the retries are the client's own, so every retry goes through the fence. A port
that fails (a pulled USB cable) is closed and opened afresh by the next attempt, so the client works again once the
port is back; until then every request is a :class:`DrumError` naming the port.

The Mega's bootloader must never be kept from starting the sketch. Opening the port resets the board (the USB
bridge's DTR auto-reset); its stk500v2 bootloader then waits :data:`MEGA_BOOT_WINDOW_S` for a programmer, and a single
byte in that window keeps it in programming mode until no byte has come for :data:`MEGA_BOOT_TRAP_S` (stk500boot.c,
``recchar_timeout``): a host that sends at once and retries every 0.5 s keeps the board there for good. So after
every open (the first, and each reopen after a port failure) the client sends nothing for ``boot_wait_s``, and after
two attempts in a row got no answer (a board reset under a polling host, by power or brown-out, may have taken a
request for a programmer's byte) it stays silent for ``boot_quiet_s`` before the next one.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import stat
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

from pymodbus.client import ModbusSerialClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.framer import FramerRTU, FramerType
from pymodbus.pdu import ExceptionResponse

from rigctl.core import drum as core_drum
from rigctl.core.drum import DrumLimits, ForceLoopConfig, SettleBand
from rigctl.core.shared_clock import SharedClock, attach_port_clock, clock_of_port, is_port_clock, release_port_clock
from rigctl.devices import wire
from rigctl.devices.clocked_serial import ClockedSerialClient
from rigctl.devices.errors import (
    DrumContactTooStiff,
    DrumError,
    DrumFault,
    DrumHomeRefused,
    DrumNotHomed,
    DrumTimeout,
    DrumWaitAborted,
    ModbusExceptionError,
    SetpointRangeError,
)
from rigctl.devices.ports import PortIdentity, lock_exclusive
from rigctl.devices.wire import (
    Command,
    DrumState,
    Fault,
    HoldingRegister as HR,
    InputRegister as IR,
    ResetCause,
    SpeedProfile,
    StatusFlag,
)

__all__ = ["DrumClient", "DrumStatus", "DrumLimits", "SettleBand", "DrumState", "Fault", "ForceLoopConfig",
           "IndexSource", "SpeedProfile", "FORCE_LOOP_REGISTERS", "default_force_loop", "force_loop_registers",
           "force_loop_from_registers"]

log = logging.getLogger(__name__)


def _s16(v: int) -> int:
    return v - 0x10000 if v & 0x8000 else v


@dataclass(frozen=True)
class DrumStatus(core_drum.DrumStatus):
    """:class:`rigctl.core.drum.DrumStatus` (the controller's state in physical units), decoded from the input
    registers (spec table 2.2). New input registers: a field with a default in the core class, its decoding in
    :meth:`from_registers`."""

    @classmethod
    def from_registers(cls, regs: list[int]) -> "DrumStatus":
        """Decode the input registers 0 .. N_INPUT - 1 (signed ones per :data:`wire.SIGNED_INPUT_REGISTERS`).

        Raises :class:`DrumError` if there are not N_INPUT registers or STATE holds no known state."""
        if len(regs) != wire.N_INPUT:
            raise DrumError(f"drum status needs the {wire.N_INPUT} input registers, got {len(regs)}")
        try:
            DrumState(regs[IR.STATE])
        except ValueError:
            raise DrumError(f"drum controller reports an unknown state {regs[IR.STATE]}") from None
        raw = (regs[IR.LOADCELL_RAW_HI] << 16) | regs[IR.LOADCELL_RAW_LO]
        if raw & 0x80000000:
            raw -= 1 << 32
        fw = regs[IR.FIRMWARE_VERSION]
        return cls(
            force_g=float(_s16(regs[IR.FORCE_G])),
            speed_mm_s=_s16(regs[IR.SPEED_0P1MMS]) / 10.0,
            speed_target_mm_s=regs[IR.SPEED_TARGET_0P1MMS] / 10.0,
            angle_deg=regs[IR.DRUM_ANGLE_0P01DEG] / 100.0,
            revolutions=regs[IR.DRUM_REVOLUTIONS],
            actuator_mm=_s16(regs[IR.ACTUATOR_POSITION_0P01MM]) / 100.0,
            state=DrumState(regs[IR.STATE]),
            faults=Fault(regs[IR.FAULT_BITS] | (regs[IR.FAULT_BITS_HI] << 16)),
            firmware=(fw >> 8, fw & 0xFF),
            heartbeat=regs[IR.HEARTBEAT],
            loadcell_raw=raw,
            force_setpoint_active_g=float(regs[IR.FORCE_SETPOINT_ACTIVE_G]),
            hx711_rate_sps=regs[IR.HX711_RATE_0P01SPS] / 100.0,
            index_source=IndexSource.SENSOR if regs[IR.INDEX_SOURCE] == 1 else IndexSource.STEPS,
            index_period_s=regs[IR.INDEX_PERIOD_MS] / 1000.0,
            index_steps=regs[IR.INDEX_STEPS],
            index_count=regs[IR.INDEX_COUNT],
            mark_period_s=regs[IR.MARK_PERIOD_0P1MS] / 10000.0,
            mark_steps=regs[IR.MARK_STEPS],
            mark_count=regs[IR.MARK_COUNT],
            contact_stiffness_g_per_mm=regs[IR.CONTACT_STIFFNESS_G_PER_MM],
            stiffness_max_g_per_mm=regs[IR.STIFFNESS_MAX_G_PER_MM],
            reset_cause=ResetCause(regs[IR.RESET_CAUSE] & 0x0F),
            boot_count=regs[IR.BOOT_COUNT],
            flags=StatusFlag(regs[IR.STATUS_FLAGS] & 0x3F),
            build_id=wire.build_id_from_words([regs[r] for r in wire.BUILD_ID_REGISTERS]),
        )


class IndexSource:
    """Values of :attr:`DrumStatus.index_source` (the INDEX_SOURCE input register, spec 2.6)."""

    SENSOR = "sensor"
    STEPS = "steps"


#: the force loop's holding registers, in order (consecutive: one function-16 write)
FORCE_LOOP_REGISTERS = (HR.HX711_RATE_SPS, HR.FORCE_KP_80SPS_NMS_G, HR.FORCE_KI_80SPS_NMS_GS,
                        HR.FORCE_KP_10SPS_NMS_G, HR.FORCE_KI_10SPS_NMS_GS)
_NMS = 1e-6  # (nm/s) -> (mm/s)


def default_force_loop(hx711_rate_sps: int | None = None) -> ForceLoopConfig:
    """The controller's power-up force-loop settings (the registers' defaults, spec 2.1), with ``hx711_rate_sps``
    instead of the default rate if given."""
    d = [wire.HOLDING_RANGE[r][2] for r in FORCE_LOOP_REGISTERS]
    return ForceLoopConfig(int(hx711_rate_sps if hx711_rate_sps is not None else d[0]),
                           d[1] * _NMS, d[2] * _NMS, d[3] * _NMS, d[4] * _NMS)


def force_loop_registers(config: ForceLoopConfig) -> list[int]:
    """Raw values of :data:`FORCE_LOOP_REGISTERS`. Raises SetpointRangeError for a rate other than 10/80 or a gain
    outside its register's range (nothing is sent)."""
    if int(config.hx711_rate_sps) not in wire.HX711_RATES_SPS:
        raise SetpointRangeError("HX711 rate", float(config.hx711_rate_sps), "SPS", 10, 80)
    raw = [int(config.hx711_rate_sps)]
    gains = (("Kp at 80 SPS", config.kp_80sps_mm_s_per_g), ("Ki at 80 SPS", config.ki_80sps_mm_s_per_g_s),
             ("Kp at 10 SPS", config.kp_10sps_mm_s_per_g), ("Ki at 10 SPS", config.ki_10sps_mm_s_per_g_s))
    for (name, v), reg in zip(gains, FORCE_LOOP_REGISTERS[1:]):
        lo, hi, _ = wire.HOLDING_RANGE[reg]
        if not lo * _NMS <= float(v) <= hi * _NMS:
            raise SetpointRangeError(name, float(v), "(mm/s)/g", lo * _NMS, hi * _NMS)
        raw.append(int(round(float(v) / _NMS)))
    return raw


def force_loop_from_registers(regs: list[int]) -> ForceLoopConfig:
    """From the raw values of :data:`FORCE_LOOP_REGISTERS`."""
    return ForceLoopConfig(int(regs[0]), regs[1] * _NMS, regs[2] * _NMS, regs[3] * _NMS, regs[4] * _NMS)


@dataclass(frozen=True)
class _Expect:
    """The shape of the response a request must get (spec section 2): function code, register count of a read,
    echoed address and value (function 6) or address and count (function 16) of a write."""

    function_code: int
    count: int | None = None  #: registers a read returns; registers a function-16 write echoes
    address: int | None = None  #: echoed by writes
    value: int | None = None  #: echoed by a function-6 write

    def mismatch(self, response: Any) -> str | None:
        """None if ``response`` answers a request of this shape, else what is wrong with it. Fields a response does
        not carry (an in-process transport's responses) are not checked."""
        fc = getattr(response, "function_code", None)
        if fc is not None:
            fc = int(fc)
            if fc & 0x80:
                return None if fc & 0x7F == self.function_code else f"an exception response to function {fc & 0x7F}"
            if fc != self.function_code:
                return f"a response to function {fc}"
        elif isinstance(response, ExceptionResponse) or response.isError():
            return None
        regs = getattr(response, "registers", None)
        if self.function_code in (3, 4):
            if regs is None or len(regs) != self.count:
                return f"{len(regs or [])} registers instead of {self.count}"
            return None
        address = getattr(response, "address", None)
        if address is None or fc is None:
            return None
        if int(address) != self.address:
            return f"the echo of address {address} instead of {self.address}"
        if self.function_code == 6 and (not regs or int(regs[0]) != self.value):
            return f"the echo of value {regs[0] if regs else None} instead of {self.value}"
        if self.function_code == 16 and int(getattr(response, "count", -1)) != self.count:
            return f"the echo of {getattr(response, 'count', None)} registers instead of {self.count}"
        return None

    @property
    def is_write(self) -> bool:
        return self.function_code in (6, 16)


#: The Mega 2560's stk500v2 bootloader (Debian arduino-core-avr ``stk500boot_v2_mega2560.hex``, ``stk500boot.c``),
#: measured under simavr (``rigctl_simavr --bootloader``): it starts the sketch 0.83 s after a reset when no byte
#: comes, s ...
MEGA_BOOT_WINDOW_S = 0.83
#: ... and after a byte it stays in programming mode until no byte has come for 5.0 s (``recchar_timeout``: F_CPU / 2
#: polls of the UART), then starts the sketch, s
MEGA_BOOT_TRAP_S = 5.0
#: silence after opening a port that resets the board: the boot window with margin (a clone's clock, USB latency), s
MEGA_BOOT_WAIT_S = 1.5
#: silence after two unanswered attempts: longer than the programming-mode timeout, s
MEGA_BOOT_QUIET_S = 6.0


def resets_on_open(port: str) -> bool:
    """Whether opening ``port`` resets the board behind it (an Arduino's DTR auto-reset): True for a serial device
    (and for a path that cannot be checked), False for a pseudo-terminal, which has no DTR line (the virtual boards;
    Linux Unix98 pty slaves are character devices of majors 136-143, Documentation/admin-guide/devices.txt)."""
    try:
        st = os.stat(port)
    except OSError:
        return True
    return not (stat.S_ISCHR(st.st_mode) and 136 <= os.major(st.st_rdev) <= 143)


#: register counts of the fence (a read of the input registers from 0), one that no unanswered request has
_FENCE_COUNTS = tuple(range(2, wire.N_INPUT))


class _WallClock:
    """The host's clock: ``time.monotonic`` and ``time.sleep`` (s)."""

    @staticmethod
    def now() -> float:
        return time.monotonic()

    @staticmethod
    def sleep(s: float) -> None:
        time.sleep(s)


class DrumClient:
    """Client of the drum controller on a serial port (Modbus RTU, 8N1).

    Parameters
    ----------
    port : str
        Serial device (e.g. ``/dev/rigctl-drum``, ``/dev/ttyACM0`` or the simulated rig's ``drum_port``), or
        ``serial:<USB serial number>``. Reopens go to the board first opened, by its USB serial number
        (:class:`rigctl.devices.ports.PortIdentity`): re-enumerated boards cannot swap.
    baudrate : int
        :data:`rigctl.devices.wire.DRUM_BAUD` (500000, exact at 16 MHz) by default (spec section 2).
    device_id : int
        Modbus device id, 1.
    timeout_s : float
        Time to wait for each answer, s.
    retries : int
        Retries of a request that got no answer, before :class:`DrumTimeout`.
    poll_s : float
        Polling period of the ``wait_*`` methods, s.
    transport : object or None
        The Modbus master to use instead of a pymodbus serial client on ``port``: anything with pymodbus'
        ``connect()``, ``close()``, ``read_holding_registers``, ``read_input_registers``, ``write_register``,
        ``write_registers`` (keyword ``device_id``) returning responses with ``registers`` / ``isError()``. The
        in-process backend (:mod:`rigctl.simulation.inprocess`) passes one that calls the controller logic directly.
    clock : object or None
        ``now() -> s`` and ``sleep(s)`` used by the ``wait_*`` polls and the bootloader waits (default:
        ``time.monotonic`` / ``time.sleep``); the in-process backend passes its simulated clock, so a wait advances
        simulated time, not wall time. A simulated rig on ports passes its shared clock
        (:class:`rigctl.core.shared_clock.SharedClock`): then the answer timeout ``timeout_s`` is of that clock too
        (:mod:`rigctl.devices.clocked_serial`), and every request is a sign of the host's life.
    boot_wait_s : float or None
        Silence after every open of the port, s (module doc): None = :data:`MEGA_BOOT_WAIT_S` if opening the port
        resets the board (:func:`resets_on_open`: a serial device), 0 for a pseudo-terminal.
    boot_quiet_s : float or None
        Silence after two attempts in a row got no answer, s: None = :data:`MEGA_BOOT_QUIET_S` on a serial device,
        0 on a pseudo-terminal.
    watchdog_ms : int or None
        WATCHDOG_MS written at :meth:`open` (None: the controller's own, default 1000 ms). For a controller whose
        answers may take longer than the watchdog (the firmware under simavr on a loaded machine: one answer
        waited out for ``timeout_s`` = 2 s is 2 s of host silence), else a single late answer trips it.

    Attributes
    ----------
    stale_responses : int
        Responses discarded because they did not answer the request they arrived for (late answers to earlier
        requests, answers to fences already given up, frames in the input before a request was sent).
    timeouts : int
        Requests (fences included) that got no answer within ``timeout_s``.
    fences : int
        Fences sent to settle the link after a timeout or a discarded response.
    boot_waits : int
        Opens of the port waited out (``boot_wait_s``).
    quiet_periods : int
        Silences of ``boot_quiet_s`` kept after two unanswered attempts.

    Raises (all methods)
    --------------------
    SetpointRangeError
        A value outside its range (checked before sending).
    ModbusExceptionError
        The controller refused the request (names the register and the exception code).
    DrumTimeout
        No answer.
    DrumError
        The port cannot be opened or another I/O failure.
    """

    def __init__(self, port: str, *, baudrate: int = wire.DRUM_BAUD, device_id: int = wire.DRUM_DEVICE_ID,
                 timeout_s: float = 0.5, retries: int = 3, poll_s: float = 0.05, transport: Any = None,
                 clock: Any = None, boot_wait_s: float | None = None, boot_quiet_s: float | None = None,
                 watchdog_ms: int | None = None) -> None:
        self.port = port
        self.watchdog_ms = watchdog_ms
        self.device_id = device_id
        self.timeout_s = timeout_s
        self.retries = retries
        self.poll_s = poll_s
        self._wait_stops: dict[int, Callable[[], bool]] = {}  # thread id -> its stop (aborting_waits)
        self._lock = threading.RLock()
        # a simulated rig's port in this process is on that rig's clock (rigctl.core.shared_clock)
        self.clock = clock or (clock_of_port(port) if transport is None else None) or _WallClock()
        # a simulated rig of another process: this client holds its clock file while open (rigctl.core.shared_clock.attach_port_clock)
        self._holds_port_clock = clock is None and is_port_clock(self.clock)
        self.stale_responses = 0
        self.timeouts = 0
        self.fences = 0
        self.boot_waits = 0
        self.quiet_periods = 0
        #: called as ``fn(host_time_s, status)`` after every :meth:`read_status` (the midpoint of the request on
        #: :attr:`clock`), from the thread that read it: live consumers of the polls (the LSL drum stream)
        self.status_listeners: list[Any] = []
        resets = transport is None and resets_on_open(port)
        self.boot_wait_s = float(boot_wait_s) if boot_wait_s is not None else (MEGA_BOOT_WAIT_S if resets else 0.0)
        self.boot_quiet_s = float(boot_quiet_s) if boot_quiet_s is not None else (MEGA_BOOT_QUIET_S if resets
                                                                                   else 0.0)
        self._unanswered = 0  # attempts in a row that got no answer
        self._identity = PortIdentity(port)
        self._unsettled = False  # answers to earlier requests may still arrive: fence before the next request
        self._fence_used: list[int] = []  # fence counts sent since the link was last settled
        self._rx = b""  # the bytes of the last response pymodbus decoded (its trace_packet hook)
        # on a simulated rig the answer timeout is of the rig's shared clock (rigctl.devices.clocked_serial)
        serial_options: dict[str, Any] = {"clock": self.clock} if isinstance(self.clock, SharedClock) else {}
        self._client = transport if transport is not None else (
            ClockedSerialClient if serial_options else ModbusSerialClient)(
            port, framer=FramerType.RTU, baudrate=baudrate, bytesize=8, parity="N", stopbits=1,
            timeout=timeout_s, retries=0, reconnect_delay=0.1, reconnect_delay_max=1.0,
            trace_packet=self._trace_packet, **serial_options,
        )

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> "DrumClient":
        """Open the port and wait out the board's bootloader (``boot_wait_s``, module doc); write ``watchdog_ms`` if
        given. Raises :class:`DrumError` if it cannot be opened (or the controller does not take ``watchdog_ms``)."""
        with self._lock:
            if not self._holds_port_clock and is_port_clock(self.clock):  # reopened after close()
                self._holds_port_clock = attach_port_clock(self.port) is self.clock
            try:
                opened = self._connect()
            except OSError as exc:
                raise DrumError(f"cannot open the drum controller port {self.port}: {exc}") from exc
            if not opened:
                raise DrumError(f"cannot open the drum controller port {self.port}")
            if self.watchdog_ms is not None:
                self.write_holding(HR.WATCHDOG_MS, int(self.watchdog_ms))
        return self

    def _connect(self) -> bool:
        """Open the port if it is closed (exclusively: pymodbus opens with ``exclusive=True``); after an open, send
        nothing for ``boot_wait_s`` (the board resets and its bootloader listens), then drop what came meanwhile."""
        if getattr(self._client, "connected", False):
            return True
        if hasattr(self._client, "comm_params"):
            # the board by its USB serial number: whichever ttyACM it is now (ports.PortIdentity)
            self._client.comm_params.host = self._identity.device()
        if not self._client.connect():
            return False
        lock_exclusive(getattr(self._client, "socket", None))  # no other program can open (and so reset) the board now
        if self.boot_wait_s > 0:
            self.boot_waits += 1
            self._silence(self.boot_wait_s)
            sock = getattr(self._client, "socket", None)
            if sock is not None:
                self._note_taken()
                sock.reset_input_buffer()
        return True

    def _note_taken(self) -> None:
        """What waits on the port is about to be taken or dropped: a simulated board of this process is told
        (:meth:`rigctl.devices.clocked_serial.ClockedSerialClient.note_taken`; a real port: nothing)."""
        note = getattr(self._client, "note_taken", None)
        if note is not None:
            note()

    def _silence(self, seconds: float) -> None:
        """Send nothing for ``seconds`` of :attr:`clock` time."""
        t0 = self.clock.now()
        while (left := seconds - (self.clock.now() - t0)) > 0:
            self.clock.sleep(min(left, 0.05))

    def close(self) -> None:
        with self._lock:
            self._client.close()
            if self._holds_port_clock:
                self._holds_port_clock = False
                release_port_clock(self.clock)

    def __enter__(self) -> "DrumClient":
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ raw register access
    def _call(self, what: str, expect: _Expect, register: str, shown: Any = None, **kwargs: Any) -> Any:
        """Send one request (``what``: the pymodbus method) and return its matched response; see the module doc.

        Raises DrumTimeout (no matching answer after ``retries`` retries), ModbusExceptionError, DrumError."""
        with self._lock:
            result, sent = None, False
            for attempt in range(self.retries + 1):
                pending = expect if sent else None  # this request may have been carried out already
                try:
                    if self._on_link and not self._connect():  # reopen after a port failure: the board resets
                        raise OSError(f"cannot open {self.port}")
                    if self._unanswered >= 2 and self.boot_quiet_s > 0:  # a bootloader may hold our bytes: let it go
                        self.quiet_periods += 1
                        self._unanswered = 0
                        log.warning("drum controller on %s: no answer twice; %g s of silence for a bootloader to "
                                    "start the sketch", self.port, self.boot_quiet_s)
                        self._silence(self.boot_quiet_s)
                    echo = self._flush_input(pending)
                    if self._unsettled:
                        settled, fence_echo = self._fence(pending)
                        echo = fence_echo or echo
                        if not settled and echo is None:
                            continue  # the fence got no answer: this attempt is used up
                    if echo is not None:  # the write's own echo came late: it was carried out
                        result = echo
                        break
                    result = self._exchange(what, expect, kwargs)
                    sent = True
                except (ConnectionException, OSError) as exc:
                    # the port failed (vanished, unplugged): close it, so that the next attempt (or call) opens it
                    # afresh once it is back
                    self._client.close()
                    if attempt == self.retries:
                        raise DrumError(f"drum controller on {self.port}: {exc}") from exc
                    continue
                except ModbusException as exc:
                    raise DrumError(f"drum controller on {self.port}: {exc}") from exc
                if result is not None:
                    break
            if result is None:
                raise DrumTimeout(
                    f"no answer from the drum controller on {self.port} ({register}: {self.retries} retries of "
                    f"{self.timeout_s:g} s; {self.timeouts} timeouts, {self.stale_responses} stale responses "
                    "discarded so far): is the controller powered and on this port?")
        if isinstance(result, ExceptionResponse) or result.isError():
            code = getattr(result, "exception_code", 0)
            raise ModbusExceptionError(register, expect.function_code, int(code), shown)
        return result

    def _trace_packet(self, sending: bool, data: bytes) -> bytes:
        if not sending:
            self._rx = bytes(data)
        return data

    def _exchange(self, what: str, expect: _Expect, kwargs: Any) -> Any:
        """One request and its response: the response, or None (timeout, or a response that does not match; the
        link is then unsettled)."""
        self._rx = b""
        try:
            response = getattr(self._client, what)(device_id=self.device_id, **kwargs)
        except ModbusIOException:
            self.timeouts += 1
            self._unanswered += 1
            self._unsettled = self._on_link  # an answer may still come (not from an in-process transport)
            return None
        self._unanswered = 0
        frames = self._frames(self._rx, response)
        if not frames:
            if self._on_link:  # pymodbus' RTU decoder accepts a CRC match over a longer span than the function's
                # frame size ("garbage after frame"): with garbage inside an answer that is a wrong value, 1 in
                # ~4,000 corrupted answers; only frames of their exact size count
                self._discard([response], f"not an RTU frame of its size, in answer to function {expect.function_code}")
                self._unsettled = True
                return None
            frames = [response]  # a direct transport (no bytes)
        # on a settled link nothing but the answer to this request can arrive, and it arrives last
        if len(frames) > 1:
            self._discard(frames[:-1], f"before the answer to function {expect.function_code}")
        problem = expect.mismatch(frames[-1])
        if problem is None:
            return frames[-1]
        self._discard(frames[-1:], f"{problem}, in answer to function {expect.function_code}")
        self._unsettled = self._on_link
        return None

    def _discard(self, frames: list[Any], why: str) -> None:
        self.stale_responses += len(frames)
        log.warning("drum controller on %s: discarded %d stale response(s): %s", self.port, len(frames), why)

    @property
    def _on_link(self) -> bool:
        """Requests go over a serial link (pymodbus' RTU client), where an answer can come late."""
        return isinstance(getattr(self._client, "framer", None), FramerRTU)

    def _frames(self, data: bytes, decoded: Any = None) -> list[Any]:
        """The Modbus RTU responses (pymodbus PDUs) of this device in ``data``, in order; bytes that are not part of
        a valid frame are skipped. Empty for a transport without pymodbus' RTU framer. ``decoded``: what pymodbus
        decoded from ``data``, taken as is when ``data`` is that one frame (its registers are not decoded twice)."""
        if not self._on_link or not data:
            return []
        decoder = self._client.framer.decoder
        out, p, n = [], 0, len(data)
        while p + FramerRTU.MIN_SIZE <= n:
            size = 0
            if data[p] == self.device_id:
                try:
                    pdu_class = decoder.lookupPduClass(data[p:])
                    size = pdu_class.calculateRtuFrameSize(data[p:]) if pdu_class else 0
                except Exception:  # noqa: BLE001 - no frame starts here
                    size = 0
            if size and p + size <= n and FramerRTU.check_CRC(
                    data[p:p + size - 2], int.from_bytes(data[p + size - 2:p + size], "big")):
                whole = decoded is not None and size == n  # the one frame of data: pymodbus decoded these bytes
                pdu = decoded if whole else decoder.decode(data[p + 1:p + size - 2])
                if pdu is not None:
                    pdu.dev_id = data[p]
                    out.append(pdu)
                    p += size
                    continue
            p += 1
        return out

    def _flush_input(self, pending: _Expect | None) -> Any:
        """Discard what waits in the input before a request is sent (responses in it are counted, and unsettle the
        link). Returns the echo of the write ``pending`` if it is there (it was carried out), else None."""
        sock = getattr(self._client, "socket", None)
        waiting = sock.in_waiting if sock is not None else 0
        if not waiting:
            return None
        self._note_taken()
        frames = self._frames(sock.read(waiting))  # type: ignore[union-attr]  # waiting > 0: a socket
        _, echo = self._sort_out(frames, pending)
        return echo

    def _sort_out(self, frames: list[Any], pending: _Expect | None,
                  fence: _Expect | None = None) -> tuple[bool, Any]:
        """Responses that arrived unasked: ``(fence answered, echo)``. The fence's answer settles the link (frames
        after it are discarded); the echo of the write ``pending`` means it was carried out; every other frame is
        discarded and counted, and unsettles the link."""
        echo = None
        for i, pdu in enumerate(frames):
            if isinstance(pdu, ExceptionResponse):
                pass
            elif fence is not None and fence.mismatch(pdu) is None:
                if i + 1 < len(frames):
                    self._discard(frames[i + 1:], "after the fence's answer")
                return True, echo
            elif pending is not None and pending.is_write and pending.mismatch(pdu) is None:
                echo = pdu
                continue
            self._discard([pdu], "a late answer to an earlier request")
            self._unsettled = True
        return False, echo

    def _fence(self, pending: _Expect | None) -> tuple[bool, Any]:
        """Settle the link: read ``k`` input registers from 0 (``k`` a count no unanswered fence or request has)
        and discard every response before the answer. Returns ``(settled, echo)``: whether the answer came within
        ``timeout_s``, and the echo of the write ``pending`` if it arrived meanwhile."""
        if not self._on_link:  # a direct transport answers each request before returning: nothing comes late
            self._unsettled = False
            self._fence_used.clear()
            return True, None
        self.fences += 1
        busy = set(self._fence_used) | ({pending.count} if pending is not None and pending.function_code == 4
                                        else set())
        count = next((c for c in _FENCE_COUNTS if c not in busy), None)
        if count is None:  # every count is taken by a fence nobody answered: reuse the oldest
            count = self._fence_used.pop(0)
        self._fence_used.append(count)
        fence = _Expect(4, count=count)
        self._rx = b""
        try:
            self._client.read_input_registers(0, count=count, device_id=self.device_id)
        except ModbusIOException:
            self.timeouts += 1
            self._unanswered += 1
            return False, None
        frames = self._frames(self._rx)
        echo = None
        deadline = self.clock.now() + self.timeout_s
        while True:
            settled, got = self._sort_out(frames, pending, fence)
            echo = got or echo
            if settled:
                self._unsettled = False
                self._fence_used.clear()
                self._unanswered = 0
                return True, echo
            if self.clock.now() >= deadline:
                self.timeouts += 1
                self._unanswered += 1
                return False, echo
            frames = self._frames(self._client.recv(None))

    @staticmethod
    def _name(table: Any, address: int) -> str:
        try:
            return str(table(address).name)
        except ValueError:
            return f"{'holding' if table is HR else 'input'} register {address}"

    def read_holdings(self, start: int, count: int) -> list[int]:
        """Read ``count`` holding registers from ``start`` (function 03); raw uint16 values."""
        res = self._call("read_holding_registers", _Expect(3, count=int(count)), self._name(HR, start),
                         address=int(start), count=int(count))
        return list(res.registers)

    def read_holding(self, reg: HR | int) -> int:
        """Read one holding register (raw uint16 in the register's unit, e.g. 0.1 mm/s)."""
        return self.read_holdings(int(reg), 1)[0]

    def read_inputs(self, start: int, count: int) -> list[int]:
        """Read ``count`` input registers from ``start`` (function 04); raw uint16 values."""
        res = self._call("read_input_registers", _Expect(4, count=int(count)), self._name(IR, start),
                         address=int(start), count=int(count))
        return list(res.registers)

    def read_input(self, reg: IR | int) -> int:
        """Read one input register (raw uint16; see :meth:`read_status` for decoded values)."""
        return self.read_inputs(int(reg), 1)[0]

    def _check_raw(self, reg: HR, value: int) -> None:
        low, high, _ = wire.HOLDING_RANGE[reg]
        if not isinstance(value, int) or not low <= value <= high:
            raise SetpointRangeError(reg.name, float(value), "(register units)", low, high)

    def write_holding(self, reg: HR | int, value: int) -> None:
        """Write one holding register (function 06) after checking the value against its range column.

        Raises :class:`SetpointRangeError` (nothing sent) or :class:`ModbusExceptionError`.
        """
        try:
            reg = HR(int(reg))
        except ValueError:
            reg = int(reg)  # unknown address: let the controller answer (exception 02)
        else:
            self._check_raw(reg, value)
        self._call("write_register", _Expect(6, address=int(reg), value=int(value)), self._name(HR, int(reg)), value,
                   address=int(reg), value=int(value))

    def write_holdings(self, start: HR | int, values: list[int]) -> None:
        """Write consecutive holding registers in one request (function 16), each range-checked first."""
        for i, v in enumerate(values):
            try:
                reg = HR(int(start) + i)
            except ValueError:
                continue  # unknown address: the controller answers exception 02
            self._check_raw(reg, v)
        self._call("write_registers", _Expect(16, count=len(values), address=int(start)), self._name(HR, int(start)),
                   list(values), address=int(start), values=list(values))

    # ------------------------------------------------------------------ setpoints in physical units
    def limits(self) -> DrumLimits:
        """The controller's current hard limits (SPEED_LIMIT_0P1MMS, FORCE_LIMIT_G): mm/s, g."""
        regs = self.read_holdings(HR.SPEED_LIMIT_0P1MMS, 2)
        return DrumLimits(speed_mm_s=regs[0] / 10.0, force_g=float(regs[1]))

    def settle_band(self) -> SettleBand:
        """When the force loop counts as on target (FORCE_TOLERANCE_G, SETTLE_TIME_MS): g, ms."""
        regs = self.read_holdings(HR.FORCE_TOLERANCE_G, 2)
        return SettleBand(force_tolerance_g=float(regs[0]), settle_time_ms=int(regs[1]))

    def set_settle_band(self, *, force_tolerance_g: float | None = None, settle_time_ms: int | None = None) -> None:
        """Set the settle band: force tolerance, g (1-500), and/or time on target, ms (0-10000). None keeps one.

        Raises :class:`SetpointRangeError` (nothing sent)."""
        for reg, value in ((HR.FORCE_TOLERANCE_G, force_tolerance_g), (HR.SETTLE_TIME_MS, settle_time_ms)):
            if value is not None:
                lo, hi, _ = wire.HOLDING_RANGE[reg]
                if not lo <= float(value) <= hi:
                    raise SetpointRangeError(reg.name, float(value), "g" if reg == HR.FORCE_TOLERANCE_G else "ms",
                                             lo, hi)
        if force_tolerance_g is not None:
            self.write_holding(HR.FORCE_TOLERANCE_G, int(round(force_tolerance_g)))
        if settle_time_ms is not None:
            self.write_holding(HR.SETTLE_TIME_MS, int(settle_time_ms))

    def settings(self) -> dict[str, int]:
        """Every holding register but COMMAND by name, raw (the controller's settings, recorded in a session's
        ``rig_config``)."""
        regs = self.read_holdings(0, wire.N_HOLDING)
        return {r.name: int(regs[int(r)]) for r in HR if r != HR.COMMAND}

    def _speed_raw(self, name: str, mm_s: float, limit_mm_s: float) -> int:
        hi = min(wire.HOLDING_RANGE[HR.SPEED_SETPOINT_0P1MMS][1] / 10.0, limit_mm_s)
        if not (0.0 <= mm_s <= hi):
            raise SetpointRangeError(name, mm_s, "mm/s", 0.0, hi, "SPEED_LIMIT_0P1MMS" if hi == limit_mm_s else "")
        return int(round(mm_s * 10))

    def set_speed(self, mm_s: float) -> None:
        """Drum surface speed for the CONSTANT profile, mm/s (0 - the controller's speed limit)."""
        raw = self._speed_raw("speed", float(mm_s), self.limits().speed_mm_s)
        self.write_holding(HR.SPEED_SETPOINT_0P1MMS, raw)

    def set_force(self, g: float) -> None:
        """Contact-force setpoint, g (0 - the controller's force limit)."""
        limit = self.limits().force_g
        hi = min(float(wire.HOLDING_RANGE[HR.FORCE_SETPOINT_G][1]), limit)
        if not (0.0 <= float(g) <= hi):
            raise SetpointRangeError("force", float(g), "g", 0.0, hi, "FORCE_LIMIT_G" if hi == limit else "")
        self.write_holding(HR.FORCE_SETPOINT_G, int(round(g)))

    def set_ramp(self, start_mm_s: float, end_mm_s: float, duration_s: float) -> None:
        """RAMP profile: linear from ``start_mm_s`` to ``end_mm_s`` over ``duration_s`` (0.001-60 s), then held.

        The three registers are written in one function-16 request (all or nothing). Does not select the profile:
        call ``set_profile(SpeedProfile.RAMP)``.
        """
        limit = self.limits().speed_mm_s
        a = self._speed_raw("ramp start speed", float(start_mm_s), limit)
        b = self._speed_raw("ramp end speed", float(end_mm_s), limit)
        lo, hi, _ = wire.HOLDING_RANGE[HR.RAMP_DURATION_MS]
        if not (lo / 1000.0 <= float(duration_s) <= hi / 1000.0):
            raise SetpointRangeError("ramp duration", float(duration_s), "s", lo / 1000.0, hi / 1000.0)
        self.write_holdings(HR.RAMP_START_SPEED_0P1MMS, [a, b, int(round(duration_s * 1000))])

    def set_profile(self, profile: SpeedProfile | int) -> None:
        """Select the speed profile: :class:`SpeedProfile` CONSTANT or RAMP."""
        try:
            profile = SpeedProfile(int(profile))
        except ValueError:
            raise SetpointRangeError("speed profile", float(profile), "(code)", 0, len(SpeedProfile) - 1) from None
        self.write_holding(HR.SPEED_PROFILE, int(profile))

    def set_limits(self, speed_mm_s: float | None = None, force_g: float | None = None) -> None:
        """Set the speed limit (mm/s, 0-200) and/or the force limit (g, 0-2000)."""
        if speed_mm_s is not None:
            lo, hi, _ = wire.HOLDING_RANGE[HR.SPEED_LIMIT_0P1MMS]
            if not lo / 10 <= float(speed_mm_s) <= hi / 10:
                raise SetpointRangeError("speed limit", float(speed_mm_s), "mm/s", lo / 10, hi / 10)
        if force_g is not None:
            lo, hi, _ = wire.HOLDING_RANGE[HR.FORCE_LIMIT_G]
            if not lo <= float(force_g) <= hi:
                raise SetpointRangeError("force limit", float(force_g), "g", lo, hi)
        if speed_mm_s is not None:
            self.write_holding(HR.SPEED_LIMIT_0P1MMS, int(round(speed_mm_s * 10)))
        if force_g is not None:
            self.write_holding(HR.FORCE_LIMIT_G, int(round(force_g)))

    def set_loadcell_scale(self, counts_per_g: float) -> None:
        """Load-cell calibration, HX711 counts per g, signed (absolute value 1-100,000; negative for a cell that
        reads negative under load), written as the 32-bit pair LOADCELL_SCALE_X100_HI/_LO in one request (spec
        2.1); SAVE_CALIBRATION keeps it in EEPROM."""
        lo, hi = wire.LOADCELL_SCALE_X100_ABS_RANGE
        v = float(counts_per_g)
        if not (math.isfinite(v) and lo / 100 <= abs(v) <= hi / 100):
            raise SetpointRangeError("load-cell scale (absolute value)", abs(v) if math.isfinite(v) else v,
                                     "counts/g", lo / 100, hi / 100)
        self.write_holdings(HR.LOADCELL_SCALE_X100_HI, list(wire.split_s32(int(round(v * 100)))))

    def loadcell_scale(self) -> float:
        """The controller's load-cell scale, HX711 counts per g (signed)."""
        return wire.join_s32(*self.read_holdings(HR.LOADCELL_SCALE_X100_HI, 2)) / 100.0

    def calibration_stiffness(self) -> int:
        """The contact's stiffness stored with the calibration, g/mm (CALIBRATION_STIFFNESS_G_PER_MM; 0: none)."""
        return self.read_holding(HR.CALIBRATION_STIFFNESS_G_PER_MM)

    def set_calibration_stiffness(self, g_per_mm: float) -> None:
        """Write CALIBRATION_STIFFNESS_G_PER_MM (g/mm, 0-5000; 0: none, no check; spec 2.12); SAVE_CALIBRATION
        keeps it in EEPROM. SetpointRangeError outside its range."""
        lo, hi, _ = wire.holding_range(HR.CALIBRATION_STIFFNESS_G_PER_MM)
        v = float(g_per_mm)
        if not (math.isfinite(v) and lo <= v <= hi):
            raise SetpointRangeError("contact stiffness stored with the calibration", v, "g/mm", lo, hi)
        self.write_holding(HR.CALIBRATION_STIFFNESS_G_PER_MM, int(round(v)))

    def force_loop(self) -> ForceLoopConfig:
        """The force loop's rate and gains (holding registers 20-24, spec 2.9)."""
        return force_loop_from_registers(self.read_holdings(HR.HX711_RATE_SPS, len(FORCE_LOOP_REGISTERS)))

    def set_force_loop(self, config: ForceLoopConfig) -> None:
        """Write the force loop's rate and gains in one function-16 request (range-checked first: SetpointRangeError;
        a rate the HX711 does not have latches HX711_RATE on the controller)."""
        self.write_holdings(HR.HX711_RATE_SPS, force_loop_registers(config))

    def set_hx711_rate(self, sps: int) -> None:
        """Tell the controller the HX711's rate (10 or 80 SPS): the loop then runs with that rate's gains, and a
        latched HX711_RATE can be cleared once it matches the measured rate."""
        if int(sps) not in wire.HX711_RATES_SPS:
            raise SetpointRangeError("HX711 rate", float(sps), "SPS", 10, 80)
        self.write_holding(HR.HX711_RATE_SPS, int(sps))

    # ------------------------------------------------------------------ commands
    def command(self, cmd: Command) -> None:
        """Write a command code to COMMAND (spec table 2.3)."""
        self.write_holding(HR.COMMAND, int(Command(cmd)))

    def _motion_command(self, cmd: Command) -> None:
        """RUN / PRESS: a refusal from a NOT_HOMED controller says so (:class:`DrumNotHomed`), one for a contact
        stiffer than the force loop holds too (:class:`DrumContactTooStiff`, spec 2.10)."""
        try:
            self.command(cmd)
        except ModbusExceptionError as exc:
            st = self.read_status() if exc.exception_code == 3 else None
            if st is not None and st.state == DrumState.NOT_HOMED:
                raise DrumNotHomed(exc.register, exc.function_code, exc.exception_code, exc.value) from None
            if st is not None and st.stiffness_max_g_per_mm and \
                    st.contact_stiffness_g_per_mm > st.stiffness_max_g_per_mm:
                raise DrumContactTooStiff(exc.register, exc.function_code, exc.exception_code, exc.value,
                                          st.contact_stiffness_g_per_mm, st.stiffness_max_g_per_mm) from None
            raise

    def run(self) -> None:
        """Start the drum on the selected profile (engages the force loop first if needed). DrumNotHomed if the
        controller has not been homed since its last reset."""
        self._motion_command(Command.RUN)

    def stop(self) -> None:
        """Safe stop: drum to rest, actuator home, state IDLE."""
        self.command(Command.STOP)

    def stop_drum(self) -> None:
        """Drum to rest, keep holding the force."""
        self.command(Command.STOP_DRUM)

    def press(self) -> None:
        """Engage the force loop (SEEKING_FORCE, then FORCE_SETTLED). DrumNotHomed if the controller has not been
        homed since its last reset."""
        self._motion_command(Command.PRESS)

    def tare(self) -> None:
        """Zero the load cell (actuator released)."""
        self.command(Command.TARE)

    def home(self) -> None:
        """Drive the actuator to its home switch (HOMING, then IDLE). DrumHomeRefused: refused (exception 03), with
        why from the state the controller refused it in (:class:`rigctl.devices.errors.DrumHomeRefused`)."""
        try:
            self.command(Command.HOME)
        except ModbusExceptionError as exc:
            if exc.exception_code != 3:
                raise
            state = int(self.read_status().state)
            raise DrumHomeRefused(exc.register, exc.function_code, exc.exception_code, exc.value, state) from None

    def clear_fault(self) -> None:
        """Clear latched faults and leave FAULT for IDLE."""
        self.command(Command.CLEAR_FAULT)

    def save_calibration(self) -> None:
        """Write the calibration registers to EEPROM."""
        self.command(Command.SAVE_CALIBRATION)

    # ------------------------------------------------------------------ status and waits
    def _read_status(self) -> DrumStatus:
        try:
            regs = self.read_inputs(0, wire.N_INPUT)
        except ModbusExceptionError as exc:
            if exc.exception_code != 2:
                raise
            raise DrumError(f"the drum controller on {self.port} has fewer than the {wire.N_INPUT} input registers of "
                            "docs/wire-protocol.md 2.2 (exception 02): its firmware is older than the installed "
                            "sources; flash them: rigctl firmware --flash PORT --board mega") from exc
        return DrumStatus.from_registers(regs)

    def read_status(self) -> DrumStatus:
        """All input registers in one request, decoded (signed registers as two's complement); passed on to
        :attr:`status_listeners`. DrumError naming the flash command when the controller has fewer input registers
        than the spec (exception 02: firmware built before registers this rigctl reads, e.g. BUILD_ID_0 .. _2)."""
        if not self.status_listeners:
            return self._read_status()
        t0 = self.clock.now()
        status = self._read_status()
        t = 0.5 * (t0 + self.clock.now())
        for fn in list(self.status_listeners):
            fn(t, status)
        return status

    @contextlib.contextmanager
    def aborting_waits(self, stop: Callable[[], bool]) -> Iterator[None]:
        """Within the block, every wait of this client in the calling thread (``wait_state``, ``wait_released``,
        ``wait_force_settled``, ``wait_speed_steady``, ...) ends with :class:`DrumWaitAborted` at its next poll once
        ``stop()`` is true, instead of at its timeout: a STOP leaves the controller where the awaited state may never
        come (HOME stopped: NOT_HOMED, never IDLE; the drum stopped: never at speed), and on a simulated rig a wait
        run out also runs the world's clock out with it. Other threads' waits are untouched (STOP's own wait for the
        release among them). Nests (the inner stop applies within the inner block)."""
        key = threading.get_ident()
        outer = self._wait_stops.get(key)
        self._wait_stops[key] = stop
        try:
            yield
        finally:
            if outer is None:
                self._wait_stops.pop(key, None)
            else:
                self._wait_stops[key] = outer

    def _wait(self, done: Any, timeout_s: float, what: str, allow_fault: bool = False) -> DrumStatus:
        clock = self.clock
        deadline = clock.now() + timeout_s
        stop = self._wait_stops.get(threading.get_ident())
        status = None
        while True:
            status = self.read_status()
            if status.state == DrumState.FAULT and not allow_fault:
                raise DrumFault(status.faults, f"while waiting for {what}")
            if done(status):
                return status
            if stop is not None and stop():
                raise DrumWaitAborted(f"stopped while waiting for {what} (state {status.state.name})")
            if clock.now() >= deadline:
                raise DrumTimeout(
                    f"drum controller did not reach {what} within {timeout_s:g} s (state {status.state.name}, "
                    f"force {status.force_g:g} g, speed {status.speed_mm_s:g} mm/s)")
            clock.sleep(self.poll_s)

    def wait_state(self, states: Any, timeout_s: float) -> DrumStatus:
        """Poll until the state is one of ``states``; returns the status. DrumFault on a fault (unless FAULT is
        awaited), DrumTimeout on timeout."""
        states = {DrumState(s) for s in ([states] if isinstance(states, (int, DrumState)) else states)}
        names = "/".join(sorted(s.name for s in states))
        return self._wait(lambda s: s.state in states, timeout_s, f"state {names}", DrumState.FAULT in states)

    def wait_homed(self, timeout_s: float) -> DrumStatus:
        """Poll until the HOME just sent has ended: IDLE, homed (the status returned). A HOME that ends without
        homing, the controller back at NOT_HOMED after HOMING (a STOP stops it there, from any face), raises
        :class:`DrumWaitAborted` at once, where a wait for IDLE ran its whole timeout out. DrumFault (HOME_NOT_FOUND
        and the rest) and DrumTimeout as every wait."""
        seen_homing = False

        def homed(s: DrumStatus) -> bool:
            nonlocal seen_homing
            seen_homing = seen_homing or s.state == DrumState.HOMING
            if seen_homing and s.state == DrumState.NOT_HOMED:
                raise DrumWaitAborted("HOME stopped before it homed (the controller is NOT_HOMED again)")
            return s.state == DrumState.IDLE

        return self._wait(homed, timeout_s, "state IDLE (homed)")

    def wait_hx711_rate(self, timeout_s: float) -> DrumStatus:
        """Poll until the controller has timed its HX711's output rate at boot (``hx711_rate_sps`` > 0: 6 DOUT-ready
        edges, 75 ms at 80 SPS, 0.6 s at 10 SPS; docs/wire-protocol.md 2.9); until then it refuses PRESS and RUN.
        A fault ends the wait too (e.g. HX711_RATE: the rate measured is not the one configured): the status returned
        says which. DrumTimeout if neither happens within ``timeout_s``."""
        return self._wait(lambda s: bool(s.hx711_rate_sps) or s.state == DrumState.FAULT, timeout_s,
                          "the HX711 rate timed at boot", allow_fault=True)

    def wait_released(self, timeout_s: float, home_mm: float = 0.05) -> DrumStatus:
        """Poll until IDLE with the actuator within ``home_mm`` of home, or its home switch closed (after STOP: the
        sensor is free; a back-off ends at the switch, where a step count that lost steps may still read more).
        DrumFault / DrumTimeout."""
        return self._wait(lambda s: s.state == DrumState.IDLE and (s.actuator_mm <= home_mm or s.home_switch), timeout_s,
                          f"IDLE with the actuator home (within {home_mm:g} mm)")

    def wait_force_settled(self, timeout_s: float) -> DrumStatus:
        """Poll until the force loop is on target: state FORCE_SETTLED (or RUNNING with the force within
        FORCE_TOLERANCE_G of the setpoint). DrumFault / DrumTimeout."""
        tol = self.settle_band().force_tolerance_g

        def done(s: DrumStatus) -> bool:
            return s.state == DrumState.FORCE_SETTLED or (
                s.state == DrumState.RUNNING and abs(s.force_g - s.force_setpoint_active_g) <= tol)

        return self._wait(done, timeout_s, "a settled force")

    def wait_speed_steady(self, timeout_s: float, tol_mm_s: float = 0.5, n_polls: int = 3) -> DrumStatus:
        """Poll until the drum speed is within ``tol_mm_s`` of the profile's target for ``n_polls`` polls in a row
        with the target unchanged. DrumFault / DrumTimeout."""
        state: dict[str, Any] = {"n": 0, "target": None}

        def done(s: DrumStatus) -> bool:
            ok = abs(s.speed_mm_s - s.speed_target_mm_s) <= tol_mm_s and s.speed_target_mm_s == state["target"]
            state["n"] = state["n"] + 1 if ok else 0
            state["target"] = s.speed_target_mm_s
            return state["n"] >= n_polls - 1 and ok

        return self._wait(done, timeout_s, f"a steady speed (+-{tol_mm_s:g} mm/s)")
