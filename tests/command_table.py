"""The drum controller's command table, read from docs/wire-protocol.md (``<!-- table: command-states -->``): which
command each state allows and the state the write leaves. The one copy the tests hold: the all-pairs walk against
controller.c (tests/firmware/test_fw_command_table.py) and the conformance suite read it from here."""

from __future__ import annotations

from pathlib import Path

from rigctl.devices.wire import Command, DrumState

from .test_wire_spec import spec_tables

SPEC = Path(__file__).resolve().parents[1] / "docs" / "wire-protocol.md"
#: a cell: the command refused (exception 03, nothing changes)
REFUSED = "refused"
#: a cell: accepted, the state stays
SAME = "="
#: a cell: accepted, IDLE if homed else NOT_HOMED
REST = "REST"


def command_table() -> dict[DrumState, dict[Command, str]]:
    """``{state: {command: cell}}`` for every state and command of the spec (KeyError / ValueError when the table
    misses one or names another)."""
    rows = spec_tables(SPEC.read_text())["command-states"]
    table = {DrumState[row["state"]]: {Command[name]: cell for name, cell in row.items() if name != "state"}
             for row in rows}
    for state in DrumState:
        cells = table[state]
        assert set(cells) == set(Command), f"{state.name}: {sorted(c.name for c in set(Command) ^ set(cells))}"
        for cell in cells.values():
            assert cell in (REFUSED, SAME, REST) or cell in DrumState.__members__, cell
    return table


def refused_in(state: DrumState) -> list[Command]:
    """The commands ``state`` refuses."""
    return [cmd for cmd, cell in command_table()[state].items() if cell == REFUSED]


def unchanged_in(state: DrumState) -> list[Command]:
    """The commands ``state`` accepts and stays in."""
    return [cmd for cmd, cell in command_table()[state].items() if cell == SAME]
