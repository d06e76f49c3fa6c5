"""``rigctl analyze``: the paper's PCA + LDA analyses (Fig. 3, Table 1, Fig. 4) on an encoded file."""

from __future__ import annotations

import json
import sys
import tempfile
import warnings
from pathlib import Path

import click

from rigctl.cli.outputs import UsageProblem, check_output, image_suffixes, replacing, require_dask, same_file
from rigctl.cli.progress import bars

TASKS = ("textures", "groups", "extrapolation", "speed-extrapolation", "realtime", "all", "variance")


def _parse_pcs(text):
    text = str(text).strip()
    lo, _, hi = text.partition("-")
    try:
        lo_i, hi_i = (1, int(lo)) if not hi else (int(lo), int(hi))
    except ValueError:
        raise click.BadParameter(f"expected N or 1-N, got '{text}'") from None
    if lo_i != 1 or hi_i < 1:
        raise click.BadParameter("PC ranges start at 1 (nested PCs 1..N), e.g. 1-50")
    return hi_i


def _floats(text):
    if text is None:
        return None
    try:
        return [float(x) for x in str(text).split(",") if x.strip()]
    except ValueError:
        raise click.BadParameter(f"expected comma-separated numbers, got '{text}'") from None


def _check_variants(path, variants):
    """Refuse variants the file does not have (a session file to encode: variants the encoder does not know)."""
    if not variants:
        return
    from rigctl.analysis.data import list_variants
    from rigctl.storage.encoded import ALL_VARIANTS

    have = list_variants(path) or list(ALL_VARIANTS)
    bad = [v for v in variants if v not in have]
    if bad:
        raise UsageProblem(f"--variants: {', '.join(bad)} not in {path}; choose from {', '.join(have)}")


def _load(path, encode, variants, task="table1", progress=False):
    from rigctl.analysis.data import NotEncodedError, default_variants, list_variants, load_features

    try:
        if variants is None and list_variants(path):
            variants = default_variants(list_variants(path), task)
        return load_features(path, variants)
    except NotEncodedError as exc:
        if not encode:
            raise click.ClickException(str(exc)) from None
    try:
        from rigctl.encoding.pipeline import encode_session
    except ImportError as exc:  # pragma: no cover - depends on the encoding package
        raise click.ClickException(f"cannot encode on the fly: rigctl.encoding.pipeline unavailable ({exc})") from None
    with tempfile.TemporaryDirectory(prefix="rigctl-analyze-") as tmp:  # the features are read into memory
        out = Path(tmp) / (Path(path).stem + ".encoded.h5")
        click.echo(f"encoding {path} on the fly (rigctl encode) ...", err=True)
        with bars(progress) as bar:
            encode_session(path, out, progress=bar)
        return load_features(out, variants or default_variants(list_variants(out), task))


def _variance(fs, variants):
    from rigctl.analysis.variance import decompose_all

    try:
        return decompose_all(fs, variants)
    except (ValueError, KeyError) as exc:
        raise click.ClickException(f"--variance: {exc}") from None


def _check_pcs(fs, n_pcs, explicit):
    """PC counts 1..n_pcs must fit the data: at most one PC per trial and per feature."""
    n_features = min(f.shape[1] for f in fs.features.values())
    allowed = min(n_features, fs.n_trials)
    if explicit and n_pcs > allowed:
        raise UsageProblem(f"--pcs 1-{n_pcs}: the data allows 1-{allowed} ({fs.n_trials} trials, {n_features} "
                           "features per trial)")


def _check_outputs(file, new_session, overwrite, **outputs):
    """Refuse every output (option -> path) before the analysis runs: existing without --overwrite, an input,
    two outputs on one file, an image format matplotlib does not write."""
    given = {opt: path for opt, path in outputs.items() if path}
    images = image_suffixes() if given.get("--plot") or given.get("--confusion") else None
    seen = []
    for opt, path in given.items():
        check_output(path, option=opt, overwrite=overwrite, inputs=(file, new_session),
                     suffixes=images if opt in ("--plot", "--confusion") else None)
        for other_opt, other in seen:
            if same_file(path, other):
                raise UsageProblem(f"{opt} and {other_opt} both name {path}: give each its own file")
        seen.append((opt, path))



def _session_and_params(file):
    from rigctl.analysis.model import session_of

    try:
        return session_of(file)
    except FileNotFoundError as exc:
        raise click.ClickException(f"{exc} (with --encode)") from None


