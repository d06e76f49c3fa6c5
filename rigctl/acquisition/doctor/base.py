"""The doctor's framework: a check is a small function ``check(ctx) -> CheckResult``; :func:`run_doctor` runs them in
order on one :class:`DoctorContext` (which opens the rig when the first check needs it) and returns a dated
:class:`DoctorReport`.

A check reports ``pass``, ``fail`` (with the fix, in words) or ``skip`` (with why its data is not available: a
register this firmware does not have, a simulated board without a USB serial number, ...). A check never passes on
data it could not get: it raises :class:`Skip` instead.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as _dt
import math
import threading
from collections.abc import Callable, Iterable
from typing import Any

from rigctl.acquisition.rig import Rig
from rigctl.acquisition.rigconfig import load_rig_config, save_rig_config
from rigctl.core.drum import DrumError, DrumState
from rigctl.core.interfaces import TaxelSource
from rigctl.devices.drum import _WallClock

__all__ = ["CheckResult", "Check", "DoctorContext", "DoctorReport", "Skip", "STATUSES", "run_doctor", "save_report",
           "last_report"]

#: what a check can report
STATUSES = ("pass", "fail", "skip")


#: the start of a skip's summary when the rig could not be opened, and when the run was cancelled
NOT_OPENED = "the rig did not open"
CANCELLED = "cancelled"


class Skip(Exception):
    """Raised by a check whose data is not available; the message says why (becomes ``skip: <why>``)."""


@dataclasses.dataclass(frozen=True)
class CheckResult:
    """One check's outcome.

    Attributes
    ----------
    name : the check's name (``port-permissions``, ``loadcell-polarity``, ...)
    status : "pass" | "fail" | "skip"
    summary : one line: what was measured (with units) or why it was skipped
    fix : what to do about a failure (empty for pass and skip)
    values : the measured numbers (JSON scalars or lists), units in the keys
    """

    name: str
    status: str
    summary: str
    fix: str = ""
    values: dict[str, Any] = dataclasses.field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.status not in STATUSES:
            raise ValueError(f"check status must be one of {STATUSES}, got {self.status!r}")

    def line(self) -> str:
        """``PASS name: summary`` (``-> fix: ...`` on a failure), one line."""
        text = f"{self.status.upper():4}  {self.name}: {self.summary}"
        return f"{text} -> fix: {self.fix}" if self.fix else text

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"name": self.name, "status": self.status, "summary": self.summary}
        if self.fix:
            d["fix"] = self.fix
        if self.values:
            d["values"] = {k: _plain(v) for k, v in self.values.items()}
        return d


def _plain(v: Any) -> Any:
    """A JSON value of the rig config's kinds: numpy scalars as Python numbers, NaN/inf as null, tuples as lists."""
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if hasattr(v, "item") and not isinstance(v, (str, bytes)):
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def passed(name: str, summary: str, **values: Any) -> CheckResult:
    return CheckResult(name, "pass", summary, values=values)


def failed(name: str, summary: str, fix: str, **values: Any) -> CheckResult:
    return CheckResult(name, "fail", summary, fix=fix, values=values)


@dataclasses.dataclass(frozen=True)
class Check:
    """A named check: ``fn(ctx)`` returns a :class:`CheckResult` or raises :class:`Skip`; ``moves`` marks checks
    that move the drum or the actuator (run after the passive ones; the rig is stopped safely after each)."""

    name: str
    fn: Callable[["DoctorContext"], CheckResult]
    moves: bool = False
    title: str = ""


