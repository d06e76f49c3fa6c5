"""The ``rigctl`` console script's entry: :func:`main` imports the command line (:mod:`rigctl.cli`) and runs it.

A module of its own, outside the ``rigctl`` package: importing rigctl (numpy, h5py, the core) takes the first
seconds of every command, and a Ctrl-C then, before any of rigctl's code runs, ended in a traceback of whatever was
being imported. Here it ends in one line (exit 1, nothing done), as a Ctrl-C during a command's work does.
"""

from __future__ import annotations

import sys

__all__ = ["main"]


def main() -> None:
    """Run ``rigctl`` (:func:`rigctl.cli.main`); a Ctrl-C while it is imported is one line, exit status 1."""
    try:
        from rigctl.cli import main as cli, skip_exit_collections
        from rigctl.cli.interrupts import keep_ctrl_c
    except KeyboardInterrupt:
        sys.stderr.write("Error: interrupted (Ctrl-C) while rigctl was starting: nothing was done\n")
        raise SystemExit(1) from None
    skip_exit_collections()
    keep_ctrl_c()
    cli(prog_name="rigctl")
