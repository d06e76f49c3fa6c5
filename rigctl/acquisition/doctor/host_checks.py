"""Doctor checks of the host side of the links: port permissions (the ``dialout`` group), ModemManager, the boards
found by USB serial number, and whether the rig's boards answer at all.

Sources: the ``dialout`` group and ModemManager's probing of new ``ttyACM`` devices (unless udev sets
``ENV{ID_MM_DEVICE_IGNORE}="1"``) are in /work/shared/notes/bench-facts.md ("Linux"); ports and serial numbers come
from pyserial's ``list_ports`` (:func:`rigctl.devices.ports.find_ports`).
"""

from __future__ import annotations

import glob
import grp
import os
import pwd
from pathlib import Path

from rigctl.acquisition.doctor.base import Check, CheckResult, DoctorContext, Skip, failed, passed
from rigctl.devices import ports as _ports
from rigctl.devices.ports import find_ports

#: a port named by its board's USB serial number (rigctl.devices.ports.resolve_port)
SERIAL_PREFIX = getattr(_ports, "SERIAL_PREFIX", "serial:")


def resolve(port: str) -> str:
    """The device path of ``port`` (``serial:<number>`` looked up among the connected ports). OSError when no
    connected port has that serial number."""
    resolver = getattr(_ports, "resolve_port", None)
    if resolver is None or not port.startswith(SERIAL_PREFIX):
        return port
    return str(resolver(port))

__all__ = ["CHECKS", "check_port_permissions", "check_modemmanager", "check_serial_numbers", "check_link"]

#: folders holding udev rules (a rule setting ID_MM_DEVICE_IGNORE keeps ModemManager off the boards)
UDEV_RULE_DIRS = ("/etc/udev/rules.d", "/run/udev/rules.d", "/usr/lib/udev/rules.d", "/lib/udev/rules.d")


def _user_groups(user: str) -> set[str]:
    """Groups ``user`` belongs to in the group database (may differ from the running process's, until the next
    login)."""
    names = {g.gr_name for g in grp.getgrall() if user in g.gr_mem}
    try:
        names.add(grp.getgrgid(pwd.getpwnam(user).pw_gid).gr_name)
    except KeyError:
        pass
    return names


def port_access_problem(path: str) -> tuple[str, str] | None:
    """Why this process cannot read and write the serial port ``path``, as ``(problem, fix)``, or None if it can.

    Uses ``os.access`` (the kernel's answer for this process's user and groups) and names the device's group and
    whether the user is already in it (then only a new login is missing).
    """
    try:
        p = Path(resolve(path))
    except OSError as exc:
        return str(exc), "plug the board in; `rigctl ports` lists the serial ports with their serial numbers"
    if not p.exists():
        return f"{path} does not exist", "plug the board in; `rigctl ports` lists the serial ports"
    if os.access(p, os.R_OK | os.W_OK):
        return None
    st = p.stat()
    try:
        group = grp.getgrgid(st.st_gid).gr_name
    except KeyError:
        group = str(st.st_gid)
    try:
        user = pwd.getpwuid(os.getuid()).pw_name
    except KeyError:
        user = str(os.getuid())
    mode = f"{st.st_mode & 0o777:03o}"
    if group in _user_groups(user) and st.st_mode & 0o060 == 0o060:
        return (f"{path} (group {group}, mode {mode}): {user} is in {group} but this login is not yet",
                f"log out and in again (or run `newgrp {group}`)")
    return (f"{path} (group {group}, mode {mode}) is not readable and writable by {user}",
            f"sudo usermod -aG {group} {user}, then log out and in again")


def check_port_permissions(ctx: DoctorContext) -> CheckResult:
    ports = ctx.ports()
    if not ports:
        raise Skip(f"the {ctx.mode} rig has no serial ports")
    problems = [(role, port_access_problem(path)) for role, path in ports.items()]
    bad = [(role, pf) for role, pf in problems if pf is not None]
    if bad:
        role, (problem, fix) = bad[0]
        more = f" (and {len(bad) - 1} more)" if len(bad) > 1 else ""
        return failed("port-permissions", f"{role} port {problem}{more}", fix,
                      ports_without_access=[ports[r] for r, _ in bad])
    return passed("port-permissions", "read/write on " + ", ".join(f"{r} {p}" for r, p in ports.items()))


def _modemmanager_running() -> bool:
    for comm in glob.glob("/proc/[0-9]*/comm"):
        try:
            if Path(comm).read_text().strip() == "ModemManager":
                return True
        except OSError:
            continue
    return False


