"""``rigctl rigs``: the installed rigs (the entry points of the group ``rigctl.rigs``), whether each loads."""

from __future__ import annotations

import json

import click


@click.command("rigs")
@click.option("--json", "as_json", is_flag=True, default=False, help="Print the list as JSON.")
def rigs(as_json: bool) -> None:
    """List the installed rigs: name, the distribution that registers it, what it is, and whether its plugin loads
    (a broken one with its error, in one line). Open one with `rigctl acquire PROTOCOL --rig NAME` (options:
    --rig-option KEY=VALUE); docs/guides/my-hardware.md writes one. Exit status 0 (a broken plugin is listed, not an
    error of this command)."""
    from rigctl.core.rig_plugins import describe_rigs

    infos = describe_rigs()
    if as_json:
        click.echo(json.dumps([{"name": i.name, "distribution": i.distribution, "version": i.version,
                                "entry_point": i.target, "description": i.description, "loads": i.error is None,
                                "error": i.error, "builtin": i.builtin} for i in infos], indent=2))
        return
    width = max((len(i.name) for i in infos), default=4)
    dist_width = max((len(f"{i.distribution} {i.version}".strip()) for i in infos), default=4)
    for i in infos:
        dist = f"{i.distribution} {i.version}".strip()
        what = i.description if i.error is None else f"BROKEN: {i.error}"
        click.echo(f"{i.name:<{width}}  {dist:<{dist_width}}  {what}")
