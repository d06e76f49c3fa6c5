"""``rigctl protocols``: the built-in protocols, and the click type that takes a protocol path or a built-in name."""

from __future__ import annotations

from pathlib import Path

import click


class ProtocolArg(click.ParamType):
    """A protocol file, or the name of a built-in protocol (``quick_check``): converts to the file's Path."""

    name = "protocol"

    def convert(self, value, param, ctx):
        from rigctl.acquisition.builtin import find_protocol

        if isinstance(value, Path) and value.is_file():
            return value
        try:
            return find_protocol(value)
        except FileNotFoundError as exc:
            self.fail(str(exc), param, ctx)

    def shell_complete(self, ctx: click.Context, param: click.Parameter,
                       incomplete: str) -> list[click.shell_completion.CompletionItem]:
        """The built-in protocols' names that start with ``incomplete``, and the shell's own file completion (a
        protocol file of the user's)."""
        from click.shell_completion import CompletionItem

        from rigctl.acquisition.builtin import builtin_protocols, summary

        names = [CompletionItem(n, help=summary(p)) for n, p in builtin_protocols().items() if n.startswith(incomplete)]
        return [*names, CompletionItem(incomplete, type="file")]


PROTOCOL = ProtocolArg()


@click.command("protocols")
@click.option("--path", "show_path", is_flag=True, help="Show where each file is.")
def protocols(show_path):
    """List the built-in protocols (run one by name: ``rigctl acquire quick_check --sim --out q.h5``)."""
    from rigctl.acquisition.builtin import builtin_protocols, summary

    items = builtin_protocols()
    if not items:
        raise click.ClickException("no built-in protocols found in this installation")
    width = max(len(n) for n in items) + 2
    for name, path in items.items():
        click.echo(f"{name:<{width}}{summary(path)}" + (f"  [{path}]" if show_path else ""))