def _mm_ignore_rules() -> list[str]:
    """udev rule files that set ``ID_MM_DEVICE_IGNORE``."""
    found = []
    for d in UDEV_RULE_DIRS:
        for f in sorted(glob.glob(os.path.join(d, "*.rules"))):
            try:
                if "ID_MM_DEVICE_IGNORE" in Path(f).read_text(errors="replace"):
                    found.append(f)
            except OSError:
                continue
    return found


def check_modemmanager(ctx: DoctorContext) -> CheckResult:
    if ctx.simulated:
        raise Skip("simulated boards are ptys, which ModemManager does not probe (it probes USB ttyACM devices)")
    if not _modemmanager_running():
        return passed("modemmanager", "ModemManager is not running", running=False)
    rules = _mm_ignore_rules()
    if rules:
        return passed("modemmanager", f"ModemManager runs but udev tells it to ignore devices ({rules[0]})",
                      running=True, rule_files=rules)
    return failed("modemmanager", "ModemManager is running and no udev rule sets ID_MM_DEVICE_IGNORE: it probes "
                  "the boards' ttyACM ports (bytes into the Mega's bootloader, a port busy for seconds)",
                  "install the rig's udev rules (rigctl udev-rules > 99-rigctl.rules; they set "
                  "ENV{ID_MM_DEVICE_IGNORE}=\"1\"), or sudo systemctl disable --now ModemManager", running=True)


def check_serial_numbers(ctx: DoctorContext) -> CheckResult:
    if ctx.simulated:
        raise Skip("simulated boards on ptys have no USB serial number")
    ports = ctx.ports()
    infos = {os.path.realpath(i.device): i for i in find_ports()}
    lines, problems = [], []
    values: dict[str, object] = {}
    for role, path in ports.items():
        try:
            info = infos.get(os.path.realpath(resolve(path)))
        except OSError as exc:
            problems.append((str(exc), "plug the board in; `rigctl ports` lists the serial numbers"))
            continue
        if info is None:
            problems.append((f"{role} port {path} is not a USB serial port of this machine",
                             "plug the board in; `rigctl ports` lists the candidates"))
            continue
        values[f"{role}_serial_number"] = info.serial_number
        expected = "mega" if role == "drum" else "uno"
        if info.board is not None and info.board != expected:
            problems.append((f"{role} port {path} is an {info.description} (expected the {expected})",
                             "swap --drum-port and --taxel-port"))
        if not info.serial_number:
            problems.append((f"{role} port {path} ({info.description}) reports no USB serial number: its ttyACM/"
                             f"ttyUSB name can change on replug and the boards can swap", "name the port by its USB "
                             "path (/dev/serial/by-path/...) or use a board whose USB bridge has a serial number "
                             "(genuine 16U2); with one, `rigctl udev-rules` gives stable names"))
        else:
            lines.append(f"{role} {info.serial_number}")
    if problems:
        problem, fix = problems[0]
        return failed("serial-numbers", problem, fix, **values)
    sn = [v for k, v in values.items() if k.endswith("serial_number")]
    if len(set(sn)) != len(sn):
        return failed("serial-numbers", "both ports report the same serial number", "check the ports", **values)
    return passed("serial-numbers", ", ".join(lines), **values)


def check_link(ctx: DoctorContext) -> CheckResult:
    try:
        rig = ctx.rig()
    except Skip:
        return failed("link", f"cannot open the {ctx.mode} rig: {ctx.open_error}",
                      "check the cables and ports (`rigctl ports`), and the lines above")
    st = rig.drum.read_status()
    banner = getattr(rig.stream, "banner", None) or {}
    fw = banner.get("firmware")
    lay = rig.layout
    return passed("link", f"drum controller fw {st.firmware[0]}.{st.firmware[1]} state {st.state.name}; taxel "
                  f"streamer fw {fw[0] if fw else '?'}.{fw[1] if fw else '?'}, {lay.n_channels} channels at "
                  f"{lay.sample_rate_hz:g} Hz", mega_firmware=list(st.firmware),
                  uno_firmware=list(fw) if fw else None)


CHECKS = (
    Check("port-permissions", check_port_permissions, title="serial port permissions (dialout)"),
    Check("modemmanager", check_modemmanager, title="ModemManager keeps off the boards"),
    Check("serial-numbers", check_serial_numbers, title="boards found by USB serial number"),
    Check("link", check_link, title="both boards answer"),
)
