"""``rigctl sim dataset``: render a protocol straight from the physical model into a session file (no pacing)."""

from __future__ import annotations

import json

import click

from rigctl.cli.outputs import check_output
from rigctl.cli.progress import bars
from rigctl.cli.protocols import PROTOCOL


@click.command("dataset")
@click.argument("protocol", type=PROTOCOL)
@click.option("--out", "out", required=True, type=click.Path(dir_okay=False), help="Session file (.h5) to write.")
@click.option("--trials-per-condition", type=click.IntRange(min=1), default=None,
              help="Override the protocol's trials per condition (e.g. 10 for a reduced paper dataset).")
@click.option("--seed", type=int, default=0, show_default=True,
              help="Dataset seed (trial i draws from SeedSequence([seed, i]); any --workers gives the same file).")
@click.option("--workers", type=click.IntRange(min=0), default=None,
              help="Processes rendering trials while this one writes (default: cores - 1; 0: render here too).")
@click.option("--compression", type=click.Choice(["none", "lzf", "gzip"]), default="none", show_default=True,
              help="HDF5 compression of the taxels (none is fastest; the full paper dataset is then ~3 GB).")
@click.option("--start-at", "start_at", type=click.Choice(["index", "any-angle"]), default="index", show_default=True,
              help="Where each trial starts on the drum: at its index mark (trials of a texture phase-aligned, as "
                   "rigctl's rig records) or at an arbitrary angle (a rig whose recorder gets no index signal). "
                   "A resumed file keeps the model it was started with.")
@click.option("--overwrite", is_flag=True, help="Replace an existing output file.")
@click.option("--resume", is_flag=True, help="Continue an interrupted output file (renders only missing trials).")
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def dataset(protocol, out, trials_per_condition, seed, workers, compression, start_at, overwrite, resume, as_json,
            quiet):
    """Generate a simulated dataset from PROTOCOL (e.g. protocols/paper_dataset.toml) without real-time pacing.

    Writes the same session layout as `rigctl acquire` (kind "simulated-dataset"), trial by trial, on all cores.
    """
    from rigctl.acquisition.protocol import ProtocolError, load_protocol
    from rigctl.simulation.dataset import generate_dataset
    from rigctl.simulation.model import RigConfig

    if resume and overwrite:
        raise click.UsageError("--resume and --overwrite exclude each other")
    check_output(out, overwrite=overwrite or resume, inputs=(protocol,),
                 overwrite_hint="continue it with --resume, or pass --overwrite")
    config = RigConfig()
    config.drum.start_at_index = start_at == "index"
    try:
        with bars(not quiet) as progress:
            summary = generate_dataset(load_protocol(protocol), out, trials_per_condition=trials_per_condition, seed=seed,
                                       workers=workers, progress=progress, config=config,
                                       compression=None if compression == "none" else compression,
                                       overwrite=overwrite, resume=resume)
    except ProtocolError as exc:
        raise click.ClickException(str(exc)) from None
    except (FileExistsError, TypeError, ValueError) as exc:
        raise click.ClickException(str(exc)) from None
    if as_json:
        click.echo(json.dumps(summary))
    else:
        click.echo(f"{summary['n_trials']} trials, {summary['trial_seconds']:.0f} s of trials in "
                   f"{summary['wall_s']:.1f} s ({summary['realtime_factor']:.0f}x real time, "
                   f"{summary['workers']} workers) -> {summary['path']} ({summary['bytes'] / 1e6:.1f} MB)")
