"""``rigctl safety``: the host's safety rules as a safety officer reads them."""

from __future__ import annotations

import click


@click.group()
def safety() -> None:
    """The host's safety rules: one table of events, states and actions (docs/safety.md)."""


@safety.command("table")
def table() -> None:
    """Print the host's safety table as markdown: every event a face sends, when it is allowed (anything else is
    refused), the state after and the actions. docs/safety.md holds it verbatim."""
    from rigctl.operations import safety_table_markdown

    click.echo(safety_table_markdown(), nl=False)
