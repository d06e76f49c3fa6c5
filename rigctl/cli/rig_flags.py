"""The flags that choose the rig, shared by ``rigctl acquire`` and ``rigctl doctor``: one definition (and help text)
of each option they both take, and the check that the flags name one rig (a usage error, exit 2, before anything
opens)."""

from __future__ import annotations

from pathlib import Path

import click

from rigctl.cli.ranges import LSL_WAIT_S
from rigctl.core.faults import FAULTS, FaultSpec, FaultSpecError, parse_fault
from rigctl.core.rig_plugins import rig_names

__all__ = ["allow_firmware_mismatch_option", "truth_log_option", "hx711_rate_option",
           "hil_bootloaders_option", "inprocess_option", "drum_port_option", "taxel_port_option", "inject_option",
           "lsl_wait_option", "check_one_rig", "check_truth_log", "parse_injections", "FAULT_FORMS", "RIG", "rig_option",
           "rig_options_option", "check_rig_flags"]


class RigName(click.ParamType):
    """``--rig NAME``: an installed rig (the entry points of the group ``rigctl.rigs``; no plugin is imported to
    check the name: a broken one fails when it opens, in one line)."""

    name = "NAME"

    def convert(self, value: object, param: click.Parameter | None, ctx: click.Context | None) -> str:
        text = str(value)
        names = rig_names()
        if text not in names:
            self.fail(f"{text!r} is no installed rig: one of {', '.join(names)} (`rigctl rigs` lists them)", param,
                      ctx)
        return text

    def shell_complete(self, ctx: click.Context, param: click.Parameter,
                       incomplete: str) -> list[click.shell_completion.CompletionItem]:
        return [click.shell_completion.CompletionItem(n) for n in rig_names() if n.startswith(incomplete)]


RIG = RigName()

#: ``--rig NAME`` (``acquire``): open an installed rig by name (a plugin's, or one of rigctl's own)
rig_option = click.option(
    "--rig", "rig", type=RIG, default=None,
    help="Open this installed rig: a plugin's backend (your own hardware: docs/guides/my-hardware.md) or one of "
         "rigctl's own; `rigctl rigs` lists them. Not with --sim/--hil/--inprocess/--drum-port/--replay/--handheld "
         "(those choose rigctl's own rigs).")


def _parse_rig_options(ctx: click.Context, param: click.Parameter, value: tuple[str, ...]) -> dict[str, str]:
    out: dict[str, str] = {}
    for text in value:
        key, sep, val = text.partition("=")
        key = key.strip()
        if not sep or not key:
            raise click.BadParameter(f"{text!r}: give KEY=VALUE", ctx, param)
        if key in out:
            raise click.BadParameter(f"{key} given twice", ctx, param)
        out[key] = val
    return out


#: ``--rig-option KEY=VALUE`` (repeatable): options handed to a plugin rig's factory
rig_options_option = click.option(
    "--rig-option", "rig_options", multiple=True, metavar="KEY=VALUE", callback=_parse_rig_options,
    help="An option of the --rig plugin (repeatable), handed to its factory as text (its `rigctl rigs` line and its "
         "documentation name them); drum=sim|inprocess streams a sensor-only plugin through that simulated drum.")


def check_rig_flags(rig: str | None, rig_options: dict[str, str], *, others: bool) -> None:
    """Raise click.UsageError when ``--rig`` comes with a flag that chooses another rig (``others``), or
    ``--rig-option`` without a plugin's ``--rig``."""
    if rig is not None and others:
        raise click.UsageError("--rig NAME chooses the rig: drop --sim/--hil/--inprocess/--drum-port/--replay/"
                               "--handheld")
    if rig_options and rig is None:
        raise click.UsageError("--rig-option is an option of a plugin rig: give --rig NAME")

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


#: ``--lsl-wait SECONDS`` (``acquire``, ``serve``): wait for a recorder on the marker stream before a run starts
lsl_wait_option = click.option(
    "--lsl-wait", "lsl_wait_s", type=LSL_WAIT_S, default=0.0, show_default=True, metavar="SECONDS",
    help="With LSL: before a run's first marker and trial, wait up to SECONDS for a consumer (LabRecorder) of the "
         "marker stream, so the recording holds run_start; carries on (saying so) when none comes. liblsl tells "
         "whether a consumer is connected, not how many (docs/lsl.md).")


def parse_injections(ctx: click.Context, param: click.Parameter, value: tuple[str, ...]) -> tuple[FaultSpec, ...]:
    """The ``FAULT@T[+D]`` specs of a repeatable option or argument parsed (click.BadParameter naming a bad one)."""
    out = []
    for text in value:
        try:
            out.append(parse_fault(text))
        except FaultSpecError as exc:
            raise click.BadParameter(str(exc).removeprefix(f"--inject {text}: "), ctx, param) from None
    return tuple(out)


#: how the help names a fault that takes a value
FAULT_FORMS = {"taxel-ohm": "taxel-ohm=N", "contact-stiffness": "contact-stiffness=G_PER_MM", "slip": "slip=N%",
               "home-switch": "home-switch=closed|open", "cell-gain": "cell-gain=X", "cell-offset": "cell-offset=G",
               "coupling-slip": "coupling-slip=N%", "steps-lost": "steps-lost=N%",
               "hx711-dout-noise": "hx711-dout-noise=P", "calibration-scale": "calibration-scale=X"}