class DoctorContext:
    """What the checks share: the rig kind, its ports, the rig (opened on first use by ``opener``), the rig config
    path and measurements cached for several checks (e.g. one capture at rest for the noise floor, crosstalk and
    the Uno's clock).

    A rig the context opened streams taxel frames only while a check takes them (:meth:`taxel_stream`): its stream
    is stopped when it has opened and after each check, so the taxel board's UART and the host's frame parser idle
    through the checks that need no frames (most of them; on the firmware under simavr, ~2.5 of ~17 CPU-s). An open
    rig given as ``rig`` (the GUI's) keeps streaming as it was.

    Parameters
    ----------
    mode : "sim" | "hil" | "hardware" | "replay" | "inprocess"
    opener : ``opener() -> Rig`` (e.g. ``lambda: rigctl.rigs.open_rig(kind, ...)``); the context closes a rig it
        opened. Or ``rig``: an open rig (the GUI's), left open.
    drum_port, taxel_port : the boards' serial ports when known before opening (hardware); else taken from the
        opened rig's backend.
    config_path : the rig config file (default ``$RIGCTL_CONFIG`` / ``~/.config/rigctl/rig.json``).
    rest_s : duration of the taxel capture at rest, s (noise floor, crosstalk, Uno clock).
    place_mass : ``place_mass(g)`` returns once the operator has put ``g`` grams on the load cell (0: taken off), for
        the reference-mass check on hardware; None: a simulated rig's own (its backend's), else that check is skipped.
    """

    def __init__(self, mode: str, *, opener: Callable[[], Rig] | None = None, rig: Rig | None = None,
                 drum_port: str | None = None, taxel_port: str | None = None, config_path: Any = None,
                 rest_s: float = 10.0, place_mass: Callable[[float], Any] | None = None) -> None:
        if opener is None and rig is None:
            raise ValueError("DoctorContext needs an opener or an open rig")
        self.mode = mode
        self._opener = opener
        self._rig = rig
        self._owns_rig = False
        self.open_error: str | None = None
        self._ports = {k: v for k, v in (("drum", drum_port), ("taxel", taxel_port)) if v}
        self.config_path = config_path
        self.rest_s = float(rest_s)
        self.place_mass = place_mass
        self._stream_paused = False
        self.cache: dict[str, Any] = {}
        #: set it (from any thread) to stop: the running check ends as ``skip: cancelled`` at its next poll, the
        #: rig is stopped safely, the remaining checks are skipped
        self.cancel = threading.Event()

    def check_cancel(self) -> None:
        """Raise :class:`Skip` if :attr:`cancel` is set (the checks' polling loops call it)."""
        if self.cancel.is_set():
            raise Skip(CANCELLED)

    @property
    def simulated(self) -> bool:
        """True unless the rig is real hardware."""
        return self.mode != "hardware"

    def rig(self) -> Rig:
        """The open rig (opened on first use). Raises :class:`Skip` if it could not be opened."""
        if self._rig is None:
            if self.open_error is not None:
                raise Skip(f"{NOT_OPENED} ({self.open_error})")
            assert self._opener is not None
            try:
                self._rig = self._opener()
                self._owns_rig = True
                self.pause_stream()
            except Exception as exc:  # noqa: BLE001 - reported by the link check, skipped by the others
                self.open_error = " ".join(str(exc).split()) or type(exc).__name__
                raise Skip(f"{NOT_OPENED} ({self.open_error})") from exc
        return self._rig

    def taxel_stream(self) -> TaxelSource:
        """The rig's taxel stream, streaming (a stream :meth:`pause_stream` stopped is started again: its board
        restarts its sequence at 0, and the frames before the new stream's first are not taken). Raises
        :class:`Skip` if the rig could not be opened, ``TaxelStreamError`` if the stream cannot be started."""
        rig = self.rig()
        if self._stream_paused:
            self._stream_paused = False
            rig.stream.start()
        return rig.stream

    def pause_stream(self) -> None:
        """Stop the taxel stream of a rig this context opened until a check asks for frames (:meth:`taxel_stream`);
        nothing for an open rig given to the context, or none open. Never raises (a link error shows in the next
        check that takes frames)."""
        if self._rig is None or not self._owns_rig or self._stream_paused:
            return
        self._stream_paused = True
        with contextlib.suppress(Exception):
            self._rig.stream.stop()

    def ports(self) -> dict[str, str]:
        """``{"drum": path, "taxel": path}``: as given, else the opened rig backend's (``{}`` for a backend without
        serial ports, e.g. the in-process rig)."""
        if not self._ports:
            desc = self.rig().backend.describe()
            self._ports = {k[:-5]: str(v) for k, v in desc.items()
                           if k in ("drum_port", "taxel_port") and v and str(v).startswith("/")}
        return dict(self._ports)

    @property
    def clock(self) -> Any:
        """The drum client's clock (simulated on the in-process rig), else the host's monotonic clock."""
        return getattr(self.rig().drum, "clock", None) or _WallClock()

    def cached(self, key: str, fn: Callable[[], Any]) -> Any:
        """``fn()`` once per context (a failure is cached too and raised again)."""
        if key not in self.cache:
            try:
                self.cache[key] = ("ok", fn())
            except Exception as exc:  # noqa: BLE001 - re-raised to every check that needs it
                self.cache[key] = ("error", exc)
        kind, value = self.cache[key]
        if kind == "error":
            raise value
        return value

    def close(self) -> None:
        """Stop the rig safely and close it if this context opened it."""
        if self._rig is not None and self._owns_rig:
            with contextlib.suppress(Exception):
                self._rig.close()
            self._rig = None


