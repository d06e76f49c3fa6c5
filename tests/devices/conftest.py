"""Fixtures of the device tests: virtual boards on real ptys, clients on the real pyserial/pymodbus stacks."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl.devices.drum import DrumClient
from rigctl.simulation.model import RigModel
from rigctl.simulation.virtual_mega import VirtualMega
from rigctl.simulation.virtual_uno import VirtualUno


@pytest.fixture
def mega(tmp_path):
    """A VirtualMega on its own real-time control loop (200 Hz), Modbus port at ``mega.path``."""
    board = VirtualMega(RigModel(seed=7), tmp_path / "drum", eeprom_path=tmp_path / "eeprom.json").start()
    yield board
    board.close()


@pytest.fixture
def drum(mega):
    """A DrumClient connected to the ``mega`` fixture."""
    with DrumClient(mega.path, timeout_s=0.5, retries=2, poll_s=0.02) as client:
        yield client


class CountingSource:
    """Deterministic taxel samples: sample k (counted from the board's start) holds ``(k * 7 + channel) % 1024``."""

    def __init__(self):
        self.k = 0

    def __call__(self, n):
        k = self.k + np.arange(n)
        self.k += n
        samples = ((k[:, None] * 7 + np.arange(18)[None, :]) % 1024).astype(np.uint16)
        return samples, (k % 500) == 0


@pytest.fixture
def uno(tmp_path):
    """A VirtualUno on its own real-time clock, fed by :class:`CountingSource`; port at ``uno.path``."""
    board = VirtualUno(tmp_path / "taxel", reset_delay_s=0.1)
    board.run_paced(CountingSource())
    yield board
    board.close()
