"""The flags that choose the rig, shared by ``rigctl acquire`` and ``rigctl doctor``: one definition (and help text)
of each option they both take, and the check that the flags name one rig (a usage error, exit 2, before anything
opens)."""

from __future__ import annotations

import click

__all__ = ["hil_bootloaders_option", "inprocess_option", "drum_port_option", "taxel_port_option", "check_one_rig"]

hil_bootloaders_option = click.option(
    "--hil-bootloaders", is_flag=True, default=False,
    help="As --hil, with the boards' real bootloaders (stk500v2, optiboot) under simavr: opening a port resets its "
         "board as a real one's auto-reset does, and the host waits the boot window out.")
inprocess_option = click.option(
    "--inprocess", is_flag=True, default=False,
    help="Use the in-process simulated rig: the model and controller logic of --sim without ports or threads, on a "
         "simulated clock (a dry run in a fraction of the real time; no wire is exercised).")
drum_port_option = click.option("--drum-port", default=None,
                                help="Serial port of the drum controller (Mega) on real hardware.")
taxel_port_option = click.option("--taxel-port", default=None,
                                 help="Serial port of the taxel streamer (Uno) on real hardware.")


def check_one_rig(*, sim: bool, hil: bool, inprocess: bool, drum_port: str | None) -> None:
    """Raise click.UsageError when the flags name more than one rig: the hardware ports beside a simulated rig, or
    more than one of ``--sim``, ``--hil`` (``--hil-bootloaders``) and ``--inprocess``."""
    if drum_port is not None and (sim or hil or inprocess):
        raise click.UsageError("--drum-port/--taxel-port select the hardware rig: drop --sim/--hil/--inprocess")
    if sim + hil + inprocess > 1:
        raise click.UsageError("choose one of --sim, --hil and --inprocess")
