"""``rigctl import``: recordings of any sensor (CSV, NPY/NPZ, MATLAB .mat, NWB) as a session file."""

from __future__ import annotations

import click

from rigctl.cli.interrupts import stop_on_sigterm
from rigctl.cli.jsonout import json_text
from rigctl.cli.outputs import HDF5_SUFFIXES, UsageProblem, check_output
from rigctl.cli.progress import bars, progress_option, show_bars
from rigctl.cli.ranges import MAX_VOLTS, RATE_HZ, floats


def _checked_layout(ctx, param, value):
    """--layout parsed before any work (a usage error, exit 2, naming the option); passed on as given."""
    if value is not None:
        from rigctl.core.sensor import parse_layout

        try:
            parse_layout(value)
        except ValueError as exc:
            raise click.BadParameter(str(exc)) from None
    return value


def _checked_segment(ctx, param, value):
    """--segment parsed before any work (a usage error, exit 2, naming the option); passed on as given."""
    if value is not None:
        from rigctl.storage.importers import parse_segment

        try:
            parse_segment(value)
        except ValueError as exc:
            raise click.BadParameter(str(exc).removeprefix(f"--segment {value!r}: ")) from None
    return value


@click.command("import")
@click.argument("files", nargs=-1, required=True, type=click.Path())
@click.option("--out", "out", required=True, type=click.Path(dir_okay=False, writable=True), help="Session file (.h5) to write.")
@click.option("--rate", "rate_hz", type=RATE_HZ, default=None,
              help="Sample rate of the recordings, Hz (required unless the mapping or an NWB file gives it).")
@click.option("--channels", type=click.IntRange(1, 1_000_000), default=None, help="Taxel channels per sample.")
@click.option("--layout", default=None, metavar="ROWSxCOLSxLAYERS", callback=_checked_layout,
              help="Taxel grid, e.g. 3x3x1 (default: from the channel count; 18 -> the paper's 3x3x2).")
@click.option("--label-pattern", default=None, metavar="PATTERN",
              help="File-name pattern naming texture, speed_mm_s, force_g, repeat, e.g. "
                   "'{texture}__V{speed_mm_s}__{rep}.csv'.")
@click.option("--texture", default=None, help="Texture label of the files no pattern or mapping labels.")
@click.option("--resample", "resample_hz", type=RATE_HZ, default=None,
              metavar="HZ", help="Resample to this rate (scipy.signal.resample_poly); recorded in the session.")
@click.option("--segment", "segment_spec", default=None, metavar="METHOD", callback=_checked_segment,
              help="Cut continuous recordings into trials, per file at its own level: fixed:SECONDS[:HOP_S], "
                   "threshold[:LEVEL[%][:MIN_S[:SMOOTH_S]]] (LEVEL: % of the file's own swing, default 50%, or "
                   "counts) or cycles[:N[:MIN_PERIOD_S[:MAX_PERIOD_S]]] (press-and-slide cycles, the period checked "
                   "against its harmonics). A table per file is printed.")
@click.option("--align", type=click.Choice(["onset", "none"]), default=None,
              help="cycles: cut each trial at its press onset (default) or from sample 0 (none).")
@click.option("--pre-ms", type=floats(0, 60_000), default=None, metavar="MS",
              help="Margin kept before each press onset / run start, ms [default: 0].")
@click.option("--min-swing", type=floats(0, 1e6, min_open=True), default=None, metavar="RATIO",
              help="threshold/cycles: the presses' swing must reach RATIO x the noise at rest, unless (cycles) the "
                   "activity is clearly periodic [default: 10].")
@click.option("--press-period-s", type=floats(0, 1e6, min_open=True), default=None, metavar="S",
              help="cycles: the rig's press period, s, when known: the presses are counted against it (a press the "
                   "file lacks is missed, a bump off the rig's period is no press); without it, against rigctl's own "
                   "press finder (said). A file's own (mapping [files.NAME] or an NPZ's press_period_s) goes first.")
@click.option("--mapping", type=click.Path(exists=True, dir_okay=False), default=None,
              help="TOML mapping giving any of these values, per-file labels and the texture set.")
@click.option("--volts-ref", type=floats(0, MAX_VOLTS, min_open=True), default=None, metavar="V",
              help="The recordings are volts with this ADC reference: one count is V/2^bits volts (5 V, 10 bits: "
                   "5/1024 V), so V itself is past the top count (default: the recordings are counts).")
@click.option("--scale", type=floats(-1e12, 1e12), default=None, metavar="S",
              help="Readings that are not counts: counts = x * S + O, then rounded (recorded). Without it, "
                   "--offset or --volts-ref, readings that are not whole counts are refused.")
@click.option("--clip", is_flag=True, default=None,
              help="Pin values outside the ADC range (volts at or above --volts-ref, a --resample overshoot) to it, "
                   "counted and printed; without it they are refused.")
@click.option("--close-gaps", is_flag=True, default=None,
              help="Close the gaps inside a trial's time stamps (a CSV time column: interpolated across; NWB, XDF: "
                   "the samples joined back to back; frames lost in rigctl's XDF stream), named and declared in the "
                   "ledger; without it such a file is refused.")
