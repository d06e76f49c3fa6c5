"""The Mega drum controller firmware under simavr, driven by the project's own DrumClient, by Debian's mbpoll and
by raw (malformed) Modbus frames (hardware in the loop).

The register map, commands, states, setpoints, force loop, faults and the watchdog are tested once for both drum
controllers (this firmware and the virtual Mega) in tests/conformance; what is here needs the firmware itself: step
rates on the STEP pin, mbpoll, malformed frames, the round trip, the EEPROM across a reset."""

from __future__ import annotations

import math
import re
import shutil
import subprocess
import time

import pytest
import serial

from rigctl import firmware
from rigctl.devices import wire
from rigctl.devices.drum import DrumClient
from rigctl.rigs import drum_answer_timeout_s

from .conftest import home

pytestmark = pytest.mark.hil

HR, IR = wire.HoldingRegister, wire.InputRegister
State, Fault = wire.DrumState, wire.Fault


def hil_drum(rig) -> DrumClient:
    """A DrumClient for the Mega under simavr, with the answer timeout ``open_rig("hil")`` gives it (on a starved
    host the firmware runs at 0.1-0.4 of real time)."""
    return DrumClient(rig.drum_port, timeout_s=drum_answer_timeout_s("hil"))


def expected_step_rate(v_mm_s: float) -> float:
    """Spec 2.6: f = v * steps_per_rev * microsteps / (pi * diameter)."""
    return v_mm_s * 200 * 16 / (math.pi * 100.0)


@pytest.fixture
def drum(hil_rig):
    with hil_drum(hil_rig) as d:
        home(d)
        yield d
        # leave the rig idle and fault-free for the next test
        hil_rig.bump(0)
        d.stop()
        if d.read_status().state == State.FAULT:
            time.sleep(0.1)
            d.clear_fault()
        d.write_holding(HR.WATCHDOG_MS, 1000)
        d.wait_state([State.IDLE], timeout_s=10)


@pytest.mark.parametrize("v", [40, 80, 120])
def test_speed_setpoint_gives_the_step_rate(hil_rig, drum, v):
    drum.write_holding(HR.WATCHDOG_MS, 5000)  # the pin measurement below keeps the host quiet for ~1 s
    drum.set_force(0)
    drum.set_speed(v)
    drum.run()
    st = drum.wait_speed_steady(timeout_s=5.0, tol_mm_s=0.5)
    assert st.state == State.RUNNING
    rate = hil_rig.step_rate_hz(window_s=1.0)
    f = expected_step_rate(v)
    assert abs(rate / f - 1) < 0.005, f"{v} mm/s: {rate:.2f} steps/s on the STEP pin, expected {f:.2f}"
    st = drum.read_status()
    assert abs(st.speed_mm_s / v - 1) < 0.005 and st.speed_target_mm_s == pytest.approx(v)
    drum.stop_drum()


MBPOLL = shutil.which("mbpoll")


def mbpoll(port, *args, values=()) -> subprocess.CompletedProcess:
    """mbpoll as a Modbus RTU master on ``port`` (0-based register numbers, ``-0``); ``values`` are written."""
    if MBPOLL is None:
        pytest.fail("mbpoll is not installed (Debian package mbpoll)")
    return subprocess.run([MBPOLL, "-m", "rtu", "-a", "1", "-b", str(wire.DRUM_BAUD), "-P", "none", "-o", "1", "-0", *args,
                           port, *map(str, values)], capture_output=True, text=True, timeout=20)


def registers(text: str) -> dict[int, int]:
    return {int(r): int(v) for r, v in re.findall(r"^\[(\d+)\]:\s+(-?\d+)", text, re.M)}


def test_mbpoll_reads_and_writes_the_registers(hil_rig):
    with hil_drum(hil_rig) as d:
        ours = d.read_holdings(0, wire.N_HOLDING)
    out = mbpoll(hil_rig.drum_port, "-t", "4", "-r", "0", "-c", str(wire.N_HOLDING), "-1")
    assert out.returncode == 0, out.stdout + out.stderr
    regs = registers(out.stdout)
    assert [regs[i] for i in range(wire.N_HOLDING)] == ours
    for reg in (HR.RAMP_START_SPEED_0P1MMS, HR.RAMP_END_SPEED_0P1MMS, HR.RAMP_DURATION_MS, HR.LOADCELL_SCALE_X100,
                HR.ACTUATOR_STEPS_PER_MM):  # registers no test writes: still the spec's defaults
        assert regs[int(reg)] == wire.HOLDING_RANGE[reg][2], reg.name
    out = mbpoll(hil_rig.drum_port, "-t", "3", "-r", "0", "-c", str(wire.N_INPUT), "-1")
    assert out.returncode == 0, out.stdout + out.stderr
    regs = registers(out.stdout)
    assert regs[int(IR.FIRMWARE_VERSION)] == 265  # 1.9
    # BUILD_ID_0 .. _2 (spec 2.2): the id rigctl's build gave the image, most significant word first (mbpoll prints
    # uint16 registers as signed decimals)
    own = firmware.build_id()
    assert [regs[int(r)] & 0xFFFF for r in (IR.BUILD_ID_0, IR.BUILD_ID_1, IR.BUILD_ID_2)] == \
        [int(own[i:i + 4], 16) for i in (0, 4, 8)]
    out = mbpoll(hil_rig.drum_port, "-t", "4", "-r", str(int(HR.SETTLE_TIME_MS)), values=[450])
    assert out.returncode == 0, out.stdout + out.stderr
    out = mbpoll(hil_rig.drum_port, "-t", "4", "-r", str(int(HR.SPEED_SETPOINT_0P1MMS)), values=[2001])  # out of range
    assert out.returncode != 0
    with hil_drum(hil_rig) as d:
        assert d.read_holding(HR.SETTLE_TIME_MS) == 450
        assert d.read_holding(HR.SPEED_SETPOINT_0P1MMS) <= 2000
        d.write_holding(HR.SETTLE_TIME_MS, 300)


