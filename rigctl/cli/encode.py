"""``rigctl encode SESSION``: encode a session into SA/RA spike trains and features (paper eqs. 1-5)."""

from __future__ import annotations

from pathlib import Path

import click

from rigctl.cli.outputs import HDF5_SUFFIXES, UsageProblem, check_output, require_dask, scheduler_address
from rigctl.cli.progress import bars, progress_option, show_bars
from rigctl.cli.ranges import MAX_WINDOWS, WORKERS, floats
from rigctl.storage.encoded import ALL_VARIANTS, ENCODED_SUFFIX


def _windows_scaled(ctx, param, value):
    if str(value).strip().lower() in ("longest", "whole", "all"):
        return None
    try:
        n = int(value)
    except ValueError:
        raise click.BadParameter(f"{value!r} is neither a count nor 'longest'") from None
    if not 1 <= n <= MAX_WINDOWS:
        raise click.BadParameter(f"{n} is not in the range 1<=x<={MAX_WINDOWS}")
    return n


def _check_sizes(session, out, *, variants, batch, window_s, windows_unscaled, windows_scaled, store_spikes):
    """Refuse, before any work, an encoding whose output does not fit the disk or whose batch does not fit the
    memory (:func:`rigctl.encoding.sizing.estimate_encode`), naming the option and the figure (exit 2)."""
    from rigctl.encoding.sizing import available_memory_bytes, estimate_encode
    from rigctl.storage.encoded import MAIN_VARIANTS
    from rigctl.storage.outputs import free_bytes, size_text
    from rigctl.storage.session import SessionError, open_session

    try:
        with open_session(session) as s:
            est = estimate_encode(s, window_s=window_s, n_windows_unscaled=windows_unscaled,
                                  n_windows_scaled=windows_scaled, variants=variants, batch_trials=batch,
                                  store_spikes=MAIN_VARIANTS if store_spikes else ())
    except SessionError as exc:
        raise click.ClickException(str(exc)) from None
    what = (f"--windows-unscaled {windows_unscaled}" if windows_unscaled else
            f"--window-ms {window_s * 1000:g}" if window_s < 0.1 else "--out")
    free = free_bytes(out.parent if str(out.parent) else ".")
    if free is not None and est.out_bytes > free + (out.stat().st_size if out.is_file() else 0):
        raise UsageProblem(f"{what}: the encoded file would be about {size_text(est.out_bytes)} "
                           f"({est.n_trials} trials, {est.n_windows_unscaled} unscaled windows), {size_text(free)} "
                           f"free in {out.parent}")
    mem = available_memory_bytes()
    if mem is not None and est.batch_bytes > mem:
        raise UsageProblem(f"--batch {batch}: one batch needs about {size_text(est.batch_bytes)} of memory "
                           f"({est.n_windows_unscaled} unscaled windows), {size_text(mem)} available: lower --batch"
                           + (" or --windows-unscaled" if windows_unscaled else ""))


def _range_of(path: Path | None):
    """The per-taxel range of an encoded file (``--range-from``), None without one. Raises ValueError, OSError."""
    if path is None:
        return None
    import numpy as np

    from rigctl.encoding.normalise import TaxelRange
    from rigctl.storage.encoded import open_encoded

    with open_encoded(path) as f:
        n = f.normalisation
    return TaxelRange(np.asarray(n["taxel_min"], np.float64), np.asarray(n["taxel_max"], np.float64),
                      source=str(path))



@click.command("encode")
@click.argument("session", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--out", "out", type=click.Path(dir_okay=False, writable=True, path_type=Path), default=None,
              help="Encoded file to write (default: SESSION with suffix .enc.h5).")
@click.option("--overwrite", is_flag=True, help="Replace the output file if it exists.")
@click.option("--scheduler", default=None, callback=scheduler_address,
              help="Dask scheduler address (tcp://host:8786), or 'local' for a local cluster; default: this "
                   "process, numba on all cores.")
@click.option("--workers", type=WORKERS, default=None, help="Worker processes for --scheduler local.")
@click.option("--batch", "batch", type=click.IntRange(1, 100_000), default=256, show_default=True,
              help="Trials per batch.")
@click.option("--variant", "variants", multiple=True, type=click.Choice(ALL_VARIANTS),
              help="Variant to compute (repeatable); default: all (speed-scaled ones are skipped, with a warning, "
                   "when some trials have no speed).")
@click.option("--window-ms", type=floats(0, 60_000, min_open=True), default=100.0, show_default=True,
              help="Feature window length, ms.")
@click.option("--windows-unscaled", type=click.IntRange(1, MAX_WINDOWS), default=None,
              help="Windows per spike train of the unscaled variants (original, force_scaled); default: enough "
                   "for the longest trial in the session.")
