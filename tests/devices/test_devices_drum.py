"""DrumClient against VirtualMega over real ptys and the real pymodbus client/server stacks: what the client adds
(decoding, named errors, ranges checked before sending, timeouts) and what only the simulator has (its threads
starved, its EEPROM file). The controller's own behaviour is the conformance suite (tests/conformance/), run
against both the virtual Mega and the firmware."""

from __future__ import annotations

import json
import threading
import time

import pytest

from rigctl.devices import wire
from rigctl.devices.drum import DrumClient, DrumStatus
from rigctl.devices.errors import DrumFault, DrumNotHomed, DrumTimeout, ModbusExceptionError, SetpointRangeError
from rigctl.devices.wire import DrumState, Fault, HoldingRegister as HR, InputRegister as IR
from rigctl.simulation.model import RigModel
from rigctl.simulation.virtual_mega import VirtualMega

from .conftest import home


# wall: the HEARTBEAT register's count judged against time.monotonic around two reads
@pytest.mark.realtime
def test_every_input_register_read(drum, mega):
    # HOME ends (IDLE) at the tare's reading and the drivers drop at the controller's next 1 ms tick: a read between the
    # two saw DRIVERS_ENABLED on a loaded CI run; at rest is after that tick
    end = time.monotonic() + 1.0
    while drum.read_input(IR.STATUS_FLAGS) & wire.StatusFlag.DRIVERS_ENABLED and time.monotonic() < end:
        time.sleep(0.01)
    regs = drum.read_inputs(0, wire.N_INPUT)
    assert [drum.read_input(reg) for reg in wire.RESERVED_INPUT] == [0] * len(wire.RESERVED_INPUT)
    assert regs[IR.FIRMWARE_VERSION] == 265  # 1.9
    assert regs[IR.STATE] == DrumState.IDLE  # homed by the fixture
    assert regs[IR.RESET_CAUSE] == wire.ResetCause.POWER_ON and regs[IR.BOOT_COUNT] == 0  # first boot of its EEPROM
    # homed and tared; the fixture's board is calibrated (a default calibration refuses PRESS, spec 2.11)
    assert regs[IR.STATUS_FLAGS] == wire.StatusFlag.HOMED | wire.StatusFlag.TARED | wire.StatusFlag.HOME_SWITCH
    assert regs[IR.FAULT_BITS] == 0
    assert regs[IR.FORCE_SETPOINT_ACTIVE_G] == 0
    assert 0 <= regs[IR.DRUM_ANGLE_0P01DEG] < 36000
    status = drum.read_status()
    raw = mega.model.loadcell_raw
    assert abs(status.loadcell_raw - raw) < 50 * 420  # same reading, within 50 g of noise between the two reads
    assert status.firmware == wire.MEGA_FIRMWARE_VERSION
    # the drum has not turned since power-up: no index-sensor edge yet, the angle is the step count's (0)
    assert (status.index_source, status.angle_deg, status.index_count) == ("steps", 0.0, 0)
    assert status.hx711_rate_sps == pytest.approx(80.0, abs=0.5)  # timed at boot from the DOUT-ready edges
    # +1 per 10 ms of the board's clock: each read samples the counter somewhere between its request and its reply,
    # so the count between two reads is bounded by the times around them (a loaded host may stretch the 0.3 s wait);
    # the virtual board's clock moves in its physics thread's steps, which a loaded host may hold back a few ticks
    t0_sent = time.monotonic()
    hb0 = drum.read_input(IR.HEARTBEAT)
    t0_back = time.monotonic()
    time.sleep(0.3)
    t1_sent = time.monotonic()
    hb1 = drum.read_input(IR.HEARTBEAT)
    t1_back = time.monotonic()
    ticks = (hb1 - hb0) % 65536
    assert (t1_sent - t0_back) / 0.010 - 5 <= ticks <= (t1_back - t0_sent) / 0.010 + 1, (ticks, t1_back - t0_sent)