@dataclasses.dataclass
class DoctorReport:
    """The doctor's results on one rig: ``checked_utc`` (ISO 8601), ``rig`` (the mode), ``results`` in order."""

    checked_utc: str
    rig: str
    results: list[CheckResult]

    @property
    def ok(self) -> bool:
        """No check failed (skipped checks do not count as failures; they are listed as such)."""
        return not any(r.status == "fail" for r in self.results)

    def counts(self) -> dict[str, int]:
        return {s: sum(r.status == s for r in self.results) for s in STATUSES}

    def not_run(self, *, named: bool) -> list[CheckResult]:
        """The checks that could not run. ``named``: the operator named the checks (``--check``): every skip of one
        is a check asked for and not done (the e-stop pressed, the port held by another face, the controller in
        FAULT). Otherwise (every check) a skip may only mean the check does not apply to this rig (no serial
        ports on a simulated rig), and those that could not run are the ones the rig's state prevented: the rig did
        not open, or the run was cancelled. A script's ``rigctl doctor && rigctl acquire`` must never read these
        as OK (``rigctl doctor`` exits 1)."""
        return [r for r in self.results if r.status == "skip"
                and (named or r.summary.startswith((NOT_OPENED, CANCELLED)))]

    def to_dict(self) -> dict[str, Any]:
        return {"checked_utc": self.checked_utc, "rig": self.rig, "ok": self.ok,
                "checks": [r.to_dict() for r in self.results]}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "DoctorReport":
        return cls(d["checked_utc"], d["rig"], [CheckResult(c["name"], c["status"], c["summary"], c.get("fix", ""),
                                                            dict(c.get("values", {}))) for c in d["checks"]])


def _run_one(check: Check, ctx: DoctorContext) -> CheckResult:
    try:
        if check.moves:
            _start(ctx)
        result = check.fn(ctx)
    except Skip as why:
        return CheckResult(check.name, "skip", str(why))
    except Exception as exc:  # noqa: BLE001 - a check that could not finish has not passed
        return CheckResult(check.name, "fail", f"the check could not finish: {' '.join(str(exc).split())}",
                           fix="see the message; rerun `rigctl doctor --check " + check.name + "`")
    finally:
        if check.moves and ctx._rig is not None:
            _make_safe(ctx)
        ctx.pause_stream()
    if result.name != check.name:
        result = dataclasses.replace(result, name=check.name)
    return result


def _start(ctx: DoctorContext) -> None:
    """A check that moves the rig is a start (opening moved nothing: docs/safety.md): HOME and TARE first when the
    rig has not homed since it opened or was acknowledged (:meth:`rigctl.acquisition.rig.Rig.home_if_pending`),
    unless a fault is latched. A HOME that fails (e.g. ACTUATOR_DIRECTION: its direction proof) is left for the
    check to report from the controller's state."""
    rig = ctx.rig()
    if not rig.home_pending or rig.safety.latch is not None:
        return
    with contextlib.suppress(DrumError):
        if rig.drum.read_status().state != DrumState.FAULT:
            rig.home_if_pending()


def _make_safe(ctx: DoctorContext) -> None:
    """After a check that moved the rig: STOP and wait for the actuator home (never raises)."""
    rig = ctx._rig
    assert rig is not None
    rig.safe_stop()
    with contextlib.suppress(Exception):
        rig.drum.wait_released(timeout_s=30.0)


def run_doctor(checks: Iterable[Check], ctx: DoctorContext, *,
               on_result: Callable[[CheckResult], Any] | None = None) -> DoctorReport:
    """Run ``checks`` in order on ``ctx``; ``on_result(result)`` after each (the CLI prints, the GUI shows it).

    The context's rig is stopped safely after each check that moves it and closed at the end if the context opened
    it. Never raises for a failing check (it is a ``fail`` line); returns the :class:`DoctorReport`.
    """
    stamp = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
    results = []
    try:
        for check in checks:
            result = CheckResult(check.name, "skip", "cancelled") if ctx.cancel.is_set() else _run_one(check, ctx)
            results.append(result)
            if on_result is not None:
                on_result(result)
    finally:
        ctx.close()
    return DoctorReport(stamp, ctx.mode, results)


def save_report(report: DoctorReport, path=None) -> None:
    """Store ``report`` in the rig config file (``doctor.<rig kind>``, dated), replacing that kind's previous one.

    Raises :class:`rigctl.acquisition.rigconfig.RigConfigError` (nothing written) if the file is not valid."""
    cfg = load_rig_config(path)
    block = dict(cfg.get("doctor") or {})
    block[report.rig] = report.to_dict()
    cfg["doctor"] = block
    save_rig_config(cfg, path)


def last_report(kind: str, path=None) -> DoctorReport | None:
    """The stored report of the rig ``kind`` ("hardware", "sim", ...), or None."""
    d = (load_rig_config(path).get("doctor") or {}).get(kind)
    return DoctorReport.from_dict(d) if d else None