def _save_model(path, session, params, variant, n_pcs, max_pcs, *, source):
    from rigctl.analysis.model import model_info, texture_pipeline, trials_of_session
    from rigctl.storage.encoded import ALL_VARIANTS
    from rigctl.storage.model_file import save_model

    if variant not in ALL_VARIANTS:
        raise click.ClickException(f"--model-variant {variant}: not a variant ({', '.join(ALL_VARIANTS)})")
    trials, texture = trials_of_session(session)
    try:
        model = texture_pipeline(variant, n_pcs, max_pcs=max_pcs, params=params).fit(trials, texture)
    except ValueError as exc:
        raise click.ClickException(f"--save-model: {exc}") from None
    with replacing(path) as tmp:
        save_model(model, tmp, info=model_info(model, session=session, analysed=source))
    click.echo(f"saved the {variant} pipeline ({model[-1].n_pcs_} PCs, {len(trials)} trials) to {path}", err=True)


def _force_leak(session, params, variant, *, repeats, seed, n_pcs):
    from rigctl.analysis.model import force_leak, trials_of_session

    trials, texture = trials_of_session(session)
    try:
        return force_leak(trials, texture, variant=variant, n_pcs=n_pcs, repeats=repeats, seed=seed, params=params)
    except (ValueError, KeyError) as exc:
        raise click.ClickException(f"--force-leak {variant}: {exc}") from None


def _format_leak(leak) -> str:
    return (f"\nForce coefficients (eq. 1) of {leak['variant']}, {leak['n_pcs']} PCs, {leak['folds']}-fold CV x "
            f"{leak['repeats']}:\n"
            f"  fitted on all trials (the paper; test labels leak in): {100 * leak['fitted_on_all']:.1f} %\n"
            f"  fitted per fold (training trials only):                {100 * leak['per_fold']:.1f} %\n"
            f"  leak: {100 * leak['leak']:+.1f} points")

@click.command("analyze")
@click.argument("file", type=click.Path(exists=True, dir_okay=False))
@click.option("--task", type=click.Choice(TASKS), default="all", show_default=True,
              help="Analysis: Fig. 3A textures, 3B groups, 3C-F extrapolation, speed-only extrapolation, Fig. 4 "
                   "real-time; 'all' = the six rows of Table 1.")
@click.option("--pcs", default="1-50", show_default=True, help="PC counts 1-N (PCA fitted once per split).")
@click.option("--repeats", type=click.IntRange(1), default=20, show_default=True, help="Repetitions per task.")
@click.option("--variants", default=None, help="Comma-separated variants (default: all in the file).")
@click.option("--per-texture", type=click.IntRange(2), default=500, show_default=True,
              help="Trials drawn per texture for textures/groups (scaled down when the data has fewer).")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--table1", "table1_", is_flag=True, help="Print the paper's Table 1 layout (implies --task all).")
@click.option("--table-pcs", type=click.IntRange(1), default=50, show_default=True, help="PC count of the table.")
@click.option("--compare-paper", is_flag=True, help="Show the paper's Table 1 values beside ours.")
@click.option("--json", "as_json", is_flag=True, help="Print the results as JSON on stdout.")
@click.option("--plot", type=click.Path(dir_okay=False), default=None,
              help="Fig. 3-like plot of accuracy vs PCs (format from the extension: .png, .pdf, .svg, ...).")
@click.option("--confusion", type=click.Path(dir_okay=False), default=None,
              help="PNG of confusion matrices (of the first untrained extrapolation cell, else the first task).")
@click.option("--csv", "csv_path", type=click.Path(dir_okay=False), default=None, help="Long-format CSV of curves.")
@click.option("--overwrite", is_flag=True, help="Replace existing --csv/--plot/--confusion/--save-model files.")
@click.option("--train-speeds", default=None, help="Trained speeds, mm/s (extrapolation default 40,60,80; "
                                                    "speed-extrapolation: required).")
@click.option("--test-speeds", default=None, help="Untrained speeds tested (default: all others).")
@click.option("--train-forces", default=None, help="Trained forces, g (extrapolation default 250,500).")
@click.option("--baseline", type=click.Choice(["keep", "remove", "both"]), default="keep", show_default=True,
              help="Per-trial, per-spike-train level removal before PCA (FabricSlide: the level alone separates "
                   "fabrics); 'both' reports both.")
@click.option("--channels", type=int, default=None,
              help="Spike trains per trial (for --baseline; default from the file's sensor layout: SA/RA x taxels).")
@click.option("--new-session", type=click.Path(exists=True, dir_okay=False), default=None,
              help="realtime: an encoded second session, classified after mean-centering calibration.")
@click.option("--train-profiles", default="slow,medium", show_default=True, help="realtime: trained profiles.")
@click.option("--save-model", type=click.Path(dir_okay=False), default=None,
              help="Also fit the raw-trials-to-label pipeline (--model-variant, --model-pcs) on every trial of the "
                   "session and save it (.skops; the GUI's real-time view loads it).")
