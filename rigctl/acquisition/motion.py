"""Drum-controller moves shared by the rig facade and the calibration (which import this module, not each other)."""

from __future__ import annotations

from rigctl.core.interfaces import DrumController

__all__ = ["wait_released"]


def wait_released(drum: DrumController, *, timeout_s: float = 20.0, home_mm: float = 0.05) -> None:
    """Send STOP and wait until the controller is IDLE with the actuator within ``home_mm`` of home.

    STOP sets IDLE at once while the actuator is still backing off; TARE and plate changes need it home.
    Raises :class:`rigctl.devices.errors.DrumTimeout` / ``DrumFault``.
    """
    drum.stop()
    drum.wait_released(timeout_s=timeout_s, home_mm=home_mm)