@click.option("--offset", type=floats(-1e12, 1e12), default=None, metavar="O", help="See --scale (default 0).")
@click.option("--columns", default=None, metavar="A,B,...",
              help="CSV: the channel columns, in channel order (header names or 0-based indices); the other "
                   "columns are not imported (default: every column but the time column).")
@click.option("--time-column", default=None, metavar="NAME",
              help="CSV: the column of sample times; the readings are resampled onto the --rate grid (linear), the "
                   "jitter and gaps stated (default: a column named as one: time, timestamp, t, seconds, time_s, "
                   "time_ms, millis, 'Time (ms)', time_us, micros, time_ns, ...). Its unit: --time-unit or its name.")
@click.option("--time-unit", type=click.Choice(["s", "ms", "us", "ns"]), default=None,
              help="The time column's unit (required when its name does not say it; never guessed). The rate it "
                   "implies is checked against --rate before anything is allocated.")
@click.option("--repeated-stamps", type=click.Choice(["refuse", "keep-first"]), default=None,
              help="Rows with the time stamp of the row before: refuse (default), or keep the first of each (the "
                   "others dropped, counted and printed, recorded in the import steps).")
@click.option("--variable", default=None, metavar="NAME",
              help="NPZ / MAT: the array, NWB: the TimeSeries holding the taxels (a file with several series and "
                   "none named taxels is refused without it; the one read is always named).")
@click.option("--nan", "nan", type=click.Choice(["refuse", "hold", "interpolate"]), default=None,
              help="NaN samples: refuse (default; the error names the file, the count and the first samples), hold "
                   "the last good value, or interpolate linearly between good samples.")
@click.option("--bits", "adc_bits", type=click.IntRange(1, 16), default=None,
              help="ADC resolution of the stored counts [default: 10].")
@click.option("--preset", type=click.Choice(["fabricslide"]), default=None,
              help="A known dataset: FILES is its folder (fabricslide = rigctl import-fabricslide's defaults).")
@click.option("--skip-bad", is_flag=True, default=False,
              help="Leave out a file that cannot be imported (no trial found, NaN refused, other channels...), name "
                   "it with its reason (also in the session's import steps) and import the rest.")
@click.option("--overwrite", is_flag=True, help="Replace an existing output file.")
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
@progress_option
def import_recordings(files, out, rate_hz, channels, layout, label_pattern, texture, resample_hz, segment_spec,
                      align, pre_ms, min_swing, press_period_s, mapping, volts_ref, scale, clip, close_gaps, offset,
                      columns, time_column, time_unit,
                      repeated_stamps, variable, nan, adc_bits, preset, skip_bad, overwrite, as_json, progress):
    """Import FILES (format from the extension: .csv, .npy, .npz, .mat, .nwb) into the session file --out.

    A CSV holds one column per channel (a header row is skipped; ``,``, ``;`` with decimal commas, tab or spaces;
    --columns, --time-column); arrays are (n_samples, n_channels). Steps run in order: read, resample (--resample),
    scale to ADC counts (--volts-ref, --scale/--offset), segment (--segment), label (--label-pattern, --texture,
    mapping); each is recorded in the session's attributes and what changed the numbers is printed.
    """
    from rigctl.operations import import_recordings as run
    from rigctl.storage.time_column import TimeColumnError

    check_output(out, overwrite=overwrite, inputs=(*files, mapping), kind="session", suffixes=HDF5_SUFFIXES)
    stop_on_sigterm()  # a SIGTERM mid-import removes the partial session and its lock, as a Ctrl-C does
    if preset is not None and len(files) != 1:
        raise click.UsageError(f"--preset {preset} takes one FILES argument: the FabricSlide folder")
    options = {k: v for k, v in (("close_gaps", close_gaps), ("clip", clip)) if v} if preset else dict(
        rate_hz=rate_hz, channels=channels, layout=layout, label_pattern=label_pattern, texture=texture,
        resample_hz=resample_hz, segment_spec=segment_spec, align=align, pre_ms=pre_ms, min_swing=min_swing,
        press_period_s=press_period_s, mapping=mapping,
        volts_ref=volts_ref, adc_bits=adc_bits, nan=nan, skip_bad=skip_bad, scale=scale, offset=offset, clip=clip, close_gaps=close_gaps,
        columns=[c.strip() for c in columns.split(",") if c.strip()] if columns else None,
        time_column=time_column, time_unit=time_unit, repeated_stamps=repeated_stamps, variable=variable)
    try:
        with bars(show_bars(progress) and not as_json) as progress:
            report = run(files, out, preset=preset, overwrite=overwrite, progress=progress, **options)
    except TimeColumnError as exc:  # what the command line must say (a unit, a rate that disagrees): exit 2
        raise UsageProblem(str(exc)) from None
    except (FileExistsError, FileNotFoundError, ValueError) as exc:  # RecordingImportError is a ValueError
        raise click.ClickException(str(exc)) from None
    from rigctl.storage.ledger import ledger, ledger_lines

    for line in report.warnings:
        click.echo(f"warning: {line}", err=True)
    entries = ledger(report.summary.get("steps") or {})  # every step that changed a value: the one ledger
    if as_json:
        click.echo(json_text({**report.json_summary(), "ledger": entries}))
        return
    if report.table:
        click.echo(report.table)
    click.echo(report.line())
    for line in ledger_lines(entries):
        click.echo(f"ledger: {line}")
