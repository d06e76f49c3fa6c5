"""``rigctl encode SESSION``: encode a session into SA/RA spike trains and features (paper eqs. 1-5)."""

from __future__ import annotations

from pathlib import Path

import click


@click.command("encode")
@click.argument("session", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--out", "out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Encoded file to write (default: SESSION with suffix .encoded.h5).")
@click.option("--scheduler", default=None,
              help="Dask scheduler address (tcp://host:8786), or 'local' for a local cluster; default: this "
                   "process, numba on all cores.")
@click.option("--workers", type=int, default=None, help="Worker processes for --scheduler local.")
@click.option("--batch", "batch", type=click.IntRange(min=1), default=256, show_default=True,
              help="Trials per batch.")
@click.option("--variant", "variants", multiple=True,
              help="Variant to compute (repeatable); default: all.")
@click.option("--no-spikes", is_flag=True, help="Do not store spike trains, only features.")
@click.option("--quiet", is_flag=True, help="No progress bars.")
def encode(session, out, scheduler, workers, batch, variants, no_spikes, quiet):
    """Encode SESSION: per-taxel normalisation, force coefficients (eq. 1), Izhikevich SA/RA encoding (eqs. 3-5),
    speed scaling (eq. 2) and SR/SC features for the variants original, speed_scaled, force_scaled,
    speed_force_scaled (+ label-free force and real-time variants)."""
    import h5py

    from rigctl.encoding.pipeline import ALL_VARIANTS, MAIN_VARIANTS, encode_session

    bad = [v for v in variants if v not in ALL_VARIANTS]
    if bad:
        raise click.BadParameter(f"unknown {bad}; choose from {', '.join(ALL_VARIANTS)}", param_hint="--variant")
    out = out or session.with_suffix(".encoded.h5")
    try:
        path = encode_session(session, out, variants=variants or ALL_VARIANTS, batch_trials=batch,
                              scheduler=scheduler, workers=workers, progress=not quiet,
                              store_spikes=() if no_spikes else MAIN_VARIANTS)
    except (ValueError, KeyError, OSError) as exc:
        raise click.ClickException(str(exc)) from exc
    with h5py.File(path, "r") as f:
        click.echo(f"wrote {path}: {f.attrs['n_trials']} trials in {f.attrs['encode_seconds']:.1f} s")
        for v in f["features"]:
            click.echo(f"  /features/{v}: {f['features'][v].shape}")
        for name in ("force_coefficients", "force_coefficients_label_free"):
            if name in f:
                a = f[name].attrs
                click.echo(f"  {name}: {a['n_not_converged']} of {a['n_coefficients']} not converged "
                           f"(largest coefficient {f[name]['coeff'].max():.3g}, cap 5)")
            elif f"{name}_note" in f.attrs:
                click.echo(f"  {name}: {f.attrs[f'{name}_note']}")
