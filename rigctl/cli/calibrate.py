"""``rigctl calibrate loadcell``: the load cell calibrated with a known mass, the scale written to the drum
controller's EEPROM and the rig config, the contact's stiffness measured with the verified scale stored with it (a thin
face over :func:`rigctl.operations.calibrate_loadcell`, which the GUI's calibration tab calls too). The fault advice
sends the operator here (a zero that moved, a scale that is wrong: docs/safety.md)."""

from __future__ import annotations

import sys
from pathlib import Path

import click

from rigctl.cli.ranges import SEED, floats
from rigctl.cli.rig_flags import (
    acknowledgement,
    ask_operator_mass,
    check_config,
    check_rig_face_flags,
    drum_port_option,
    hil_bootloaders_option,
    inprocess_option,
    taxel_port_option,
)

#: the reference masses a calibration takes, g: a mass the cell reads well above its noise, at most FORCE_LIMIT_G's
#: largest value (docs/wire-protocol.md 2.2: 1,500 g; the library refuses what the controller would trip on)
MASS_G = floats(1.0, 1500.0)


@click.group("calibrate")
def calibrate() -> None:
    """Calibrate the rig: the load cell with a known mass (``rigctl calibrate loadcell --mass-g 200``)."""


@calibrate.command("loadcell")
@click.option("--mass-g", "mass_g", type=MASS_G, required=True,
              help="The reference mass put on the load cell, g (weighed: the scale is only as good as it).")
@click.option("--sim", "sim", is_flag=True, default=False, help="Calibrate the simulated rig (the default).")
@click.option("--hil", is_flag=True, default=False, help="Calibrate the real firmware under simavr.")
@hil_bootloaders_option
@inprocess_option
@drum_port_option
@taxel_port_option
@click.option("--config", "config_path", type=click.Path(dir_okay=False, writable=True, path_type=Path), default=None,
              help="Rig config file the calibration is stored in (default $RIGCTL_CONFIG or ~/.config/rigctl/rig.json; "
                   "the one it replaces is kept for Undo).")
@click.option("--seed", type=SEED, default=0, show_default=True, help="Seed of the simulated rig.")
@click.option("--ack", "ack", metavar="REASON", default=None,
              help="Acknowledge a fault the drum controller still latches when the rig opens (its cause gone), "
                   "logged with your login name and REASON; without it a latched fault stops the calibration.")
def loadcell(mass_g, sim, hil, hil_bootloaders, inprocess, drum_port, taxel_port, config_path, seed, ack):
    """Calibrate the load cell with a known mass. The rig HOMEs and TAREs (a start: the actuator moves home), reads
    the cell without the mass, asks you to put the mass on it and take it off again (a simulated rig rests it
    itself), writes the scale to the drum controller's EEPROM and the rig config, then presses the mounted plate
    (300 g) and stores the contact's stiffness its probe measured with the new scale (the scale check of every later
    press compares with it: docs/wire-protocol.md 2.12). Exit status 1 if the calibration failed (nothing stored
    then), 2 for a usage error."""
    hil = hil or hil_bootloaders
    check_rig_face_flags(ack=ack, sim=sim, hil=hil, inprocess=inprocess, drum_port=drum_port, taxel_port=taxel_port)
    hardware = drum_port is not None
    if hardware and not sys.stdin.isatty():
        raise click.UsageError("on the hardware rig the calibration asks you to put the mass on the load cell and take "
                               "it off: run it in a terminal")
    check_config(config_path, True)
    from rigctl.operations import Home, RigSource, calibrate_loadcell, open_control

    source = RigSource.from_flags(hil=hil, drum_port=drum_port, taxel_port=taxel_port, bootloaders=hil_bootloaders,
                                  inprocess=inprocess)
    acknowledge = acknowledgement(ack)
    place = ask_operator_mass if hardware else None
    with open_control(source, home=Home.UNLESS_FAULTED, seed=seed, host_config_path=config_path,
                      acknowledge=acknowledge) as control:
        result = calibrate_loadcell(control, mass_g, place_mass=place, remove_mass=(lambda _g: place(0.0)) if place
                                    else None, config_file=config_path)
    stiffness = (f"; the contact's stiffness {result.contact_stiffness_g_per_mm:.0f} g/mm stored with it"
                 if result.contact_stiffness_g_per_mm > 0 else "; no contact stiffness measured (the stored one kept)")
    click.echo(f"load cell calibrated with {result.mass_g:g} g: {result.counts_per_g:.2f} counts/g, the mass reads "
               f"{result.check_force_g:.1f} g on the new scale (noise {result.noise_counts:.0f} counts){stiffness}; "
               f"stored in the drum controller's EEPROM and the rig config")