@click.option("--windows-scaled", default="20", show_default=True, callback=_windows_scaled,
              help="Windows per spike train of the speed-scaled variants (20 = 2 s at the 120 mm/s reference, the "
                   "paper's), or 'longest': enough for the longest trial in scaled time (whole trials).")
@click.option("--crop-s", type=floats(0, 1e6, min_open=True), default=None, metavar="S",
              help="Cut every trial to its first S seconds before encoding: a common length when trial durations "
                   "differ by texture (a label the padding would carry; the command warns and gives S). Recorded "
                   "in the encoded file's parameters.")
@click.option("--range-from", "range_from", type=click.Path(exists=True, dir_okay=False, path_type=Path), default=None,
              metavar="ENCODED",
              help="Normalise with this encoded file's per-taxel range instead of the session's own (the paper's one "
                   "initial range: a handheld calibration or real-time block with its training block's, "
                   "TRAINING.enc.h5, as the live classifier encodes them).")
@click.option("--no-spikes", is_flag=True, help="Do not store spike trains, only features.")
@progress_option
@click.option("--keep-nonfinite", is_flag=True,
              help="Use trials whose force or speed readings hold NaN or inf (flagged; default: excluded).")
def encode(session, out, overwrite, scheduler, workers, batch, variants, window_ms, windows_unscaled,
           windows_scaled, crop_s, no_spikes, progress, keep_nonfinite, range_from):
    """Encode SESSION: per-taxel normalisation, force coefficients (eq. 1), Izhikevich SA/RA encoding (eqs. 3-5),
    speed scaling (eq. 2) and SR/SC features for the variants original, speed_scaled, force_scaled,
    speed_force_scaled (+ label-free force and real-time variants). The session's sensor layout gives the channel
    count; a session not recorded at 1 kHz is resampled to the model's 1 ms step first (reported, and recorded in
    the encoded file)."""
    from rigctl.encoding.pipeline import EncodeParams, encode_session
    from rigctl.storage.encoded import MAIN_VARIANTS, open_encoded
    from rigctl.storage.outputs import OutputError
    from rigctl.storage.session import SessionError

    out = check_output(out or session.with_name(session.stem + ENCODED_SUFFIX), overwrite=overwrite, inputs=(session,),
                       suffixes=HDF5_SUFFIXES, kind="encoded")
    require_dask(scheduler, otherwise="encode in this process")
    _check_sizes(session, out, variants=list(variants) or None, batch=batch, window_s=window_ms / 1000.0,
                 windows_unscaled=windows_unscaled, windows_scaled=windows_scaled, store_spikes=not no_spikes)
    import warnings

    try:
        params = EncodeParams(window_s=window_ms / 1000.0, n_windows_unscaled=windows_unscaled,
                              n_windows_scaled=windows_scaled, crop_s=crop_s)
        with warnings.catch_warnings(record=True) as caught, bars(show_bars(progress)) as bar:
            warnings.simplefilter("always")
            path = encode_session(session, out, variants=list(variants) or None, batch_trials=batch,
                                  scheduler=scheduler, workers=workers, progress=bar,
                                  store_spikes=() if no_spikes else MAIN_VARIANTS, params=params,
                                  overwrite=overwrite, keep_nonfinite=keep_nonfinite,
                                  taxel_range=_range_of(range_from))
        for w in caught:  # one line each, not Python's file:line form
            click.echo(f"warning: {w.message}", err=True)
    except OutputError:  # another writer took the output meanwhile: refused like any output (exit 2, as export)
        raise
    except (ValueError, KeyError, OSError, SessionError) as exc:
        msg = str(exc.args[0]) if isinstance(exc, KeyError) and exc.args else str(exc)
        raise click.ClickException(" ".join(msg.split())) from None
    with open_encoded(path) as f:
        a = f.attrs
        click.echo(f"wrote {path}: {f.n_trials} trials, {f.layout.n_channels} taxels "
                   f"({f.layout.shape_text}) in {a.get('encode_seconds', 0.0):.1f} s")
        click.echo(f"  rate: {a.get('resampling', 'not recorded')}")
        click.echo(f"  windows: {a.get('windows_note', '')}")
        for v in f.variants:
            click.echo(f"  /features/{v}: {f.feature_shape(v)}")
        if f.skipped_variants:
            click.echo(f"  skipped (see the warnings): {', '.join(f.skipped_variants)}")
        for lf in (False, True):
            name = "force_coefficients_label_free" if lf else "force_coefficients"
            table = f.force_coefficients(label_free=lf)
            if table is not None:
                st = f.force_fit_stats(label_free=lf)
                click.echo(f"  {name}: {st.get('n_not_converged')} of {st.get('n_coefficients')} not converged "
                           f"(largest coefficient {table['coeff'].max():.3g}, cap 5)")
            elif f"{name}_note" in a:
                click.echo(f"  {name}: {a[f'{name}_note']}")
