"""``rigctl doctor``: bring-up checks on the connected rig, one line each with pass / fail / skip and the fix.

The library call behind the CLI (``rigctl doctor``) and the GUI's doctor dialog::

    from rigctl.acquisition import doctor
    ctx = doctor.DoctorContext("sim", opener=lambda: rigctl.rigs.open_rig("sim"))
    report = doctor.run_doctor(doctor.select(), ctx, on_result=print)
    doctor.save_report(report)            # dated, into the rig config's "doctor" block

Checks, in order (:data:`CHECKS`): the host side (:mod:`.host_checks`: port permissions, ModemManager, serial
numbers, both boards answer), the drum controller (:mod:`.drum_checks`: firmware version and build, reset cause,
HX711 rate, load-cell zero, scale and polarity, force step response, drum speed from the index) and the taxel
streamer (:mod:`.taxel_checks`: noise floor, crosstalk, the Uno's clock). The passive checks run first; the ones
that move the rig (``Check.moves``) after them, the rig stopped safely after each.
"""

from __future__ import annotations

from collections.abc import Iterable

from rigctl.acquisition.doctor import drum_checks, host_checks, taxel_checks
from rigctl.acquisition.doctor.base import (
    STATUSES,
    Check,
    CheckResult,
    DoctorContext,
    DoctorReport,
    Skip,
    last_report,
    run_doctor,
    save_report,
)

__all__ = ["CHECKS", "STATUSES", "Check", "CheckResult", "DoctorContext", "DoctorReport", "Skip", "check_names",
           "last_report", "run_doctor", "save_report", "select"]

_ALL = host_checks.CHECKS + drum_checks.CHECKS + taxel_checks.CHECKS
#: every check, passive ones first, then those that move the rig
CHECKS: tuple[Check, ...] = tuple(c for c in _ALL if not c.moves) + tuple(c for c in _ALL if c.moves)


def check_names() -> list[str]:
    """The checks' names, in the order they run."""
    return [c.name for c in CHECKS]


def select(names: Iterable[str] | None = None) -> list[Check]:
    """The checks named (in :data:`CHECKS` order), or all. Raises ValueError naming an unknown check."""
    if names is None:
        return list(CHECKS)
    wanted = list(names)
    unknown = [n for n in wanted if n not in check_names()]
    if unknown:
        raise ValueError(f"unknown check {unknown[0]!r}; the checks are {', '.join(check_names())}")
    return [c for c in CHECKS if c.name in wanted]