@click.option("--force-leak", "force_leak_", default=None, metavar="VARIANT",
              help="Also report a force-scaled VARIANT (e.g. speed_force_scaled) with its label-dependent force "
                   "coefficients fitted on all trials (the paper) and within each CV fold, and the difference "
                   "(re-encodes the session per fold).")
@click.option("--model-variant", default="speed_scaled", show_default=True,
              help="Feature variant of the saved model (its pipeline: normalise, [force,] encode, features, PCA+LDA).")
@click.option("--model-pcs", type=click.IntRange(1), default=25, show_default=True)
@click.option("--encode", "encode_", is_flag=True, help="If FILE is a session file, encode it first.")
@click.option("--threads", type=click.IntRange(1), default=None,
              help="Limit BLAS threads and repetitions at a time to N (busy machines).")
@click.option("--jobs", type=click.IntRange(1), default=None,
              help="Repetitions run side by side in this process (default: one per core, at most --threads).")
@click.option("--scheduler", default=None,
              help="Run the repetitions on a Dask cluster: scheduler address (tcp://host:8786), or 'local' for a "
                   "local cluster of --workers processes.")
@click.option("--workers", type=click.IntRange(1), default=None, help="Worker processes for --scheduler local.")
@click.option("--variance", is_flag=True,
              help="Also print where the feature variance lies (texture, condition, interaction, residual; per "
                   "variant). --task variance prints only that.")
@click.option("--progress/--no-progress", default=True, show_default=True)
@click.pass_context
def analyze(ctx, file, task, pcs, repeats, variants, per_texture, seed, table1_, table_pcs, compare_paper, as_json,
            plot, confusion, csv_path, overwrite, train_speeds, test_speeds, train_forces, baseline, channels, new_session,
            train_profiles, save_model, model_variant, model_pcs, encode_, threads, jobs, scheduler, workers, progress,
            variance, force_leak_):
    """Run the paper's PCA + LDA analyses on FILE, an encoded file (``rigctl encode`` output).

    Accuracy is computed for PCs 1..N with one PCA per split; results print as Table 1 (mean and sd over repetitions,
    Welch's t-test / Cohen's d stars vs Original), or as JSON with --json.
    """
    from threadpoolctl import threadpool_limits

    _check_outputs(file, new_session, overwrite, **{"--csv": csv_path, "--plot": plot, "--confusion": confusion,
                                                     "--save-model": save_model})
    explicit_pcs = ctx.get_parameter_source("pcs") is not click.core.ParameterSource.DEFAULT
    require_dask(scheduler, otherwise="run in this process")
    limiter = threadpool_limits(threads) if threads else None
    par = {"n_jobs": min(jobs, threads) if jobs and threads else (jobs or threads), "scheduler": scheduler,
           "workers": workers}
    try:
        _run(file, task, pcs, repeats, variants, per_texture, seed, table1_, table_pcs, compare_paper, as_json, plot,
             confusion, csv_path, train_speeds, test_speeds, train_forces, baseline, channels, new_session,
             train_profiles, save_model, model_variant, model_pcs, encode_, progress, explicit_pcs,
             variance=variance or task == "variance", par=par, force_leak_=force_leak_)
    finally:
        if limiter is not None:
            limiter.unregister()


