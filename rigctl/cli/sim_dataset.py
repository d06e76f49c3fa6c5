"""``rigctl sim dataset``: render a protocol straight from the physical model into a session file (no pacing)."""

from __future__ import annotations

from pathlib import Path

import click

from rigctl.acquisition.protocol import MAX_PLAN_TRIALS
from rigctl.cli.interrupts import is_interrupt
from rigctl.cli.jsonout import json_text
from rigctl.cli.outputs import HDF5_SUFFIXES, UsageProblem, check_output
from rigctl.cli.progress import bars, progress_option, show_bars
from rigctl.cli.protocols import PROTOCOL
from rigctl.cli.ranges import SEED, WORKERS_OR_0

#: bytes a simulated trial stores per sample beyond its taxels: seq (2), flags (1), host_time_s (8)
_SAMPLE_EXTRA_BYTES = 11


def dataset_size(protocol, trials_per_condition=None) -> tuple[int | None, float | None]:
    """(trials, bytes) of the dataset ``protocol`` renders, from its conditions without building the plan: the
    paper's sensor (``rigctl sim dataset`` renders it), uncompressed taxels plus seq/flags/host time per sample and
    the traces and HDF5 objects (~20 KiB a trial: the uncompressed paper dataset measured 4.4 GB)."""
    from rigctl.core.sensor import PAPER_SENSOR

    if not hasattr(protocol, "profiles"):  # a script protocol: its size is not known before it runs
        return None, None
    tpc = int(trials_per_condition or protocol.trials_per_condition)
    per_condition = len(protocol.textures) * len(protocol.forces_g) * tpc
    seconds = sum(protocol.trial_duration_s(p) for p in protocol.profiles) * per_condition
    per_sample = PAPER_SENSOR.n_channels * 2 + _SAMPLE_EXTRA_BYTES
    n_trials = per_condition * len(protocol.profiles)
    return n_trials, seconds * PAPER_SENSOR.sample_rate_hz * per_sample + n_trials * 20 * 1024


@click.command("dataset")
@click.argument("protocol", type=PROTOCOL)
@click.option("--out", "out", required=True, type=click.Path(dir_okay=False, writable=True), help="Session file (.h5) to write.")
@click.option("--trials-per-condition", type=click.IntRange(1, MAX_PLAN_TRIALS), default=None,
              help="Override the protocol's trials per condition (e.g. 10 for a reduced paper dataset).")
@click.option("--seed", type=SEED, default=0, show_default=True,
              help="Dataset seed (trial i draws from SeedSequence([seed, i]); any --workers gives the same file).")
@click.option("--workers", type=WORKERS_OR_0, default=None,
              help="Processes rendering trials while this one writes (default: cores - 1; 0: render here too).")
@click.option("--compression", type=click.Choice(["none", "lzf", "gzip"]), default="none", show_default=True,
              help="HDF5 compression of the taxels (none is fastest; the full paper dataset is then ~4.4 GB).")
@click.option("--start-at", "start_at", type=click.Choice(["index", "any-angle"]), default="index", show_default=True,
              help="Where each trial starts on the drum: at its index mark (trials of a texture phase-aligned, as "
                   "rigctl's rig records) or at an arbitrary angle (a rig whose recorder gets no index signal). "
                   "A resumed file keeps the model it was started with.")
@click.option("--overwrite", is_flag=True, help="Replace an existing output file.")
@click.option("--resume", is_flag=True, help="Continue an interrupted output file (renders only missing trials).")
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
@progress_option
def dataset(protocol, out, trials_per_condition, seed, workers, compression, start_at, overwrite, resume, as_json,
            progress):
    """Generate a simulated dataset from PROTOCOL (e.g. protocols/paper_dataset.toml) without real-time pacing.

    Writes the same session layout as `rigctl acquire` (kind "simulated-dataset"), trial by trial, on all cores.
    """
    from rigctl.acquisition.protocol import ProtocolError, load_protocol

    if resume and overwrite:
        raise click.UsageError("--resume and --overwrite exclude each other")
    if resume and not Path(out).exists():
        raise UsageProblem(f"--resume: {out} does not exist: start it without --resume")
    try:
        loaded = load_protocol(protocol)
    except ProtocolError as exc:
        raise UsageProblem(str(exc)) from None
    n_trials, need = dataset_size(loaded, trials_per_condition)
    if n_trials is None:  # a script protocol: sized when it runs
        pass
    elif n_trials > MAX_PLAN_TRIALS:
        raise UsageProblem(f"--trials-per-condition {trials_per_condition}: the plan would hold {n_trials} trials, "
                           f"more than {MAX_PLAN_TRIALS}")
    elif n_trials == 0:
        raise UsageProblem(f"{protocol}: the protocol plans no trial (no textures, forces or speeds)")
    check_output(out, overwrite=overwrite or resume, inputs=(protocol,), suffixes=HDF5_SUFFIXES,
                 overwrite_hint="continue it with --resume, or pass --overwrite", need_bytes=None if resume else need,
                 kind="session")
    from rigctl.simulation.dataset import generate_dataset  # the model, numba: after the checks
    from rigctl.simulation.model import RigConfig

    config = RigConfig()
    config.drum.start_at_index = start_at == "index"
    try:
        with bars(show_bars(progress)) as progress:
            summary = generate_dataset(loaded, out, trials_per_condition=trials_per_condition, seed=seed,
                                       workers=workers, progress=progress, config=config,
                                       compression=None if compression == "none" else compression,
                                       overwrite=overwrite, resume=resume)
    except KeyboardInterrupt:
        raise _interrupted(out, protocol) from None
    except Exception as exc:
        if is_interrupt(exc):  # a Ctrl-C that C code turned into its own error (an import's, rigctl.cli.interrupts)
            raise _interrupted(out, protocol) from None
        if isinstance(exc, (ProtocolError, FileExistsError, TypeError, ValueError)):
            raise click.ClickException(str(exc)) from None
        raise
    if as_json:
        click.echo(json_text(summary))
    else:
        n = summary["workers"]  # 0: rendered in this process (a small dataset, or --workers 0)
        where = f"{n} worker process{'es' if n != 1 else ''}" if n else "rendered in this process"
        click.echo(f"{summary['n_trials']} trials, {summary['trial_seconds']:.0f} s of trials in "
                   f"{summary['wall_s']:.1f} s ({summary['realtime_factor']:.0f}x real time, "
                   f"{where}) -> {summary['path']} ({summary['bytes'] / 1e6:.1f} MB)")


def _interrupted(out, protocol) -> click.ClickException:
    """The line a Ctrl-C ends ``sim dataset`` with: nothing written, or the trials so far kept and how to go on."""
    if not Path(out).exists():  # interrupted before the file was made: nothing to keep or continue
        return click.ClickException(f"interrupted before {out} was made: nothing was written")
    return click.ClickException(f"interrupted: the trials rendered so far are kept in {out}; continue with "
                                f"`rigctl sim dataset {protocol} --out {out} --resume`")
