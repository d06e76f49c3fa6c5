"""Fixtures of the device tests: virtual boards on real ptys, clients on the real pyserial/pymodbus stacks."""

from __future__ import annotations

import pytest

from rigctl.devices.drum import DrumClient
from rigctl.devices.wire import DrumState
from rigctl.simulation.counting import CountingSource
from rigctl.simulation.model import RigModel
from rigctl.simulation.virtual_mega import VirtualMega
from rigctl.simulation.virtual_uno import VirtualUno


@pytest.fixture
def mega(tmp_path):
    """A VirtualMega on its own real-time control loop (200 Hz), Modbus port at ``mega.path``; calibrated (a default
    calibration refuses PRESS and RUN, docs/wire-protocol.md 2.11)."""
    board = VirtualMega(RigModel(seed=7), tmp_path / "drum", eeprom_path=tmp_path / "eeprom.json",
                        factory_calibrated=True).start()
    yield board
    board.close()


def home(client: DrumClient) -> None:
    """HOME a controller that has just powered up (NOT_HOMED: it refuses RUN and PRESS until then), as a rig does
    when it opens (rigctl.acquisition.rig.Rig.connect)."""
    client.home()
    client.wait_state(DrumState.IDLE, timeout_s=5)


@pytest.fixture
def drum(mega):
    """A DrumClient connected to the ``mega`` fixture, the controller homed."""
    with DrumClient(mega.path, timeout_s=0.5, retries=2, poll_s=0.02) as client:
        home(client)
        yield client


@pytest.fixture
def uno(tmp_path):
    """A VirtualUno on its own real-time clock, fed by :class:`CountingSource`; port at ``uno.path``."""
    board = VirtualUno(tmp_path / "taxel", reset_delay_s=0.1)
    board.run_paced(CountingSource())
    yield board
    board.close()


@pytest.fixture
def clocked_uno(tmp_path):
    """A VirtualUno on a clock of its own shared with the host, unpaced (``uno.clock``: a TaxelStream opening
    ``uno.path`` finds it, and its banner wait, stamps and waits judge it; a starved host pauses the board), fed by
    :class:`CountingSource`; port at ``uno.path``."""
    board = VirtualUno(tmp_path / "taxel", reset_delay_s=0.1)
    board.run_on_clock(CountingSource())
    yield board
    board.close()
