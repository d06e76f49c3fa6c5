"""``rigctl firmware``: build both boards' images from the sources installed with rigctl, for flashing a real rig."""

from __future__ import annotations

import click

#: image -> (avrdude part, programmer, extra flags), the boards' stock bootloaders (docs/firmware.md)
AVRDUDE = {
    "uno_taxel": ("m328p", "arduino", ""),
    "mega_drum": ("m2560", "wiring", " -D"),
}


@click.command("firmware")
@click.option("--sources", "show_sources", is_flag=True, help="Only print the firmware source folder.")
def firmware(show_sources):
    """Build the Uno and Mega images from the firmware sources shipped with rigctl (into a user cache folder, or
    arduino/build in a checkout) and print the .hex files with the avrdude commands that flash them.

    Needs Debian's gcc-avr avr-libc binutils-avr arduino-core-avr make.
    """
    from rigctl import firmware as fw

    if show_sources:
        click.echo(fw.sources())
        return
    try:
        out = fw.build(targets=("all",))
    except fw.FirmwareBuildError as exc:
        lines = [s for s in str(exc).splitlines() if s.strip()]
        raise click.ClickException(f"{lines[0]} ... {lines[-1]} (are gcc-avr avr-libc binutils-avr "
                                   f"arduino-core-avr make installed?)") from None
    click.echo(f"sources: {fw.sources()}")
    click.echo(f"build:   {out}")
    for image, (part, programmer, extra) in AVRDUDE.items():
        hex_file = out / f"{image}.hex"
        click.echo(f"avrdude -p {part} -c {programmer} -P PORT -b 115200{extra} -U flash:w:{hex_file}")