def _frame(*pdu: int) -> bytes:
    return bytes(pdu) + wire.crc16(bytes(pdu)).to_bytes(2, "little")


def _transact(ser: serial.Serial, req: bytes, expect: int = 5, timeout_s: float = 1.0) -> bytes:
    """Send ``req``; read until ``expect`` bytes came or ``timeout_s`` passed (``expect=0``: collect for 0.3 s)."""
    ser.reset_input_buffer()
    ser.write(req)
    out = b""
    deadline = time.monotonic() + (timeout_s if expect else 0.3)
    while time.monotonic() < deadline and (not expect or len(out) < expect):
        out += ser.read(max(1, ser.in_waiting))
    return out


def test_malformed_requests_get_exceptions_never_a_hang(hil_rig):
    """What only the firmware can do (it frames requests by t3.5 silence, the virtual Mega's pymodbus server by
    length): a truncated request with a valid CRC gets exception 03, and line noise is survived. Functions, CRC,
    other devices, broadcast and length errors of whole frames: tests/conformance, for both controllers."""
    with serial.Serial(hil_rig.drum_port, wire.DRUM_BAUD, timeout=0.2) as ser:
        before = _transact(ser, _frame(1, 3, 0, 0, 0, 2), expect=9)
        assert len(before) == 9 and before[:3] == bytes([1, 3, 4])
        assert _transact(ser, _frame(1, 3, 0, 0, 0)) == _frame(1, 0x83, 3)  # truncated request, valid CRC
        assert _transact(ser, bytes(range(0, 250, 3)), expect=0) == b""
        # the device recovers: the next valid request is answered (a second try is allowed, as a master would
        # retry: on a loaded host the simulated line may still be busy with the noise when it is sent, and Modbus
        # then rightly sees one long garbage frame)
        for _attempt in range(2):
            resp = _transact(ser, _frame(1, 4, 0, int(IR.FIRMWARE_VERSION), 0, 1), expect=7)
            if resp:
                break
        assert resp == _frame(1, 4, 2, *wire.MEGA_FIRMWARE_VERSION)
        assert _transact(ser, _frame(1, 3, 0, 0, 0, 2), expect=9) == before


def test_modbus_round_trip_time(hil_rig):
    with hil_drum(hil_rig) as d:
        d.read_status()
        n = 50
        t0 = time.perf_counter()
        for _ in range(n):
            d.read_status()
        rtt = (time.perf_counter() - t0) / n
    reply = 5 + 2 * wire.N_INPUT  # id, function, byte count, the registers, CRC
    print(f"Modbus round trip (read {wire.N_INPUT} input registers, pymodbus <-> firmware under simavr): "
          f"{rtt * 1e3:.1f} ms")
    # simavr times every byte from UBRR: no round trip beats the wire (request 8 B + t3.5 (1.75 ms above 19200 baud)
    # + the reply (71 B for 33 registers), 11 bit times a byte in simavr: 3.5 ms at 500000 baud). Upper bounds are
    # benchmarks/bench_firmware_hil.py's business.
    assert rtt > (8 + reply) * 11 / wire.DRUM_BAUD + 1.75e-3


def test_calibration_survives_a_reset_only_when_saved(hil_rig):
    with hil_drum(hil_rig) as d:
        d.write_holding(HR.LOADCELL_SCALE_X100, 41234)
        d.write_holding(HR.ACTUATOR_STEPS_PER_MM, 401)
        d.save_calibration()
        d.write_holding(HR.LOADCELL_SCALE_X100, 40000)  # changed but not saved
        booted = wire.boot_count_after(d.read_status().boot_count, wire.ResetCause.EXTERNAL)
        hil_rig.reset_mega()
        # on the Mega's clock: a request lost in the reset costs the client its answer timeouts (2 s each, retried),
        # more than a few seconds of a loaded host's time
        deadline = hil_rig.clock.now() + 10
        while True:  # the controller restarts (BOOT_COUNT: one warm reset more), defaults in RAM, calibration from EEPROM
            try:  # (not "the heartbeat back below the last": a reset 0.5 s after power-up, whose first answer came
                st = d.read_status()  # after a lost request's 2 s, counted past it: "no restart seen" in 1 of 4 runs)
                if st.boot_count == booted:
                    break
            except Exception:
                pass
            assert hil_rig.clock.now() < deadline, "no restart seen"
            hil_rig.clock.sleep(0.05)
        hil_rig.clock.sleep(0.3)  # longer than the load-cell timeout: a reset mid HX711 read must come up clean
        st = d.read_status()
        assert (st.state, st.faults, st.reset_cause) == (State.NOT_HOMED, Fault(0), wire.ResetCause.EXTERNAL)
        assert not st.calibration_defaults
        home(d)
        assert d.read_holding(HR.LOADCELL_SCALE_X100) == 41234
        assert d.read_holding(HR.ACTUATOR_STEPS_PER_MM) == 401
        assert d.read_holding(HR.SETTLE_TIME_MS) == wire.HOLDING_RANGE[HR.SETTLE_TIME_MS][2]
        # back to the spec's defaults, saved, for the other tests
        d.write_holding(HR.LOADCELL_SCALE_X100, wire.HOLDING_RANGE[HR.LOADCELL_SCALE_X100][2])
        d.write_holding(HR.ACTUATOR_STEPS_PER_MM, wire.HOLDING_RANGE[HR.ACTUATOR_STEPS_PER_MM][2])
        d.save_calibration()
