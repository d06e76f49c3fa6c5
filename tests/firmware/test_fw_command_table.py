"""The command table of docs/wire-protocol.md (``command-states``: which command each state allows and the state the
write leaves) against the firmware's own ``controller.c``, built for the host (rigctl.simulation.mega_c): every
(state, command) pair. Each state is reached on the model rig (controller.c with its glue and the physics), the
controller's struct saved there, and each command written to that saved struct (``ctl_write_holding``, what the
Modbus handler calls): accepted or refused, and the state it leaves, cell by cell. A change of one cell of the C guard
fails it (the second test: a copy of the sources with STOP_DRUM allowed in IDLE)."""

from __future__ import annotations

import re
import shutil
from typing import Any

from rigctl import firmware
from rigctl.devices.wire import Command, DrumState as S, HoldingRegister as HR
from rigctl.simulation import mega_c
from rigctl.simulation.controller import MegaController
from rigctl.simulation.model import RigModel

from ..command_table import REFUSED, REST, SAME, command_table


def _write(ctl: MegaController, reg: int, value: int) -> None:
    assert ctl.write_registers(6, reg, [int(value)]) is None, (HR(reg).name, value, ctl.state, ctl.faults)


def _run_until(ctl: MegaController, done, what: str, limit_ms: int = 20000) -> None:
    for _ in range(limit_ms // 10):
        ctl.note_request()
        ctl.step(10, render=False)
        if done():
            return
    raise AssertionError(f"never {what}: {ctl.snapshot()}")


def reach_every_state(library: tuple[Any, Any] | None = None) -> dict[S, bytes]:
    """``{state: the controller's struct in it}``, each reached with ordinary commands on the model rig, the guards of
    the table met (at home unloaded where it matters, calibrated, the HX711's rate measured)."""
    ctl = MegaController(RigModel(seed=11), factory_calibrated=True, library=library)
    ffi, c = ctl._ffi, ctl._c
    saved: dict[S, bytes] = {}

    def save() -> None:
        saved[ctl.state] = bytes(ffi.buffer(c))

    _write(ctl, HR.WATCHDOG_MS, 10000)
    save()  # NOT_HOMED: out of reset, at home
    _write(ctl, HR.COMMAND, Command.HOME)
    save()  # HOMING (from NOT_HOMED)
    _run_until(ctl, lambda: ctl.state == S.IDLE, "IDLE after HOME")
    save()  # IDLE, homed, tared at the switch
    _write(ctl, HR.SETTLE_TIME_MS, 200)
    _write(ctl, HR.FORCE_SETPOINT_G, 300)
    _write(ctl, HR.COMMAND, Command.PRESS)
    save()  # SEEKING_FORCE
    _run_until(ctl, lambda: ctl.state == S.FORCE_SETTLED, "FORCE_SETTLED")
    save()
    _write(ctl, HR.SPEED_SETPOINT_0P1MMS, 400)
    _write(ctl, HR.COMMAND, Command.RUN)
    save()  # RUNNING
    _write(ctl, HR.COMMAND, Command.STOP)
    _run_until(ctl, lambda: ctl.state == S.IDLE and ctl.model.actuator_mm <= 0 and abs(ctl.force_g) < 20,
               "back home after STOP")
    ctl.set_estop(True)  # FAULT whose condition is gone: an e-stop closed again
    ctl.step(10, render=False)
    ctl.set_estop(False)
    _run_until(ctl, lambda: ctl.state == S.FAULT and not ctl.estop_open, "FAULT")
    save()
    assert set(saved) == set(S), sorted(s.name for s in set(S) - set(saved))
    return saved


def walk(saved: dict[S, bytes], library: tuple[Any, Any]) -> list[str]:
    """Each command written to each saved state; the cells where controller.c does other than the table says."""
    ffi, lib = library
    c = ffi.new("ctl_t *")
    value = ffi.new("uint16_t[1]")
    wrong = []
    for state, cells in command_table().items():
        for cmd, cell in cells.items():
            ffi.buffer(c)[:] = saved[state]
            homed = bool(c.homed)
            value[0] = int(cmd)
            ex = lib.ctl_write_holding(c, int(HR.COMMAND), 1, value)
            got = "refused" if ex == 3 else f"exception {ex}" if ex else S(c.state).name
            if cell == REFUSED:
                want = "refused"
            elif cell == SAME:
                want = state.name
            elif cell == REST:
                want = "IDLE" if homed else "NOT_HOMED"
            else:
                want = cell
            if got != want:
                wrong.append(f"{state.name} x {cmd.name}: table {cell!r} ({want}), controller.c {got}")
    return wrong


def test_every_state_and_command_as_the_table_says():
    library = mega_c.load()
    assert walk(reach_every_state(library), library) == []


def test_one_cell_changed_in_the_c_guard_fails_the_walk(tmp_path):
    """The walk sees a change of one cell: a copy of the sources whose command_allowed also allows STOP_DRUM in IDLE
    (where the table says refused) differs in that cell and no other."""
    src = tmp_path / "arduino"
    shutil.copytree(firmware.sources(), src, ignore=shutil.ignore_patterns("build"))
    path = src / "mega_drum" / "controller.c"
    text = path.read_text()
    changed, n = re.subn(r"(case RIGCTL_CMD_STOP_DRUM:\n\s+return) force_engaged\(c\);",
                         r"\1 force_engaged(c) || s == RIGCTL_STATE_IDLE;", text)
    assert n == 1
    path.write_text(changed)
    library = mega_c.open_library(mega_c.build(src, tmp_path / "build"))
    assert walk(reach_every_state(library), library) == [
        "IDLE x STOP_DRUM: table 'refused' (refused), controller.c SEEKING_FORCE"]
