"""What a face may see of the drum controller: :class:`DrumView`, the read-only side of the rig's drum client.

A face (the GUI, the CLI, ``rigctl serve``, a Python protocol, the LSL feed) reads the controller through the rig's
owner, :class:`rigctl.operations.RigControl`; every command that moves (or could move) the rig goes through the
owner's methods, where the safety latch refuses it before anything is sent (docs/safety.md, issue 76: a latched rig
pressed through the raw client the owner handed out). The view has no command: no press, run, HOME, setpoint,
clear, calibration write or limit. What it has: the status, the settings and limits, the waits on them, and the clock
the rig's time runs on.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from rigctl.core.drum import Clock, DrumLimits, DrumState, DrumStatus
from rigctl.core.interfaces import DrumController

__all__ = ["DrumView"]


class DrumView:
    """The read-only view of ``drum`` (a :class:`rigctl.core.interfaces.DrumController`): reads and waits only.

    Attributes
    ----------
    clock : the rig's clock (:class:`rigctl.core.drum.Clock`: the wall's, or a simulated rig's)
    """

    __slots__ = ("__drum",)

    def __init__(self, drum: DrumController) -> None:
        self.__drum = drum  # name-mangled: the view hands out no way to the client

    @property
    def clock(self) -> Clock:
        return self.__drum.clock

    @property
    def status_listeners(self) -> list[Any] | None:
        """The client's status listeners (each ``fn(status)`` at every status read), None when it keeps none."""
        listeners: list[Any] | None = getattr(self.__drum, "status_listeners", None)
        return listeners

    def read_status(self) -> DrumStatus:
        """The controller's status now (a read: it moves nothing). DrumError."""
        return self.__drum.read_status()

    def read_holding(self, register: int) -> int:
        """One holding register's raw value (a read; the client's that have them: the Modbus clients). DrumError,
        AttributeError on a client without registers."""
        read: Any = self.__drum  # not on the DrumController protocol: the Modbus clients' own
        return int(read.read_holding(register))

    def settings(self) -> dict[str, int]:
        """The controller's settings registers (name -> raw value). DrumError."""
        return self.__drum.settings()

    def limits(self) -> DrumLimits:
        """The controller's hard limits. DrumError."""
        return self.__drum.limits()

    def loadcell_scale(self) -> float:
        """The load cell's scale the controller holds, counts/g. DrumError."""
        return self.__drum.loadcell_scale()

    def calibration_stiffness(self) -> int:
        """The contact's stiffness stored with the controller's calibration, g/mm (0: none). DrumError."""
        return self.__drum.calibration_stiffness()

    def wait_state(self, states: Iterable[DrumState], timeout_s: float) -> DrumStatus:
        """Wait for one of ``states`` (s of the rig's clock). DrumTimeout, DrumFault."""
        return self.__drum.wait_state(states, timeout_s)

    def wait_released(self, timeout_s: float, home_mm: float | None = None) -> DrumStatus:
        """Wait until the actuator has backed off (s of the rig's clock; ``home_mm``: the client's default). DrumTimeout,
        DrumFault."""
        if home_mm is None:
            return self.__drum.wait_released(timeout_s)
        return self.__drum.wait_released(timeout_s, home_mm)

    def wait_force_settled(self, timeout_s: float) -> DrumStatus:
        """Wait for FORCE_SETTLED (s of the rig's clock). DrumTimeout, DrumFault."""
        return self.__drum.wait_force_settled(timeout_s)

    def wait_speed_steady(self, timeout_s: float, tol_mm_s: float | None = None) -> DrumStatus:
        """Wait until the drum's speed is steady (s of the rig's clock; ``tol_mm_s``, mm/s: the client's default).
        DrumTimeout, DrumFault."""
        if tol_mm_s is None:
            return self.__drum.wait_speed_steady(timeout_s)
        return self.__drum.wait_speed_steady(timeout_s, tol_mm_s)