def test_status_decodes_signed_registers():
    regs = [0] * wire.N_INPUT
    regs[IR.FORCE_G] = 0xFFF6  # -10 g
    regs[IR.SPEED_0P1MMS] = 0xFC18  # -100.0 mm/s
    regs[IR.ACTUATOR_POSITION_0P01MM] = 0xFF9C  # -1.00 mm
    regs[IR.LOADCELL_RAW_HI], regs[IR.LOADCELL_RAW_LO] = 0xFFFF, 0xFFFE  # -2
    regs[IR.FIRMWARE_VERSION] = 0x0102
    regs[IR.FAULT_BITS] = 0b0011
    regs[IR.RESET_CAUSE] = 0b1000
    regs[IR.BOOT_COUNT] = 65535
    regs[IR.STATUS_FLAGS] = 0b001011
    s = DrumStatus.from_registers(regs)
    assert (s.force_g, s.speed_mm_s, s.actuator_mm, s.loadcell_raw) == (-10, -100.0, -1.0, -2)
    assert s.firmware == (1, 2)
    assert s.faults == Fault.FORCE_LIMIT | Fault.WATCHDOG
    assert (s.reset_cause, s.boot_count) == (wire.ResetCause.WATCHDOG, 65535)
    assert s.calibration_defaults and s.homed and s.estop_open and not s.drivers_enabled


def test_out_of_range_setpoints_refused_before_anything_is_sent(drum, mega):
    drum.set_limits(speed_mm_s=100, force_g=800)
    writes = mega.write_requests
    cases = [
        (lambda: drum.set_speed(120), "speed", "mm/s", 100),  # above the controller's current limit
        (lambda: drum.set_speed(-1), "speed", "mm/s", 100),
        (lambda: drum.set_force(1000), "force", "g", 800),
        (lambda: drum.set_ramp(40, 150, 2.0), "ramp end speed", "mm/s", 100),
        (lambda: drum.set_ramp(40, 80, 0.0), "ramp duration", "s", 60),
        (lambda: drum.set_ramp(40, 80, 61.0), "ramp duration", "s", 60),
        (lambda: drum.set_limits(speed_mm_s=250), "speed limit", "mm/s", 200),
        (lambda: drum.set_limits(force_g=2500), "force limit", "g", 2000),
        (lambda: drum.set_loadcell_scale(0.001), "load-cell scale (absolute value)", "counts/g", 100000),
        (lambda: drum.set_loadcell_scale(-100001), "load-cell scale (absolute value)", "counts/g", 100000),
        (lambda: drum.set_profile(5), "speed profile", "(code)", 1),
        (lambda: drum.write_holding(HR.WATCHDOG_MS, 50), "WATCHDOG_MS", "(register units)", 10000),
    ]
    for call, name, unit, high in cases:
        with pytest.raises(SetpointRangeError) as info:
            call()
        err = info.value
        assert (err.name, err.unit, err.high) == (name, unit, high)
        assert name in str(err) and unit in str(err)
    assert mega.write_requests == writes  # the server saw no write at all
    assert mega.snapshot()["holding"][HR.SPEED_SETPOINT_0P1MMS] == 0
    drum.set_speed(100)  # the limit itself is allowed
    assert drum.read_holding(HR.SPEED_SETPOINT_0P1MMS) == 1000


def test_modbus_exceptions_become_named_errors(drum, mega):
    with pytest.raises(ModbusExceptionError) as info:
        drum.read_holdings(wire.N_HOLDING - 2, 5)  # runs off the table
    name = HR(wire.N_HOLDING - 2).name
    assert info.value.exception_code == 2 and info.value.register == name
    assert name in str(info.value) and "illegal data address" in str(info.value)
    with pytest.raises(ModbusExceptionError) as info:
        drum.read_input(wire.N_INPUT)
    assert info.value.exception_code == 2 and f"input register {wire.N_INPUT}" in str(info.value)
    # a write the client passes (within the range column) that the controller refuses: force above its limit,
    # in one function-16 request together with a valid speed: nothing of it is applied
    with pytest.raises(ModbusExceptionError) as info:
        drum.write_holdings(HR.SPEED_SETPOINT_0P1MMS, [900, 1800])
    assert info.value.exception_code == 3 and info.value.register == "SPEED_SETPOINT_0P1MMS"
    assert drum.read_holdings(0, 2) == [0, 0]
    # a command not allowed in the current state
    drum.set_force(300)
    drum.press()
    with pytest.raises(ModbusExceptionError) as info:
        drum.home()
    assert (info.value.register, info.value.exception_code) == ("COMMAND", 3)
    drum.stop()


