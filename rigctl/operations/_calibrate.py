"""Calibrating an open rig, as the operator does it from the CLI or the GUI: the load cell with a known mass, and the
per-taxel normalisation from a live capture or a calibration session, checked, stored (the previous one kept for
Undo) and taken up by the rig at once (later sessions carry it).

The steps are :mod:`rigctl.acquisition.calibration`'s; this module strings them together around a
:class:`rigctl.operations.RigControl` so that no face repeats them.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from rigctl.acquisition import calibration as cal
from rigctl.acquisition.rigconfig import load_rig_config
from rigctl.core.normalisation import TaxelRange
from rigctl.core.sensor import SensorLayout
from rigctl.operations._control import RigControl, rig_of

__all__ = ["calibrate_loadcell", "record_taxel_normalisation", "store_taxel_normalisation", "StoredNormalisation"]

ConfigPath = str | os.PathLike[str] | None


def calibrate_loadcell(control: RigControl, mass_g: float, *, place_mass: Callable[[float], Any] | None = None,
                       remove_mass: Callable[[float], Any] | None = None,
                       config_file: ConfigPath = None) -> cal.LoadCellCalibration:
    """Calibrate the load cell of ``control``'s rig with a known ``mass_g`` (g) and store the result in the rig
    config (:func:`rigctl.acquisition.calibration.calibrate_loadcell`); the rig takes the new config up at once.

    ``place_mass`` / ``remove_mass`` return once the operator has put the mass on / taken it off; without them, a
    simulated rig rests the mass itself (CalibrationError on hardware). A start: a rig not homed since it opened (or
    was acknowledged) HOMEs and TAREs first (opening moves nothing). Raises ValueError, CalibrationError,
    LatchedFault, DrumError."""
    rig = rig_of(control)
    with rig.latching("calibration"):
        rig.home_if_pending()
    if place_mass is None:
        place_mass, remove_mass = cal.simulated_mass(rig_of(control))
    result = cal.calibrate_loadcell(rig.drum, mass_g, place_mass=place_mass, remove_mass=remove_mass,
                                    config_file=config_file)
    control.host_config = load_rig_config(config_file)
    return result


@dataclass(frozen=True)
class StoredNormalisation:
    """A taxel normalisation that was checked and stored: ``norm`` and the taxels whose span was small
    (``low_taxels``: reported, not refused)."""

    norm: TaxelRange
    low_taxels: list[int]


def store_taxel_normalisation(norm: TaxelRange, layout: SensorLayout, *, config_file: ConfigPath = None,
                              control: RigControl | None = None) -> StoredNormalisation:
    """Store ``norm`` as the rig config's taxel normalisation unless its span is implausibly small for ``layout``'s
    ADC (:func:`rigctl.acquisition.calibration.check_taxel_span` raises CalibrationError: the previous one stays in
    use); the one it replaces is kept for Undo; ``control``'s rig takes it up at once."""
    low = cal.check_taxel_span(norm, layout.adc_max)
    cal.store_taxel_normalisation(norm, config_file)
    if control is not None:
        control.host_config = load_rig_config(config_file)
    return StoredNormalisation(norm, low)


def record_taxel_normalisation(control: RigControl, seconds: float, *, config_file: ConfigPath = None,
                               cancel: threading.Event | None = None,
                               progress: Callable[[float], Any] | None = None) -> StoredNormalisation:
    """Capture ``seconds`` s of the live taxel stream (the operator runs the drum over the textures meanwhile),
    take each taxel's minimum and maximum, check and store them (:func:`store_taxel_normalisation`).

    The capture runs on the rig's clock (wall time; simulated time in-process). ``cancel`` ends it early;
    ``progress(fraction)`` is called about every 0.1 s. Raises CalibrationError (nothing stored), ValueError (no
    frames)."""
    clock = control.drum.clock
    taxels = control.taxels
    taxels.begin_capture()
    t0 = clock.now()
    try:
        while clock.now() - t0 < seconds and not (cancel is not None and cancel.is_set()):
            if progress is not None:
                progress(min(1.0, (clock.now() - t0) / seconds))
            clock.sleep(0.1)
    finally:
        cap = taxels.end_capture()
    norm = cal.taxel_normalisation([cap.samples], source=f"live capture {seconds:g} s")
    return store_taxel_normalisation(norm, control.layout, config_file=config_file, control=control)