#: ``--inject FAULT@T[+D]`` (repeatable): faults injected into a simulated rig (rigctl.core.faults, docs/safety.md)
inject_option = click.option(
    "--inject", "inject", multiple=True, metavar="FAULT@T[+D]", callback=parse_injections,
    help="Inject a fault into the simulated rig (repeatable): FAULT starts T s after the rig is open and lasts D s "
         "(no +D: to the end), on the rig's own clock (simulated time with --inprocess); FAULT@0: wired that way "
         "from power-on (before the rig opens). FAULT is one of "
         + ", ".join(FAULT_FORMS.get(name, name) for name in FAULTS)
         + "; docs/safety.md says what the rig does with each and what clears it.")


#: ``--hx711-rate 10|80`` (``acquire``, ``doctor``, ``serve``): the simulated HX711's rate (docs/config.md)
hx711_rate_option = click.option(
    "--hx711-rate", "hx711_rate", type=click.Choice(["10", "80"]), default=None, metavar="10|80",
    callback=lambda ctx, param, value: None if value is None else int(value),
    help="With --sim, --hil, --inprocess or --replay: the simulated HX711 converts at 10 or 80 samples/s (its RATE "
         "pin low or high); default the rig config's force_loop.hx711_rate_sps, else 80. The controller is told the "
         "rate at open by the force loop written, as on a real rig: the rig config's force_loop block with this rate "
         "(docs/config.md; the file is not changed).")


#: ``--allow-firmware-mismatch``: open boards whose firmware build differs from the installed sources'
allow_firmware_mismatch_option = click.option(
    "--allow-firmware-mismatch", is_flag=True, default=False,
    help="Run even if a board's firmware build differs from the installed sources' (checked at every open; without "
         "it the run is refused with one line naming both builds and `rigctl firmware --flash`). A drum controller below "
         "the safety floor is refused all the same.")


#: ``--truth-log FILE`` (``acquire``, ``doctor``): the simulated rig's ground truth as CSV (rigctl.simulation.truth)
truth_log_option = click.option(
    "--truth-log", "truth_log", type=click.Path(dir_okay=False, writable=True, path_type=Path), default=None,
    metavar="FILE",
    help="With --sim or --hil: write the physical model's ground truth to FILE (CSV: wall_time_s, Unix time; time_s "
         "from the run's start, the clock --inject uses; true_force_g, actuator_mm, drum_speed_mm_s, "
         "motor_mm (the actuator motor's own travel); >= 100 Hz). "
         "FILE must not exist.")


def check_truth_log(truth_log: Path | None, kind: str) -> None:
    """Raise click.UsageError for a --truth-log the rig of ``kind`` cannot write (not "sim"/"hil") or a FILE that
    exists."""
    if truth_log is None:
        return
    if kind not in ("sim", "hil"):
        raise click.UsageError("--truth-log works with --sim or --hil (the models whose ground truth it writes)")
    if truth_log.exists():
        raise click.UsageError(f"--truth-log {truth_log}: the file exists (it is never overwritten)")


def check_one_rig(*, sim: bool, hil: bool, inprocess: bool, drum_port: str | None) -> None:
    """Raise click.UsageError when the flags name more than one rig: the hardware ports beside a simulated rig, or
    more than one of ``--sim``, ``--hil`` (``--hil-bootloaders``) and ``--inprocess``."""
    if drum_port is not None and (sim or hil or inprocess):
        raise click.UsageError("--drum-port/--taxel-port select the hardware rig: drop --sim/--hil/--inprocess")
    if sim + hil + inprocess > 1:
        raise click.UsageError("choose one of --sim, --hil and --inprocess")


def check_config(config_path: Path | None, save: bool) -> None:
    """``--config`` (``doctor``, ``calibrate``): the rig config read (and, with ``save``, checked as the file the
    result replaces) before the rig starts: a session, another program's file, a device or a file that is not a rig
    config is refused (exit 2)."""
    from rigctl.acquisition.rigconfig import CalibrationError, config_path as resolved, load_rig_config
    from rigctl.cli.outputs import UsageProblem
    from rigctl.storage.outputs import OutputError, check_replaceable

    path = resolved(config_path)
    try:
        if save:
            check_replaceable(path, option="--config")
        load_rig_config(path)
    except (OutputError, CalibrationError) as exc:
        raise UsageProblem(f"--config: {exc}" if not str(exc).startswith("--config") else str(exc)) from None


def ask_operator_mass(mass_g: float) -> None:
    """The operator puts ``mass_g`` grams on the load cell (0: takes it off) and presses Enter (the reference-mass
    check of ``rigctl doctor``, the calibration of ``rigctl calibrate loadcell``, on hardware)."""
    click.prompt(f"put the {mass_g:g} g reference mass on the load cell, then press Enter" if mass_g
                 else "take the reference mass off the load cell, then press Enter", default="", show_default=False,
                 err=True)


def check_rig_face_flags(*, ack: str | None, sim: bool, hil: bool, inprocess: bool, drum_port: str | None,
                         taxel_port: str | None) -> None:
    """The flags ``doctor`` and ``calibrate`` share, checked before the rig opens: ``--ack`` with a reason, both
    hardware ports or neither, one rig (:func:`check_one_rig`). Raises click.UsageError."""
    if ack is not None and not ack.strip():
        raise click.UsageError("--ack takes the reason the fault may be cleared (logged)")
    if (drum_port is None) != (taxel_port is None):
        raise click.UsageError("the hardware rig needs both --drum-port and --taxel-port")
    check_one_rig(sim=sim, hil=hil, inprocess=inprocess, drum_port=drum_port)


def acknowledgement(ack: str | None) -> tuple[str, str] | None:
    """``--ack REASON`` as :func:`rigctl.operations.open_control` takes it: ``(reason, the operator's login name)``;
    None without it."""
    if ack is None:
        return None
    from rigctl.acquisition.safety import operator_name  # imported only then: a run as another user may read less

    return ack.strip(), operator_name()
