"""``rigctl udev-rules``: print udev rules giving the rig's boards stable names by USB serial number."""

from __future__ import annotations

import click


def _checked_serial(ctx, param, value):
    """A serial number given on the command line that no udev rule can match is a usage error (exit 2, the option
    named), judged by the rule writer itself."""
    if value is not None:
        from rigctl.devices.ports import PortInfo, udev_rules

        board = "mega" if param.name == "drum_serial" else "uno"
        try:
            udev_rules([PortInfo(device="(not connected)", vid=None, pid=None, description="", board=board,
                                 serial_number=value)])
        except ValueError as exc:
            raise click.BadParameter(str(exc).removeprefix("(not connected): ")) from None
    return value


@click.command("udev-rules")
@click.option("--drum-serial", default=None, metavar="SERIAL", callback=_checked_serial,
              help="USB serial number of the drum controller (Mega); default: the connected board that looks like one.")
@click.option("--taxel-serial", default=None, metavar="SERIAL", callback=_checked_serial,
              help="USB serial number of the taxel streamer (Uno); default: the connected board that looks like one.")
def udev_rules(drum_serial, taxel_serial):
    """Print udev rules for the rig's boards: /dev/rigctl-drum and /dev/rigctl-taxel by USB serial number (ttyACM
    numbers change on replug; the boards cannot swap), the dialout group, and ENV{ID_MM_DEVICE_IGNORE}="1" so
    ModemManager leaves them alone. Redirect into /etc/udev/rules.d/99-rigctl.rules (docs/guides/real-rig.md).
    Clone boards (CH340) cannot be told apart by USB id: give --drum-serial and --taxel-serial (`rigctl ports`
    lists the serial numbers)."""
    from dataclasses import replace

    from rigctl.devices.ports import PortInfo, find_ports, udev_rules as rules

    found = find_ports()
    boards = []
    for role, serial in (("mega", drum_serial), ("uno", taxel_serial)):
        if serial is not None:
            hit = next((p for p in found if p.serial_number == serial), None)
            boards.append(replace(hit, board=role) if hit else PortInfo(
                device="(not connected)", vid=None, pid=None, description="", board=role, serial_number=serial))
        else:
            boards.extend(p for p in found if p.board == role)
    if not boards:
        raise click.ClickException("no rig board found: connect the boards, or give --drum-serial and "
                                   "--taxel-serial (`rigctl ports` lists the ports and serial numbers)")
    try:
        click.echo(rules(boards), nl=False)
    except ValueError as exc:
        raise click.ClickException(str(exc)) from None
