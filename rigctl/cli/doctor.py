"""``rigctl doctor``: bring-up checks on the connected rig (a thin face over :mod:`rigctl.acquisition.doctor`)."""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import click

from rigctl.cli.ranges import SEED, floats
from rigctl.cli.rig_flags import (
    acknowledgement,
    ask_operator_mass,
    check_config,
    check_rig_face_flags,
    check_truth_log,
    drum_port_option,
    hil_bootloaders_option,
    hx711_rate_option,
    inject_option,
    inprocess_option,
    taxel_port_option,
    truth_log_option,
)


@click.command("doctor")
@click.option("--sim", "sim", is_flag=True, default=False, help="Check the simulated rig (the default).")
@click.option("--hil", is_flag=True, default=False, help="Check the real firmware under simavr.")
@hil_bootloaders_option
@inprocess_option
@drum_port_option
@taxel_port_option
@click.option("--check", "checks", multiple=True, metavar="NAME",
              help="Run only this check (repeatable); --list shows the names.")
@click.option("--list", "list_checks", is_flag=True, default=False, help="List the checks and exit.")
@click.option("--json", "as_json", is_flag=True, default=False, help="Print the report as JSON.")
@click.option("--config", "config_path", type=click.Path(dir_okay=False, writable=True, path_type=Path), default=None,
              help="Rig config file (default $RIGCTL_CONFIG or ~/.config/rigctl/rig.json); --save stores the report in it.")
@click.option("--save/--no-save", default=False, show_default=True,
              help="Store the report, dated, in the rig config (doctor.<rig kind>); without it nothing is written.")
@click.option("--rest-s", type=floats(2.0, 120.0), default=10.0, show_default=True,
              help="Length of the taxel capture at rest (noise floor, crosstalk, Uno clock), s.")
@click.option("--seed", type=SEED, default=0, show_default=True, help="Seed of the simulated rig.")
@click.option("--ack", "ack", metavar="REASON", default=None,
              help="Acknowledge a fault the drum controller still latches when the rig opens (its cause gone), "
                   "logged with your login name and REASON; without it the fault is kept and reported "
                   "(controller-faults fails, the checks that move skip).")
@inject_option
@hx711_rate_option
@truth_log_option
def doctor(sim, hil, hil_bootloaders, inprocess, drum_port, taxel_port, checks, list_checks, as_json, config_path, save,
           rest_s, seed, ack, inject, hx711_rate, truth_log):
    """Bring-up checks on the rig, one line each: PASS, FAIL with the fix, or SKIP with why its data is not
    available. Checks that move the rig (load-cell polarity, force step, drum speed) run last; the rig is stopped
    after each. With --save the report is stored, dated, in the rig config (doctor.<rig kind>). Opening never
    acknowledges a latched fault: it is reported (--ack REASON acknowledges it). Exit status 1 if a check failed or
    could not run (a --check skipped, or the rig did not open).
    """
    from rigctl.acquisition import doctor as doc

    if list_checks:
        for c in doc.CHECKS:
            click.echo(f"{c.name:18} {c.title}{' (moves the rig)' if c.moves else ''}")
        return
    hil = hil or hil_bootloaders
    check_rig_face_flags(ack=ack, sim=sim, hil=hil, inprocess=inprocess, drum_port=drum_port, taxel_port=taxel_port)
    from rigctl.operations import RigSource, doctor as run

    check_config(config_path, save)

    if checks:
        try:
            doc.select(checks)
        except ValueError as exc:
            raise click.BadParameter(str(exc), param_hint="--check") from None
    source = RigSource.from_flags(hil=hil, drum_port=drum_port, taxel_port=taxel_port, bootloaders=hil_bootloaders,
                                  inprocess=inprocess, inject=inject)
    check_truth_log(truth_log, source.kind)
    if truth_log is not None:
        source = dataclasses.replace(source, truth_log=str(truth_log))
    if hx711_rate is not None:
        try:
            source = dataclasses.replace(source, hx711_rate_sps=hx711_rate)
        except ValueError as exc:  # not a simulated HX711
            raise click.UsageError(str(exc)) from None
    why = source.injection_refusal()
    if why:
        raise click.UsageError(why)
    acknowledge = acknowledgement(ack)
    lines = _SkipFolder(click.echo)
    # on hardware the operator puts the reference mass on the cell when asked (a terminal only: a script skips it)
    place_mass = ask_operator_mass if source.kind == "hardware" and sys.stdin.isatty() else None
    report = run(source, checks=checks or None, host_config_path=config_path, seed=seed, rest_s=rest_s,
                 save=save, on_result=None if as_json else lines.add, acknowledge=acknowledge, place_mass=place_mass)
    lines.flush()
    if as_json:
        click.echo(json.dumps(report.to_dict(), indent=2))
    else:
        n = report.counts()
        click.echo(f"{source.kind} rig: {n['pass']} passed, {n['fail']} failed, {n['skip']} skipped"
                   + (" (stored in the rig config)" if save else ""))
    not_run = report.not_run(named=bool(checks))
    if not_run:  # a check asked for that could not run is not a pass (`doctor && acquire` scripts)
        click.echo(f"not checked: {', '.join(r.name for r in not_run)} could not run (exit 1)", err=True)
    if not report.ok or not_run:
        raise SystemExit(1)


class _SkipFolder:
    """Prints the checks' lines as they come, except that consecutive skips for one reason become one line
    (``SKIP  a, b, c (3 checks): <reason>``): a rig that did not open skipped 16 checks with 16 copies of its reason."""

    def __init__(self, echo) -> None:
        self.echo = echo
        self.skips: list = []

    def add(self, result) -> None:
        if result.status == "skip" and (not self.skips or self.skips[-1].summary == result.summary):
            self.skips.append(result)
            return
        self.flush()
        if result.status == "skip":
            self.skips.append(result)
        else:
            self.echo(result.line())

    def flush(self) -> None:
        if len(self.skips) == 1:
            self.echo(self.skips[0].line())
        elif self.skips:
            names = ", ".join(r.name for r in self.skips)
            self.echo(f"SKIP  {names} ({len(self.skips)} checks): {self.skips[0].summary}")
        self.skips = []
