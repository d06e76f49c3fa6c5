"""``rigctl firmware``: build both boards' images from the sources installed with rigctl, for flashing a real rig;
``--flash PORT`` flashes one board with avrdude (``--dry-run`` prints the command instead)."""

from __future__ import annotations

import shlex
import shutil
import subprocess

import click

#: what to try when avrdude cannot reach a board's bootloader
FLASH_HINT = ("is it the right port and board? A Mega with the 10 uF auto-reset capacitor fitted cannot be reset by "
              "avrdude: press its RESET button as avrdude starts, or take the capacitor out while flashing "
              "(docs/hardware/wiring.md)")


def _board_of(port: str) -> str | None:
    import os

    from rigctl.devices.ports import find_ports

    for info in find_ports():
        if os.path.realpath(info.device) == os.path.realpath(port):
            return info.board
    return None


def _build(fw):
    try:
        return fw.build(targets=("all",))
    except fw.FirmwareBuildError as exc:
        lines = [s for s in str(exc).splitlines() if s.strip()]
        raise click.ClickException(f"{lines[0]} ... {lines[-1]} (are gcc-avr avr-libc binutils-avr "
                                   f"arduino-core-avr make installed?)") from None


@click.command("firmware")
@click.option("--sources", "show_sources", is_flag=True, help="Only print the firmware source folder.")
@click.option("--flash", "port", default=None, metavar="PORT",
              help="Build, then flash one board on this serial port with avrdude (its bootloader).")
@click.option("--board", type=click.Choice(["mega", "uno"]), default=None,
              help="The board on --flash's port (default: guessed from its USB id).")
@click.option("--image", default=None, metavar="IMAGE",
              help="With --flash: the image to flash (uno: uno_taxel, the default, or uno_encoder, the taxel "
                   "streamer with the on-board SA encoder; mega: mega_drum).")
@click.option("--dry-run", is_flag=True, default=False,
              help="With --flash: print the exact avrdude command, build nothing, flash nothing.")
def firmware(show_sources, port, board, image, dry_run):
    """Build the Uno and Mega images from the firmware sources shipped with rigctl (into a user cache folder, or
    arduino/build in a checkout) and print the .hex files with the avrdude commands that flash them; or flash one
    board: rigctl firmware --flash /dev/ttyACM0 --board mega.

    --image uno_encoder flashes the Uno with the on-board SA encoder instead of the plain streamer.
    Needs Debian's gcc-avr avr-libc binutils-avr arduino-core-avr make (and avrdude to flash).
    """
    from rigctl import firmware as fw

    if show_sources:
        click.echo(fw.sources())
        return
    if port is None:
        if board is not None or dry_run or image is not None:
            raise click.UsageError("--board, --image and --dry-run go with --flash PORT")
        out = _build(fw)
        click.echo(f"sources: {fw.sources()}")
        click.echo(f"build:   {out}")
        for name in fw.BOARDS:
            for img in fw.IMAGES[name]:
                click.echo(shlex.join(fw.avrdude_command(name, "PORT", out / f"{img}.hex")))
        return
    board = board or _board_of(port)
    if board is None:
        raise click.UsageError(f"cannot tell which board is on {port} from its USB id: name it with --board mega|uno")
    image = image or fw.IMAGES[board][0]
    if image not in fw.IMAGES[board]:
        raise click.UsageError(f"--image {image} is not a {board} image: {' or '.join(fw.IMAGES[board])}")
    if dry_run:
        hex_file = fw.build_dir() / f"{image}.hex"
        click.echo(shlex.join(fw.avrdude_command(board, port, hex_file)))
        if not hex_file.exists():
            click.echo(f"({hex_file.name} is not built yet: rigctl firmware builds it)", err=True)
        return
    if shutil.which("avrdude") is None:
        raise click.ClickException("avrdude is not installed (sudo apt install avrdude)")
    out = _build(fw)
    cmd = fw.avrdude_command(board, port, out / f"{image}.hex")
    click.echo(shlex.join(cmd), err=True)
    if subprocess.run(cmd).returncode != 0:
        raise click.ClickException(f"avrdude could not flash the {board} on {port}: {FLASH_HINT}")
    click.echo(f"flashed the {board} on {port}")
