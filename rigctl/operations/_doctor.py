"""The doctor as an operator runs it: :func:`doctor` on a :class:`RigSource` (the CLI's ``rigctl doctor``) or on
an open :class:`RigControl` (the GUI's doctor dialog), the report stored in the rig config. The checks themselves
are :mod:`rigctl.acquisition.doctor`'s."""

from __future__ import annotations

import dataclasses
import os
import threading
from collections.abc import Callable, Iterable
from typing import Any

from rigctl.acquisition import doctor as _doctor
from rigctl.operations._control import Home, RigControl, open_control, rig_of
from rigctl.operations._source import RigSource

__all__ = ["doctor"]


def doctor(source: RigSource | None = None, *, control: RigControl | None = None,
           checks: Iterable[str] | None = None, host_config_path: str | os.PathLike | None = None,
           seed: int = 0, config: Any = None, rest_s: float = 10.0, save: bool = True,
           on_result: Callable[[_doctor.CheckResult], Any] | None = None,
           cancel: threading.Event | None = None,
           acknowledge: tuple[str, str] | None = None,
           place_mass: Callable[[float], Any] | None = None) -> _doctor.DoctorReport:
    """Run the doctor's checks (all, or those named in ``checks``) and store the dated report.

    Parameters
    ----------
    source : the rig to open (default the simulated rig); opened when the first check needs it (after the port
        checks on hardware, so a port without permission is reported as such), homed unless a fault is latched (the
        fault is then reported, never cleared behind the operator's back), and closed at the end.
    control : an open rig instead (the GUI's), left open; the checks that move it stop it safely after each.
    checks : check names (:func:`rigctl.acquisition.doctor.check_names`); ValueError for an unknown one.
    host_config_path : the rig config file the report is stored in (default ``$RIGCTL_CONFIG`` /
        ``~/.config/rigctl/rig.json``).
    seed, config : the simulated rig's seed and model configuration (simulated kinds).
    rest_s : length of the taxel capture at rest, s.
    save : store the report in the rig config (``doctor.<rig kind>``).
    on_result : called with each :class:`rigctl.acquisition.doctor.CheckResult` as it is known.
    cancel : set it (from any thread) to end the run early: the running check stops at its next poll (the rig is
        stopped safely), the rest are reported as ``skip: cancelled``.
    acknowledge : ``(reason, by)``: the operator acknowledges at open a fault the controller latches (``rigctl
        doctor --ack``; :func:`rigctl.operations.open_control`); without it such a fault is kept and reported.
    place_mass : ``place_mass(g)`` returns once the operator has put ``g`` grams on the load cell (0: off): the
        reference-mass check on hardware (a simulated rig places it itself); None: that check skips on hardware.

    Returns
    -------
    :class:`rigctl.acquisition.doctor.DoctorReport` (``ok`` False when a check failed).

    Raises
    ------
    ValueError for an unknown check name; :class:`rigctl.acquisition.rigconfig.RigConfigError` when the report
    cannot be stored (an invalid rig config file).
    """
    selected = _doctor.select(checks)
    if control is not None:
        ctx = _doctor.DoctorContext(control.mode, rig=rig_of(control), config_path=host_config_path, rest_s=rest_s,
                                    place_mass=place_mass)
    else:
        # the doctor reports a firmware build mismatch as its firmware-build check, so it opens the boards anyway
        source = dataclasses.replace(source or RigSource(), allow_firmware_mismatch=True)

        def opener():
            control = open_control(source, home=Home.UNLESS_FAULTED, config=config, seed=seed,
                                   host_config_path=host_config_path, acknowledge=acknowledge)
            return rig_of(control)

        ctx = _doctor.DoctorContext(source.kind, opener=opener, drum_port=source.drum_port,
                                    taxel_port=source.taxel_port, config_path=host_config_path, rest_s=rest_s,
                                    place_mass=place_mass)
    if cancel is not None:
        ctx.cancel = cancel
    report = _doctor.run_doctor(selected, ctx, on_result=on_result)
    if save:
        _doctor.save_report(report, host_config_path)
    return report