def _run(file, task, pcs, repeats, variants, per_texture, seed, table1_, table_pcs, compare_paper, as_json, plot,
         confusion, csv_path, train_speeds, test_speeds, train_forces, baseline, channels, new_session,
         train_profiles, save_model, model_variant, model_pcs, encode_, progress, explicit_pcs=False,
         variance=False, par=None, force_leak_=None):
    from rigctl.analysis import report, tasks

    n_pcs = _parse_pcs(pcs)
    vlist = [v.strip() for v in variants.split(",") if v.strip()] if variants else None
    if table1_:
        task = "all"
    _check_variants(file, vlist)
    fs = _load(file, encode_, vlist, task, progress)
    _check_pcs(fs, n_pcs, explicit_pcs)
    from rigctl.analysis.variance import format_variance

    shares = _variance(fs, vlist) if variance else None
    if task == "variance":
        if as_json:
            click.echo(json.dumps({"source": str(file), "variance": [r.as_dict() for r in shares]}, indent=1))
        else:
            click.echo(format_variance(shares))
        return
    if shares is not None and not as_json:
        click.echo(format_variance(shares) + "\n")
    if task == "speed-extrapolation" and not train_speeds:
        raise click.UsageError("--task speed-extrapolation needs --train-speeds (e.g. 10,20,50)")

    runs = [("", fs)]
    if baseline in ("remove", "both"):
        try:  # spike trains per trial: --channels, else from the file's sensor layout (SA/RA x channels)
            fs_b = fs.without_baseline(channels)
        except ValueError as exc:
            raise click.ClickException(f"--baseline remove: {exc}") from None
        runs = [("", fs), ("baseline_removed:", fs_b)] if baseline == "both" else [("baseline_removed:", fs_b)]

    from rigctl.analysis.parallel import connected

    par = dict(par or {})
    res_all = tasks.TaskResults()
    with warnings.catch_warnings(record=True) as caught, bars(progress, leave=False) as bar, \
            connected(par.pop("scheduler", None), par.pop("workers", None)) as client:
        par["scheduler"] = client
        warnings.simplefilter("always")
        for tag, data in runs:
            res = tasks.TaskResults()
            try:
                if task in ("textures", "groups", "all"):
                    wanted = ("textures", "groups") if task == "all" else (task,)
                    if task == "all" and data.group is None:
                        wanted = ("textures",)
                        res.warnings.append(f"groups task skipped: the texture set {data.textures.name!r} defines "
                                            "no texture groups" if data.textures.name else
                                            "groups task skipped: the file's texture set defines no texture groups")
                    res.merge(tasks.run_cv(data, wanted, variants=vlist, n_pcs=n_pcs, repeats=repeats,
                                           per_texture=per_texture, seed=seed, progress=bar, **par))
                if task in ("extrapolation", "all"):
                    res.merge(tasks.run_extrapolation(
                        data, train_speeds=_floats(train_speeds) or (40, 60, 80),
                        train_forces=_floats(train_forces) or (250, 500), test_speeds=_floats(test_speeds),
                        variants=vlist, n_pcs=n_pcs, repeats=repeats, seed=seed, progress=bar, **par))
                if task == "speed-extrapolation":
                    res.merge(tasks.run_extrapolation(
                        data, train_speeds=_floats(train_speeds), train_forces=_floats(train_forces),
                        test_speeds=_floats(test_speeds), variants=vlist, n_pcs=n_pcs, repeats=repeats, seed=seed,
                        progress=bar, prefix="speed_", **par))
                if task == "realtime":
                    other = _load(new_session, encode_, fs.variants, task) if new_session else None
                    res.merge(tasks.run_realtime(
                        data, new_session=other, train_profiles=[p.strip() for p in train_profiles.split(",")],
                        variants=vlist, n_pcs=n_pcs, repeats=repeats, seed=seed, progress=bar))
            except (ValueError, KeyError) as exc:
                raise click.ClickException(str(exc)) from None
            for t, by_v in res.curves.items():
                for c in by_v.values():
                    c.task = tag + t
                    res_all.add(c)
            res_all.counts.update({tag + k: v for k, v in res.counts.items()})
            res_all.warnings.extend(tag + w for w in res.warnings)
            res_all.settings.update(res.settings)
    del caught  # shown through res.warnings (in the table / JSON)

    leak = None
    if force_leak_ or save_model:
        session, params = _session_and_params(file)
    if force_leak_:
        leak = _force_leak(session, params, force_leak_, repeats=min(repeats, 5), seed=seed,
                           n_pcs=min(table_pcs, n_pcs))
    if save_model:
        _save_model(save_model, session, params, model_variant, model_pcs, max(model_pcs, n_pcs), source=file)

    if csv_path:
        with replacing(csv_path) as tmp:
            tmp.write_text(report.to_csv(res_all))
    if plot:
        with replacing(plot) as tmp:
            report.plot_curves(res_all, tmp, title=Path(file).name)
    if confusion:
        keys = list(res_all.curves)
        pick = next((k for k in keys if k.endswith("untrained_speed_force")), None) or next(
            (k for k in keys if "untrained" in k), keys[0])
        with replacing(confusion) as tmp:
            report.plot_confusions(res_all, tmp, pick)
    if as_json:
        if shares is None and leak is None:
            click.echo(report.to_json(res_all, table_pcs, source=str(file)))
        else:
            out = report.to_dict(res_all, table_pcs, source=str(file))
            if shares is not None:
                out["variance"] = [r.as_dict() for r in shares]
            if leak is not None:
                out["force_leak"] = leak
            click.echo(json.dumps(out, indent=1, default=float))
    else:
        click.echo(report.format_table1(res_all, table_pcs, compare_paper=compare_paper))
        ordering = report.format_ordering(res_all, table_pcs)
        if ordering:
            click.echo(ordering)
        collapse = report.format_collapse(res_all)
        if collapse:
            click.echo(collapse)
        if leak is not None:
            click.echo(_format_leak(leak))
    sys.stdout.flush()
