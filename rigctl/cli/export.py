"""``rigctl export``: a session (and its encoded spike trains) in another format; ``rigctl export nwb``."""

from __future__ import annotations

import click

from rigctl.cli.outputs import UsageProblem, check_output
from rigctl.cli.progress import bars, progress_option, show_bars


@click.group("export")
def export():
    """Write a session in a format other tools read (NWB)."""


@export.command("nwb")
@click.argument("session", type=click.Path(exists=True, dir_okay=False))
@click.option("--encoded", type=click.Path(exists=True, dir_okay=False), default=None,
              help="The session's encoded file (rigctl encode): its spike trains become the NWB Units table.")
@click.option("--variants", default=None,
              help="Comma-separated variants whose spike trains are exported (default: the stored ones in real time, "
                   "not speed-scaled).")
@click.option("--out", "out", type=click.Path(dir_okay=False, writable=True), required=True, help="The NWB file to write (.nwb).")
@click.option("--overwrite", is_flag=True, help="Replace an existing --out file.")
@progress_option
@click.option("--keep-nonfinite", is_flag=True,
              help="Export trials whose force or speed readings hold NaN or inf (default: excluded).")
def nwb(session, encoded, variants, out, overwrite, progress, keep_nonfinite):
    """Export SESSION as an NWB file: taxel readings (TimeSeries), drum and load-cell traces, the trials table, the
    sensor and rig description, and with --encoded the SA/RA spike trains as a Units table (docs/nwb.md)."""
    from rigctl.storage.encoded import NotEncodedError
    from rigctl.storage.nwb import NwbExportError, check_spike_variants, estimate_nwb_bytes, export_nwb
    from rigctl.storage.session import SessionError
    from rigctl.storage.validate import TrialsExcluded

    vlist = [v.strip() for v in variants.split(",") if v.strip()] if variants else None
    if variants is not None and encoded is None:  # was ignored (the export ran without a word)
        raise UsageProblem("--variants chooses among the spike trains of --encoded FILE: give the encoded file too")
    try:
        if encoded is not None:  # before any work: an unknown variant is a usage error
            check_spike_variants(encoded, vlist)
        need = estimate_nwb_bytes(session, encoded)
    except NwbExportError as exc:
        raise UsageProblem(f"--variants: {exc}" if vlist else str(exc)) from None
    except (SessionError, NotEncodedError) as exc:
        raise click.ClickException(str(exc)) from None
    check_output(out, overwrite=overwrite, inputs=(session, encoded), suffixes=(".nwb",), need_bytes=need, kind="nwb")
    import warnings

    try:
        with warnings.catch_warnings(record=True) as caught, bars(show_bars(progress), leave=False) as on_event:
            warnings.simplefilter("always")
            summary = export_nwb(session, out, encoded_path=encoded, variants=vlist, progress=on_event,
                                 overwrite=overwrite, keep_nonfinite=keep_nonfinite)
    except (NwbExportError, SessionError, NotEncodedError) as exc:
        raise click.ClickException(str(exc)) from None
    for w in caught:  # one line each (excluded trials), as rigctl encode shows them
        if issubclass(w.category, TrialsExcluded):
            click.echo(f"warning: {w.message}", err=True)
    units = ", ".join(f"{v}: {n} units, {summary.spikes[v]} spikes" for v, n in summary.units.items())
    click.echo(f"wrote {out}: {summary.n_trials} trials, {summary.n_samples} samples x {summary.n_channels} taxels "
               f"at {summary.rate_hz:g} Hz" + (f"; {units}" if units else ""))
