"""pylsl, loaded only when Lab Streaming Layer is asked for (the optional extra ``rigctl[lsl]``; its wheel ships
liblsl): :func:`require_pylsl` returns the module or raises :class:`LslUnavailable` naming the fix. Shared by the
outlets (:mod:`rigctl.acquisition.lsl`), the LSL replay source (:mod:`rigctl.simulation.lsl_replay`) and the handheld
rig's tracker inlet (:mod:`rigctl.simulation.handheld_lsl`).

Every inlet rigctl opens is :func:`open_inlet`'s: liblsl's clock sync on (``proc_clocksync``: each sample's stamp plus
the inlet's ``time_correction()``, re-measured as the stream goes), so a stream published from another PC's clock
(or another time namespace's) is read on this machine's LSL clock; :func:`time_correction_s` is the correction it
applies, recorded beside what the stream fed."""

from __future__ import annotations

import os
from typing import Any

__all__ = ["LslUnavailable", "require_pylsl", "LIBRARY_LOG_ENV", "open_inlet", "time_correction_s"]

#: set by the command line unless --verbose (rigctl.cli.logs: the log file's path): liblsl's terminal output is then
#: kept to its errors; unset, liblsl logs as its own configuration says (INFO lines on the terminal by default)
LIBRARY_LOG_ENV = "RIGCTL_LIBRARY_LOG"
_routed = False


class LslUnavailable(RuntimeError):
    """LSL streaming was asked for but pylsl (or its liblsl) cannot be loaded."""


def require_pylsl() -> Any:
    """The pylsl module; :class:`LslUnavailable` in one line naming the fix when it (or liblsl) is missing."""
    try:
        import pylsl
    except (ImportError, RuntimeError, OSError) as exc:
        raise LslUnavailable(f"LSL streaming needs pylsl with its liblsl: pip install 'rigctl[lsl]' ({exc})") from None
    _route_liblsl_log(pylsl)
    return pylsl


def open_inlet(pylsl: Any, info: Any, *, max_buflen: int = 60) -> Any:
    """A ``pylsl.StreamInlet`` on the stream ``info`` (a resolved ``StreamInfo``) whose samples' stamps are on this
    machine's LSL clock: liblsl's clock sync (``processing_flags=proc_clocksync``; module docstring), recovering a
    lost stream, buffering ``max_buflen`` s."""
    return pylsl.StreamInlet(info, max_buflen=max_buflen, recover=True, processing_flags=pylsl.proc_clocksync)


def time_correction_s(inlet: Any, timeout_s: float = 2.0) -> float:
    """The inlet's clock correction, s: the publisher's LSL clock minus this machine's as liblsl measures it (about 0
    on one machine; -3600 for a publisher whose clock runs an hour ahead), the amount the clock sync adds to every
    stamp; NaN when it cannot be measured within ``timeout_s`` (a lost stream)."""
    try:
        return float(inlet.time_correction(timeout=timeout_s))
    except Exception:  # noqa: BLE001 - liblsl's timeout or lost stream: not measured
        return float("nan")


def _liblsl_config_text() -> str:
    """The configuration liblsl would read: ``$LSLAPICFG``, else ``~/lsl_api/lsl_api.cfg``, else
    ``/etc/lsl_api/lsl_api.cfg`` (liblsl's own order), "" when none can be read (at most 1 MiB)."""
    candidates = [os.environ.get("LSLAPICFG"), os.path.expanduser("~/lsl_api/lsl_api.cfg"), "/etc/lsl_api/lsl_api.cfg"]
    for name in candidates:
        if name and os.path.isfile(name):
            try:
                with open(name, encoding="utf-8", errors="replace") as fh:
                    return fh.read(1 << 20)
            except OSError:
                return ""
    return ""


def _route_liblsl_log(pylsl: Any) -> None:
    """Once, before liblsl is first used: liblsl's terminal output (its INFO lines by default) kept to its errors,
    the rest of its configuration as liblsl would read it (``pylsl.set_config_content`` replaces every
    configuration file). liblsl cannot be given a log file without announcing it on the terminal (loguru's "Logging
    to ..." line, whatever the level), so its records below error level are not kept. Nothing when
    ``$RIGCTL_LIBRARY_LOG`` is unset (``rigctl --verbose``, or rigctl used as a library) or pylsl cannot set it."""
    global _routed
    log = os.environ.get(LIBRARY_LOG_ENV)
    if _routed or not log:
        return
    _routed = True
    import configparser
    import io

    parser = configparser.ConfigParser(interpolation=None, strict=False)
    parser.optionxform = str  # type: ignore[assignment,method-assign]  # liblsl's keys keep their case
    try:
        parser.read_string(_liblsl_config_text())
    except configparser.Error:
        return  # a configuration liblsl may read its own way: left alone
    if not parser.has_section("log"):
        parser.add_section("log")
    parser.set("log", "level", "-2")
    text = io.StringIO()
    parser.write(text)
    try:
        pylsl.set_config_content(text.getvalue())
    except (AttributeError, NotImplementedError, OSError):
        pass
