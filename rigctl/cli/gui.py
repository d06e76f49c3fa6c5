"""``rigctl gui``: start the desktop app (PySide6 + pyqtgraph, the ``gui`` extra)."""

from __future__ import annotations

import click

from rigctl.cli.outputs import check_output
from rigctl.cli.ranges import floats
from rigctl.cli.rig_flags import inject_option

#: image formats the window grab is saved in (Qt's image writers, by extension)
SCREENSHOT_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp")


def _require_display() -> None:
    """Refuse, in one line, to start Qt without a display on Linux (Qt would abort the process, exit 134, with advice
    to reinstall it). A platform plugin chosen with QT_QPA_PLATFORM (offscreen, vnc, ...) is left to Qt."""
    import os
    import sys

    if not sys.platform.startswith("linux") or os.environ.get("QT_QPA_PLATFORM"):
        return
    if os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"):
        return
    raise click.ClickException("no display: rigctl gui needs a desktop session (DISPLAY and WAYLAND_DISPLAY are "
                               "unset); on a machine without one run it under xvfb-run, or set "
                               "QT_QPA_PLATFORM=offscreen for --screenshot")


@click.command("gui")
@click.option("--drum-port", default=None, help="Serial port of the drum controller (Mega). Default: simulated rig.")
@click.option("--taxel-port", default=None, help="Serial port of the taxel streamer (Uno). Default: simulated rig.")
@click.option("--sim", is_flag=True, help="The simulated rig (default: the source last chosen in the app's Connect "
                                        "dialog; the simulated rig the first time).")
@click.option("--hil", is_flag=True, help="The rig's own firmware under simavr (hardware-in-the-loop; needs the AVR "
                                        "toolchain and simavr).")
@click.option("--hil-bootloaders", is_flag=True, help="--hil with the boards' real bootloaders: each connect resets "
                                                    "them, as USB does on a bench.")
@click.option("--replay", type=click.Path(exists=True), default=None,
              help="Stream a recorded session file (or the FabricSlide recordings in a directory) through the "
                   "simulated rig.")
@click.option("--screenshot", type=click.Path(dir_okay=False, writable=True), default=None,
              help="Save a PNG of the main window before quitting (with --quit-after).")
@click.option("--overwrite", is_flag=True, help="Replace an existing --screenshot file.")
@click.option("--quit-after", type=floats(0, 1e6), default=None, help="Quit after this many seconds.")
@click.option("--tab", type=click.Choice(["control", "live", "protocol", "analysis", "calibration", "classify"]),
              default=None, help="Tab to show first.")
@click.option("--run", is_flag=True, help="Press and run the drum at the panel's setpoints once connected.")
@click.option("--texture", default=None, help="Mount this texture plate (a label of the rig's set, A-P by default) "
                                              "once connected.")
@click.option("--max-fps", type=floats(0, 1e6), default=None,
              help="Frame cap of the live view, frames/s (1-120; default 30: the app's MAX_FPS).")
@inject_option
def gui(drum_port, taxel_port, sim, hil, hil_bootloaders, replay, screenshot, overwrite, quit_after, tab, run, texture,
        max_fps, inject):
    """Start the desktop app: rig control, live taxels and SA/RA rasters, protocol runs, offline analysis.

    With no source option it opens the source last chosen in its Connect dialog (the simulated rig the first time;
    ``--sim`` forces it). ``--screenshot PATH --quit-after SECONDS`` renders the main window
    on the simulated rig and exits (docs, smoke tests).
    """
    if (drum_port is None) != (taxel_port is None):
        raise click.UsageError("give both --drum-port and --taxel-port (or neither for the simulated rig)")
    if sum(map(bool, (drum_port, sim, hil or hil_bootloaders, replay))) > 1:
        raise click.UsageError("choose one source: --drum-port/--taxel-port, --sim, --hil (--hil-bootloaders) or "
                               "--replay")
    if inject and drum_port:
        raise click.UsageError("--inject works on the simulated rigs (--sim, --hil, --replay), not on hardware")
    if screenshot and quit_after is None:
        raise click.UsageError("--screenshot needs --quit-after SECONDS")
    if screenshot:
        check_output(screenshot, option="--screenshot", overwrite=overwrite, inputs=(replay,),
                     suffixes=SCREENSHOT_SUFFIXES, kind="figure")
    _require_display()
    try:
        from rigctl_gui.app import main
    except ImportError as exc:
        raise click.ClickException(f"the desktop app needs the 'gui' extra (PySide6, pyqtgraph): {exc}") from None
    argv = []
    for flag, value in (("--drum-port", drum_port), ("--taxel-port", taxel_port), ("--replay", replay),
                        ("--screenshot", screenshot), ("--quit-after", quit_after), ("--tab", tab),
                        ("--texture", texture), ("--max-fps", max_fps)):
        if value is not None:
            argv += [flag, str(value)]
    for spec in inject:  # the app opens its rig with RigSource(inject=...)
        argv += ["--inject", str(spec)]
    for flag, on in (("--run", run), ("--sim", sim), ("--hil", hil), ("--hil-bootloaders", hil_bootloaders)):
        if on:
            argv.append(flag)
    raise SystemExit(main(argv))
