"""Debian's mbpoll as an independent Modbus master against `rigctl sim` (a separate process), and the CLIs."""

from __future__ import annotations

import json
import re
import shutil
import subprocess

import pytest
from click.testing import CliRunner

from rigctl.cli.sim import start_sim_process
from rigctl.devices import wire
from rigctl.devices.drum import DrumClient
from rigctl.devices.ports import find_ports, guess_board
from rigctl.devices.wire import HoldingRegister as HR, InputRegister as IR

MBPOLL = shutil.which("mbpoll")


@pytest.fixture(scope="module")
def sim_process(tmp_path_factory):
    port_dir = tmp_path_factory.mktemp("sim")
    try:
        proc, ports = start_sim_process(str(port_dir), texture="G", seed=2)
    except RuntimeError as exc:
        pytest.fail(str(exc))
    yield ports
    proc.terminate()
    out, err = proc.communicate(timeout=120)  # only bounds a hang: a starved machine takes tens of seconds to stop a sim
    assert proc.returncode == 0, err
    assert "simulated rig stopped" in out


def mbpoll(*args) -> subprocess.CompletedProcess:
    """mbpoll with an answer timeout of 5 s (-o): its request and the answer cross four pty hops to `rigctl sim` and
    back, and on a loaded machine the kernel hands a pty's bytes over up to hundreds of ms late (0.5-0.8 s measured,
    test_devices_taxel's PtyDelayProbe): 0.5 s timed out (CI), and a late answer left in the port was read by the
    next mbpoll as its own ('Invalid data'). An answer that comes is taken at once; what is judged is its content."""
    if MBPOLL is None:
        pytest.fail("mbpoll is not installed (Debian package mbpoll)")
    return subprocess.run([MBPOLL, "-m", "rtu", "-a", "1", "-b", str(wire.DRUM_BAUD), "-P", "none", "-o", "5", *args],
                          capture_output=True, text=True, timeout=20)


def parse_registers(text: str) -> dict[int, int]:
    """mbpoll's `[ref]: value` lines -> {reference: value} (references are 1-based: address + 1)."""
    return {int(r): int(v) for r, v in re.findall(r"^\[(\d+)\]:\s+(-?\d+)", text, re.M)}


# wall: a `rigctl sim` of its own process (always paced to the wall clock: the rig other programs drive as hardware),
#   mbpoll with its own answer timeout
@pytest.mark.realtime
def test_sim_prints_ports_and_mbpoll_reads_the_register_map(sim_process):
    port = sim_process["drum"]
    res = mbpoll("-t", "4", "-r", "1", "-c", str(wire.N_HOLDING), "-1", port)
    assert res.returncode == 0, res.stderr
    regs = parse_registers(res.stdout)
    # every address of the span: the spec's defaults, reserved addresses 0 (spec 2); the factory's calibration stored
    # the rig's own plate's stiffness (spec 2.12: the default rig's 250 g/mm)
    stored = {HR.CALIBRATION_STIFFNESS_G_PER_MM: 250}
    assert regs == {a + 1: (0 if a == HR.COMMAND else stored.get(a, wire.holding_range(a)[2]))
                    for a in range(wire.N_HOLDING)}
    res = mbpoll("-t", "3", "-r", "1", "-c", str(wire.N_INPUT), "-1", port)
    assert res.returncode == 0, res.stderr
    inputs = parse_registers(res.stdout)
    assert len(inputs) == wire.N_INPUT
    assert inputs[IR.FIRMWARE_VERSION + 1] == 265  # 1.9
    assert inputs[IR.STATE + 1] == wire.DrumState.NOT_HOMED  # powered up, nobody homed it


# wall: a `rigctl sim` of its own process (always paced to the wall clock: the rig other programs drive as hardware),
#   mbpoll with its own answer timeout
@pytest.mark.realtime
def test_mbpoll_writes_what_drumclient_reads_and_vice_versa(sim_process):
    port = sim_process["drum"]
    res = mbpoll("-t", "4", "-r", str(HR.SPEED_SETPOINT_0P1MMS + 1), port, "800")
    assert res.returncode == 0 and "Written 1 references" in res.stdout, res.stderr
    res = mbpoll("-t", "4", "-r", str(HR.RAMP_START_SPEED_0P1MMS + 1), port, "500", "900", "2500")  # function 16
    assert res.returncode == 0, res.stderr
    with DrumClient(port) as drum:
        assert drum.read_holding(HR.SPEED_SETPOINT_0P1MMS) == 800
        assert drum.read_holdings(HR.RAMP_START_SPEED_0P1MMS, 3) == [500, 900, 2500]
        drum.set_force(321)
    res = mbpoll("-t", "4", "-r", str(HR.FORCE_SETPOINT_G + 1), "-1", port)
    assert parse_registers(res.stdout) == {HR.FORCE_SETPOINT_G + 1: 321}


# wall: a `rigctl sim` of its own process (always paced to the wall clock: the rig other programs drive as hardware),
#   mbpoll with its own answer timeout
@pytest.mark.realtime
def test_mbpoll_sees_the_spec_exceptions(sim_process):
    port = sim_process["drum"]
    res = mbpoll("-t", "4", "-r", str(HR.SPEED_SETPOINT_0P1MMS + 1), port, "2001")
    assert res.returncode != 0 and "Illegal data value" in res.stderr
    res = mbpoll("-t", "4", "-r", str(wire.N_HOLDING + 1), "-1", port)  # no such register
    assert res.returncode != 0 and "Illegal data address" in res.stderr
    res = mbpoll("-t", "3", "-r", str(wire.N_INPUT), "-c", "2", "-1", port)  # runs off the input table
    assert res.returncode != 0 and "Illegal data address" in res.stderr


def test_guess_board_and_ports_cli():
    assert guess_board(0x2341, 0x0042)[0] == "mega"
    assert guess_board(0x2341, 0x0010)[0] == "mega"
    assert guess_board(0x2341, 0x0043)[0] == "uno"
    assert guess_board(0x2341, 0x0001)[0] == "uno"
    board, note = guess_board(0x1A86, 0x7523)
    assert board is None and "CH340" in note
    assert guess_board(None, None) == (None, "not a USB device")
    from rigctl.cli import main

    res = CliRunner().invoke(main, ["ports", "--json", "--all"])
    assert res.exit_code == 0, res.output
    listed = json.loads(res.output)
    assert [p["device"] for p in listed] == [p.device for p in find_ports(include_all=True)]
    res = CliRunner().invoke(main, ["ports"])
    assert res.exit_code == 0