# wall: the host's silence is a time.sleep, which the heartbeat grants the board
@pytest.mark.realtime
def test_watchdog_trips_when_host_goes_silent(drum, mega):
    # 2 s, not the firmware's 1 s default: on a starved machine one lost answer and its retry (the virtual Mega's
    # thread shares the host's cores) can alone outlast a shorter watchdog while the host keeps polling
    drum.write_holding(HR.WATCHDOG_MS, 2000)
    time.sleep(2.5)  # idle and silent: a monitoring host never trips it
    assert drum.read_status().state == DrumState.IDLE
    drum.set_force(250)
    drum.set_speed(60)
    drum.run()
    for _ in range(10):  # requests every 50 ms keep it fed
        time.sleep(0.05)
        assert drum.read_status().state == DrumState.RUNNING
    time.sleep(3.0)  # silence longer than WATCHDOG_MS
    status = drum.read_status()
    assert status.state == DrumState.FAULT
    assert status.faults == Fault.WATCHDOG
    assert status.speed_target_mm_s == 0 and status.force_setpoint_active_g == 0
    with pytest.raises(DrumFault) as info:
        drum.wait_force_settled(1)
    assert "WATCHDOG" in str(info.value) and info.value.faults == Fault.WATCHDOG
    with pytest.raises(ModbusExceptionError):
        drum.run()  # refused while in FAULT
    drum.stop()
    assert drum.read_status().state == DrumState.FAULT  # only CLEAR_FAULT leaves FAULT
    drum.clear_fault()
    status = drum.read_status()
    assert status.state == DrumState.IDLE and status.faults == 0


def _stall(mega, where: str, seconds: float) -> None:
    """Really stall one of the virtual Mega's threads for ``seconds`` (as a starved thread stalls), from now on:
    the Modbus server's loop (blocked), the pty copy thread (blocked mid-copy on the board port's lock), or the pty
    copy thread with the next reply in its hands (the host has been served and waits for the answer)."""
    if where == "server":
        mega._loop.call_soon_threadsafe(time.sleep, seconds)
        return
    if where == "reply":
        client = mega.bridge.client
        deliver = client.write

        def late_once(data):
            client.write = deliver
            time.sleep(seconds)
            return deliver(data)

        client.write = late_once
        return
    lock = mega.bridge.board._lock
    lock.acquire()
    threading.Timer(seconds, lock.release).start()


def _timed_link(drum: DrumClient, mega) -> tuple[list[float], list[float]]:
    """Stamp, from now on, each request the host hands to its port (after the write) and each reply the simulator
    hands to the host's port (before the write): the silence the host itself kept between a reply and its next
    request is at most the gap between the two (its own scheduling delay, measured)."""
    sends, replies = [], []
    send, deliver = drum._client.send, mega.bridge.client.write

    def timed_send(request, *args):
        n = send(request, *args)
        sends.append(time.monotonic())
        return n

    def timed_deliver(data):
        replies.append(time.monotonic())
        return deliver(data)

    drum._client.send = timed_send
    mega.bridge.client.write = timed_deliver
    return sends, replies


def _longest_host_silence_s(sends: list[float], replies: list[float], now: float) -> float:
    """The longest a request of the host (or ``now``, its silence so far) came after the reply before it reached the
    host's port, s (at most)."""
    gaps = [t - max((r for r in replies if r < t), default=t) for t in [*sends, now]]
    return max(gaps)


