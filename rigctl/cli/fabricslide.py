"""``rigctl import-fabricslide``: the FabricSlide preset of ``rigctl import`` (16 channels at 1 kHz, 10 bits,
fabrics and board in one labelled session file)."""

from __future__ import annotations

from pathlib import Path

import click

from rigctl.cli.jsonout import json_text
from rigctl.cli.outputs import HDF5_SUFFIXES, check_output
from rigctl.cli.progress import bars
from rigctl.cli.ranges import floats

#: the environment variable naming the FabricSlide folder when DIRECTORY is not given
ENV_DIR = "RIGCTL_FABRICSLIDE"


@click.command("import-fabricslide")
@click.argument("directory", required=False, envvar=ENV_DIR, type=click.Path(file_okay=False))
@click.option("--out", "out", required=True, type=click.Path(dir_okay=False, writable=True), help="Session file (.h5) to write.")
@click.option("--include-board/--no-board", default=True, show_default=True,
              help="Also import the Board10mm recordings (20 mm ridges) into the same file.")
@click.option("--pattern", default="*.csv", show_default=True, help="Glob of file names to import.")
@click.option("--trim", type=floats(0, 0.49), default=0.10, show_default=True,
              help="Fraction of each trial dropped at each end (the arm's acceleration ramps).")
@click.option("--close-gaps", is_flag=True, help="Interpolate across gaps in a file's time stamps (declared in the "
              "ledger); without it such a file is refused.")
@click.option("--clip", is_flag=True, help="Pin readings the 10-bit map puts outside 0..1023 to the range (counted, "
              "declared in the ledger); without it they are refused.")
@click.option("--overwrite", is_flag=True, help="Replace an existing output file.")
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def import_fabricslide(directory, out, include_board, pattern, trim, close_gaps, clip, overwrite, as_json, quiet):
    """Import FabricSlide CSVs from DIRECTORY (the folder holding fabric/ and board/, e.g.
    ../shared/data/fabricslide beside a checkout; default $RIGCTL_FABRICSLIDE).

    The 16 taxels are resampled to 1 kHz from the timestamps and written as 16 channels of 10-bit counts (layout
    1x16); texture = the fabric's name (texture set: fabrics + Board10mm, groups fabric/board), speed = |velocity|,
    force = the arm's setpoint; the signed velocity is a trial attribute.
    """
    from rigctl.storage.fabricslide import import_fabricslide as run

    if not directory:
        raise click.UsageError(f"give the FabricSlide folder (fabric/ and board/ of github.com/wngfra/FabricSlide): "
                               f"rigctl import-fabricslide DIRECTORY --out {out}, or set {ENV_DIR}")
    check_output(out, overwrite=overwrite, kind="session", suffixes=HDF5_SUFFIXES)
    directory = Path(directory)
    try:
        with bars(not quiet) as progress:
            summary = run(directory, out, include_board=include_board, pattern=pattern, trim=trim,
                          overwrite=overwrite, progress=progress, close_gaps=close_gaps, clip=clip)
    except (FileNotFoundError, FileExistsError, ValueError) as exc:
        raise click.ClickException(str(exc)) from None
    from rigctl.storage.ledger import ledger, ledger_lines

    entries = ledger(summary.pop("steps", None) or {})  # every step that changed a value: the one ledger
    if as_json:
        click.echo(json_text({**summary, "ledger": entries}))
    else:
        click.echo(f"{summary['n_trials']} trials, 16 channels, {summary['samples'] / 1000:.0f} s at 1 kHz -> "
                   f"{summary['path']} (textures: {', '.join(summary['labels'])})")
        for line in ledger_lines(entries):
            click.echo(f"ledger: {line}")
