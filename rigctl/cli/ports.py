"""``rigctl ports``: list serial ports and which rig board each looks like (USB VID/PID)."""

from __future__ import annotations

import json

import click


@click.command()
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of a table.")
@click.option("--all", "include_all", is_flag=True, help="Also list ports without a USB id (e.g. /dev/ttyS*).")
def ports(as_json, include_all):
    """List serial ports with their USB id and a guess of the board: mega (drum controller) or uno (taxel
    streamer). The simulated rig's ports are printed by `rigctl sim`."""
    from rigctl.devices.ports import find_ports

    found = find_ports(include_all=include_all)
    if as_json:
        click.echo(json.dumps([p.to_dict() for p in found], indent=2))
        return
    if not found:
        click.echo("no USB serial ports found (the simulated rig's ports: run `rigctl sim`).")
        return
    rows = [("device", "vid:pid", "board", "description")]
    for p in found:
        vidpid = f"{p.vid:04x}:{p.pid:04x}" if p.vid is not None else "-"
        rows.append((p.device, vidpid, p.board or "?", f"{p.description} ({p.note})" if p.note else p.description))
    widths = [max(len(r[i]) for r in rows) for i in range(3)]
    for r in rows:
        click.echo("  ".join(c.ljust(w) for c, w in zip(r[:3], widths)) + "  " + r[3])