# wall: a board thread stalled for 1.6 s of wall time while the host polls
@pytest.mark.realtime
@pytest.mark.parametrize("where", ["server", "bridge", "reply"])
def test_a_starved_simulator_does_not_call_a_punctual_host_silent(mega, where):
    """A flake under heavy CPU load: the virtual Mega's Modbus thread or pty copy thread got no CPU for longer than
    WATCHDOG_MS while the host kept polling on time, and the simulator called the host silent (WATCHDOG, the trial
    lost). The firmware handles a request within about a millisecond of its arrival, so that host was never silent.
    Here one of those threads really stalls while the host polls over the real ptys and pymodbus.

    The host must be punctual for that to be judged: a host thread itself starved for the watchdog's time (measured:
    a request that came that long after the reply before it) was silent, and the WATCHDOG is then right; such an
    attempt judges nothing and is made again (at most three times)."""
    stall_s = 1.6  # > WATCHDOG_MS (1000 ms)
    # one request at a time; the answer timeout is a bound on a hang (a reply through the ptys after the stall took
    # over 3.6 s at load ~12: the kernel hands a pty's bytes over seconds late then)
    with DrumClient(mega.path, timeout_s=stall_s + 10.0, retries=0, poll_s=0.02) as drum:
        home(drum)
        watchdog_s = drum.read_holding(HR.WATCHDOG_MS) / 1000.0
        drum.set_force(250)
        drum.set_speed(60)
        late = []
        for _attempt in range(3):
            drum.run()
            drum.wait_state([DrumState.RUNNING], timeout_s=5)
            sends, replies = _timed_link(drum, mega)
            requests = mega.requests
            _stall(mega, where, stall_s)
            t0 = time.monotonic()
            latencies, tripped = [], None
            while time.monotonic() - t0 < stall_s + 0.5:
                t = time.monotonic()
                status = drum.read_status()
                latencies.append(time.monotonic() - t)
                if status.state != DrumState.RUNNING or status.faults != 0:
                    tripped = (status.state, status.faults)
                    break
                time.sleep(0.05)
            faults = mega.snapshot()["faults"]  # (a trip after the last read)
            silence_s = _longest_host_silence_s(sends, replies, time.monotonic())
            if tripped is None and faults:
                tripped = ("after the last read", faults)
            if tripped is None:
                break
            # called silent: right only if the host was (its silence measured from its side of the link)
            assert silence_s >= watchdog_s, (tripped, f"the host was silent {silence_s:.3f} s at most")
            late.append(round(silence_s, 3))
            time.sleep(stall_s)  # the stalled thread goes on
            drum.stop()
            drum.clear_fault()
            drum.wait_state([DrumState.IDLE], timeout_s=5)
        else:
            raise AssertionError(f"the host itself was starved in every attempt: silent {late} s (> {watchdog_s} s)")
        assert max(latencies) > 1.0  # a request waited out the stall: the simulator was starved that long
        assert mega.requests - requests == len(latencies)
        assert mega.snapshot()["faults"] == 0
        # and silence is still silence, whatever the simulator's threads do meanwhile
        _stall(mega, where, 0.3)
        time.sleep(1.5)
        status = drum.read_status()
        assert status.state == DrumState.FAULT and status.faults == Fault.WATCHDOG
        drum.stop()
        drum.clear_fault()


def test_home_tare_and_calibration_eeprom(drum, mega, tmp_path):
    drum.home()
    assert drum.wait_state(DrumState.IDLE, timeout_s=2).actuator_mm == 0
    drum.tare()
    assert abs(drum.read_status().force_g) <= 5
    assert not drum.read_status().calibration_defaults  # the factory calibration (the fixture's board)
    drum.set_loadcell_scale(400.0)  # a different calibration scales the measured force
    assert drum.loadcell_scale() == 400.0 and drum.read_holding(HR.LOADCELL_SCALE_X100) == 40000
    drum.write_holding(HR.ACTUATOR_STEPS_PER_MM, 500)
    drum.save_calibration()
    assert not drum.read_status().calibration_defaults
    data = json.loads((tmp_path / "eeprom.json").read_text())
    assert data["calibration"]["scale_x100"] == 40000 and data["calibration"]["actuator_steps_per_mm"] == 500
    # the lead screw's true 400 steps/mm again: 500 would make the probe's stiffness 1.25 x (the controller takes a
    # step for 2 um, not 2.5), which the scale check of every probe refuses (LOADCELL_SCALE, wire-protocol 2.12)
    drum.write_holding(HR.ACTUATOR_STEPS_PER_MM, 400)
    drum.set_force(420)
    drum.press()
    drum.wait_force_settled(6)
    # the controller believes 420 g at 400 counts/g: the true (model) force is 420 * 400 / 420 = 400 g
    assert abs(mega.model.contact_force_g - 400) <= 20
    drum.stop()


def test_press_refused_before_home_names_why(tmp_path):
    """After power-up the controller is NOT_HOMED: PRESS and RUN come back as DrumNotHomed, which says why."""
    board = VirtualMega(RigModel(seed=7), tmp_path / "drum", factory_calibrated=True).start()
    try:
        with DrumClient(board.path, timeout_s=0.5, retries=2, poll_s=0.02) as drum:
            assert drum.read_status().state == DrumState.NOT_HOMED
            for send in (drum.press, drum.run):
                with pytest.raises(DrumNotHomed) as info:
                    send()
                assert info.value.exception_code == 3 and "NOT_HOMED" in str(info.value) and "HOME" in str(info.value)
            home(drum)
            drum.set_force(200)
            drum.press()
            drum.stop()
    finally:
        board.close()


def test_bad_eeprom_checksum_is_reported_and_defaults_used(tmp_path):
    """A calibration record whose checksum fails: the controller boots on the spec's defaults and raises
    CALIBRATION_DEFAULTS (the firmware did so silently before)."""
    path = tmp_path / "eeprom.json"
    board = VirtualMega(RigModel(seed=7), tmp_path / "drum", eeprom_path=path).start()
    try:
        with DrumClient(board.path, timeout_s=0.5, retries=2, poll_s=0.02) as drum:
            home(drum)
            drum.set_loadcell_scale(-2150.0)  # a reversed 1 kg, 1 mV/V cell: beyond firmware 1.0's 655 counts/g
            drum.save_calibration()
            assert not drum.read_status().calibration_defaults
    finally:
        board.close()
    board = VirtualMega(RigModel(seed=7), tmp_path / "drum2", eeprom_path=path).start()
    try:
        with DrumClient(board.path, timeout_s=0.5, retries=2, poll_s=0.02) as drum:
            st = drum.read_status()
            assert drum.loadcell_scale() == -2150.0 and not st.calibration_defaults and st.boot_count == 0x100
            board.corrupt_eeprom()
    finally:
        board.close()
    board = VirtualMega(RigModel(seed=7), tmp_path / "drum3", eeprom_path=path).start()
    try:
        with DrumClient(board.path, timeout_s=0.5, retries=2, poll_s=0.02) as drum:
            st = drum.read_status()
            assert st.calibration_defaults and st.boot_count == 0x200  # power-ups: BOOT_COUNT's high byte
            assert drum.loadcell_scale() == wire.HOLDING_RANGE[HR.LOADCELL_SCALE_X100][2] / 100
    finally:
        board.close()


# wall: a pty nobody serves: the answer timeout is the wall clock's
@pytest.mark.realtime
def test_timeout_when_nobody_answers(tmp_path):
    from rigctl.simulation.pty import PtyEndpoint

    silent = PtyEndpoint(tmp_path / "silent")  # a port with no controller behind it
    try:
        with DrumClient(silent.path, timeout_s=0.1, retries=1) as client:
            t0 = time.monotonic()
            with pytest.raises(DrumTimeout) as info:
                client.read_status()
            assert time.monotonic() - t0 < 2.0
            assert "no answer" in str(info.value)
    finally:
        silent.close()
