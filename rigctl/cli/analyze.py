"""``rigctl analyze``: the paper's PCA + LDA analyses (Fig. 3, Table 1, Fig. 4) on an encoded file."""

from __future__ import annotations

import dataclasses
import sys
import tempfile
from pathlib import Path

import click

from rigctl.cli.jsonout import json_text
from rigctl.cli.outputs import (
    UsageProblem,
    check_output,
    image_suffixes,
    replacing,
    require_dask,
    same_file,
    scheduler_address,
)
from rigctl.cli.progress import bars, progress_option, show_bars
from rigctl.cli.ranges import SEED, WORKERS, comma_floats as _floats

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


def _checked_cv_groups(ctx, param, value):
    """--cv-groups parsed before any work (a usage error, exit 2, naming the option)."""
    if value is not None:
        from rigctl.analysis.grouping import parse_cv_groups

        try:
            parse_cv_groups(value)
        except ValueError as exc:
            raise click.BadParameter(str(exc).split(": ", 1)[-1]) from None
    return value


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


def _load(path, encode, variants, task="table1", progress=False, keep_nonfinite=False):
    """The features of ``path``; a session file is encoded on the fly (into a temporary folder) with ``encode``."""
    from rigctl.analysis.data import NotEncodedError
    from rigctl.operations import load_or_encode

    try:
        return load_or_encode(path, variants, task=task)[0]
    except NotEncodedError as exc:
        if not encode:
            raise click.ClickException(str(exc)) from None
    with tempfile.TemporaryDirectory(prefix="rigctl-analyze-") as tmp:  # the features are read into memory
        click.echo(f"encoding {path} on the fly (rigctl encode) ...", err=True)
        import warnings

        with warnings.catch_warnings(record=True) as caught, bars(progress) as bar:
            warnings.simplefilter("always")
            try:
                loaded = load_or_encode(path, variants, task=task,
                                        encode_to=Path(tmp) / (Path(path).stem + ".encoded.h5"), progress=bar,
                                        keep_nonfinite=keep_nonfinite)[0]
            except (ValueError, KeyError) as exc:  # no usable trial, a variant the trials cannot give: one line
                for w in caught:
                    click.echo(f"warning: {w.message}", err=True)
                msg = str(exc.args[0]) if isinstance(exc, KeyError) and exc.args else str(exc)
                raise click.ClickException(" ".join(msg.split())) from None
        for w in caught:  # one line each (excluded trials, skipped variants), as rigctl encode shows them
            click.echo(f"warning: {w.message}", err=True)
        return loaded


def _import_flags_warning(path) -> None:
    """Warn (one line) when the session an encoded file was encoded from was flagged by its import (files whose trials
    do not follow their presses, outlier periods or trial counts: rigctl.storage.ledger.session_flags): the encoder
    said so, and analyze of the encoded file says it again. A session analysed directly is warned about by the
    encoder; a session no longer found says nothing here."""
    from rigctl.analysis.model import session_of
    from rigctl.storage.ledger import session_flags
    from rigctl.storage.session import SessionError, open_session

    try:
        session, params = session_of(path)
        if params is None:
            return
        with open_session(session) as s:
            flags = session_flags(s.attrs)
    except (OSError, ValueError, KeyError, SessionError):  # (FileBusy is an OSError)
        return
    if flags:
        click.echo(f"warning: {path}: encoded from {session.name}, whose import flagged {len(flags)} file(s) (rigctl "
                   f"info {session.name} lists them): {flags[0]}", err=True)


def _length_warning(path) -> None:
    """Warn (one line) when the encoded file's trial durations differ by texture (rigctl.encoding.lengths): a
    classifier can read the label off the padding. A session encoded on the fly is warned about by the encoder."""
    from rigctl.encoding.lengths import length_imbalance
    from rigctl.storage.encoded import NotEncodedError, open_encoded

    try:
        with open_encoded(path) as f:
            trials = f.trials
            operator_paced = bool(f.attrs.get("operator_paced", False))  # a handheld session's scans
    except (NotEncodedError, OSError, ValueError, KeyError):
        return
    line = length_imbalance(trials["texture"], trials["duration_s"], speed_mm_s=trials.get("speed_mm_s"),
                            force_g=trials.get("force_g"), profile=trials.get("profile"),
                            operator_paced=operator_paced)
    if line:
        click.echo(f"warning: {path}: {line}", err=True)


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


#: the kind of rigctl output each of analyze's output options writes (rigctl.storage.outputs.OUTPUT_KINDS): with
#: --overwrite each replaces only a file of its own kind (never a session, another program's file or a device)
OUTPUT_OPTION_KINDS = {"--csv": "curves", "--plot": "figure", "--confusion": "figure", "--save-model": "model"}


def _check_outputs(file, new_session, overwrite, **outputs):
    """Refuse every output (option -> path) before the analysis runs: existing without --overwrite, an input,
    two outputs on one file, an image format matplotlib does not write, a file that is not a rigctl output of the
    option's kind (:data:`OUTPUT_OPTION_KINDS`)."""
    given = {opt: path for opt, path in outputs.items() if path}
    images = image_suffixes() if given.get("--plot") or given.get("--confusion") else None
    seen = []
    for opt, path in given.items():
        check_output(path, option=opt, overwrite=overwrite, inputs=(file, new_session),
                     suffixes=images if opt in ("--plot", "--confusion") else None, kind=OUTPUT_OPTION_KINDS[opt])
        for other_opt, other in seen:
            if same_file(path, other):
                raise UsageProblem(f"{opt} and {other_opt} both name {path}: give each its own file")
        seen.append((opt, path))



def _check_plot(task, table1_, n_pcs):
    """--plot draws accuracy vs PCs: refused before any work (exit 2) when there is no curve to draw."""
    if task == "variance" and not table1_:
        raise UsageProblem("--plot: --task variance has no accuracy curves; pass --table1 or another --task")
    if n_pcs < 2:
        raise UsageProblem(f"--plot: one PC count ({n_pcs}) draws no curve; pass --pcs 1-N with N >= 2 "
                           "(e.g. --pcs 1-50)")


def _save_model(path, variant, n_pcs, max_pcs, *, source):
    from rigctl.operations import train_model
    from rigctl.storage.encoded import ALL_VARIANTS
    from rigctl.storage.model_file import save_model

    if variant not in ALL_VARIANTS:
        raise click.ClickException(f"--model-variant {variant}: not a variant ({', '.join(ALL_VARIANTS)})")
    try:
        trained = train_model(source, variant, n_pcs, max_pcs=max_pcs)
    except FileNotFoundError as exc:
        raise click.ClickException(f"{exc} (with --encode)") from None
    except ValueError as exc:
        raise click.ClickException(f"--save-model: {exc}") from None
    save_model(trained.model, path, info=trained.info)  # under the output policy
    click.echo(f"saved the {variant} pipeline ({trained.n_pcs} PCs, {trained.n_trials} trials) to {path}", err=True)


def _force_leak(source, variant, *, repeats, seed, n_pcs):
    from rigctl.operations import force_leak_report

    try:
        return force_leak_report(source, variant, n_pcs=n_pcs, repeats=repeats, seed=seed)
    except FileNotFoundError as exc:
        raise click.ClickException(f"{exc} (with --encode)") from None
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
@click.option("--repeats", type=click.IntRange(1, 10_000), default=20, show_default=True, help="Repetitions per task.")
@click.option("--variants", default=None, help="Comma-separated variants (default: all in the file).")
@click.option("--per-texture", type=click.IntRange(2, 10_000_000), default=500, show_default=True,
              help="Trials drawn per texture for textures/groups (scaled down when the data has fewer).")
@click.option("--cv-groups", default=None, metavar="recording|session|block:N", callback=_checked_cv_groups,
              help="textures/groups: folds that never put one group on both sides (StratifiedGroupKFold): each "
                   "source recording, each session, or N time blocks of each recording (default: random folds; "
                   "with one recording per texture the blocked figure is reported beside the random one).")
@click.option("--textures", "textures_", default=None, metavar="A,B,...",
              help="Analyse only these textures (comma-separated labels).")
@click.option("--seed", type=SEED, default=0, show_default=True)
@click.option("--table1", "table1_", is_flag=True, help="Print the paper's Table 1 layout (implies --task all).")
@click.option("--table-pcs", type=click.IntRange(1, 100_000), default=50, show_default=True, help="PC count of the table.")
@click.option("--compare-paper", is_flag=True,
              help="Show the paper's Table 1 values beside ours (in the table and, with --plot, on the figure).")
@click.option("--json", "as_json", is_flag=True, help="Print the results as JSON on stdout.")
@click.option("--plot", type=click.Path(dir_okay=False, writable=True), default=None,
              help="Fig. 3-like plot of accuracy vs PCs (format from the extension: .png, .pdf, .svg, ...).")
@click.option("--confusion", type=click.Path(dir_okay=False, writable=True), default=None,
              help="PNG of confusion matrices (of the first untrained extrapolation cell, else the first task).")
@click.option("--csv", "csv_path", type=click.Path(dir_okay=False, writable=True), default=None, help="Long-format CSV of curves.")
@click.option("--overwrite", is_flag=True, help="Replace existing --csv/--plot/--confusion/--save-model files.")
@click.option("--train-speeds", default=None, help="Trained speeds, mm/s (extrapolation default 40,60,80; "
                                                    "speed-extrapolation: required).")
@click.option("--test-speeds", default=None, help="Untrained speeds tested (default: all others).")
@click.option("--train-forces", default=None, help="Trained forces, g (extrapolation default 250,500).")
@click.option("--n-train", type=click.IntRange(1, 10_000_000), default=75, show_default=True,
              help="Extrapolation: training trials per texture and trained cell (fewer, in proportion, where a cell "
                   "has fewer than --n-train + --n-test).")
@click.option("--n-test", type=click.IntRange(1, 10_000_000), default=25, show_default=True,
              help="Extrapolation: test trials per texture and cell.")
@click.option("--baseline", type=click.Choice(["keep", "remove", "both"]), default="keep", show_default=True,
              help="Per-trial, per-spike-train level removal before PCA (FabricSlide: the level alone separates "
                   "fabrics); 'both' reports both.")
@click.option("--channels", type=click.IntRange(1, 1_000_000), default=None,
              help="Spike trains per trial (for --baseline; default from the file's sensor layout: SA/RA x taxels).")
@click.option("--new-session", type=click.Path(exists=True, dir_okay=False), default=None,
              help="realtime: an encoded second session, classified after mean-centering calibration.")
@click.option("--train-profiles", default="slow,medium", show_default=True, help="realtime: trained profiles.")
@click.option("--realtime-features", "realtime_features", type=click.Choice(["windows", "statistics"]),
              default="windows", show_default=True,
              help="realtime: windows: the paper's features (each taxel's 20 windows); statistics: each taxel's mean, "
                   "spread and change over its windows (place-free: what the live classifier uses by default, "
                   "rigctl acquire --classify-alignment; docs/results.md 3b).")
@click.option("--save-model", type=click.Path(dir_okay=False, writable=True), default=None,
              help="Also fit the raw-trials-to-label pipeline (--model-variant, --model-pcs) on every trial of the "
                   "session and save it (.skops; the GUI's real-time view loads it).")
@click.option("--force-leak", "force_leak_", default=None, metavar="VARIANT",
              help="Also report a force-scaled VARIANT (e.g. speed_force_scaled) with its label-dependent force "
                   "coefficients fitted on all trials (the paper) and within each CV fold, and the difference "
                   "(re-encodes the session per fold).")
@click.option("--model-variant", default="speed_scaled", show_default=True,
              help="Feature variant of the saved model (its pipeline: normalise, [force,] encode, features, PCA+LDA).")
@click.option("--model-pcs", type=click.IntRange(1, 100_000), default=25, show_default=True)
@click.option("--encode", "encode_", is_flag=True, help="If FILE is a session file, encode it first.")
@click.option("--threads", type=WORKERS, default=None,
              help="Limit BLAS threads and repetitions at a time to N (busy machines).")
@click.option("--jobs", type=WORKERS, default=None,
              help="Repetitions run side by side in this process (default: one per core, at most --threads).")
@click.option("--scheduler", default=None, callback=scheduler_address,
              help="Run the repetitions on a Dask cluster: scheduler address (tcp://host:8786), or 'local' for a "
                   "local cluster of --workers processes.")
@click.option("--workers", type=WORKERS, default=None, help="Worker processes for --scheduler local.")
@click.option("--variance", is_flag=True,
              help="Also print where the feature variance lies (texture, condition, interaction, residual; per "
                   "variant). --task variance prints only that.")
@progress_option
@click.option("--keep-nonfinite", is_flag=True,
              help="With --encode: use trials whose force or speed readings hold NaN or inf (default: excluded).")
@click.pass_context
def analyze(ctx, file, task, pcs, repeats, variants, per_texture, seed, table1_, table_pcs, compare_paper, as_json,
            plot, confusion, csv_path, overwrite, train_speeds, test_speeds, train_forces, baseline, channels, new_session,
            train_profiles, realtime_features, save_model, model_variant, model_pcs, encode_, threads, jobs, scheduler, workers, progress,
            keep_nonfinite, variance, force_leak_, cv_groups, textures_, n_train, n_test):
    """Run the paper's PCA + LDA analyses on FILE, an encoded file (``rigctl encode`` output).

    Accuracy is computed for PCs 1..N with one PCA per split; results print as Table 1 (mean and sd over repetitions,
    Welch's t-test / Cohen's d stars vs Original), or as JSON with --json.
    """
    from threadpoolctl import threadpool_limits

    from rigctl.analysis.params import Execution

    _check_outputs(file, new_session, overwrite, **{"--csv": csv_path, "--plot": plot, "--confusion": confusion,
                                                     "--save-model": save_model})
    if plot:
        _check_plot(task, table1_, _parse_pcs(pcs))
    opts = AnalyzeOptions(
        file=file, task="all" if table1_ else task, n_pcs=_parse_pcs(pcs),
        explicit_pcs=ctx.get_parameter_source("pcs") is not click.core.ParameterSource.DEFAULT,
        repeats=repeats, variants=[v.strip() for v in variants.split(",") if v.strip()] if variants else None,
        per_texture=per_texture, seed=seed, table_pcs=table_pcs, compare_paper=compare_paper, as_json=as_json,
        plot=plot, confusion=confusion, csv_path=csv_path, train_speeds=_floats(train_speeds),
        test_speeds=_floats(test_speeds), train_forces=_floats(train_forces), baseline=baseline, channels=channels,
        new_session=new_session, train_profiles=tuple(p.strip() for p in train_profiles.split(",")),
        realtime_features=realtime_features,
        save_model=save_model, model_variant=model_variant, model_pcs=model_pcs, encode=encode_, progress=show_bars(progress),
        keep_nonfinite=keep_nonfinite,
        variance=variance or task == "variance", force_leak=force_leak_, cv_groups=cv_groups, n_train=n_train,
        n_test=n_test,
        textures=[t.strip() for t in textures_.split(",") if t.strip()] if textures_ else None)
    require_dask(scheduler, otherwise="run in this process")
    limiter = threadpool_limits(threads) if threads else None
    execution = Execution(n_jobs=min(jobs, threads) if jobs and threads else (jobs or threads), scheduler=scheduler,
                          workers=workers)
    try:
        _run(opts, execution)
    finally:
        if limiter is not None:
            limiter.unregister()


@dataclasses.dataclass(frozen=True)
class AnalyzeOptions:
    """``rigctl analyze``'s options, parsed (one object instead of 27 arguments)."""

    file: str
    task: str = "all"
    n_pcs: int = 50
    explicit_pcs: bool = False
    repeats: int = 20
    variants: list[str] | None = None
    per_texture: int = 500
    seed: int = 0
    table_pcs: int = 50
    compare_paper: bool = False
    as_json: bool = False
    plot: str | None = None
    confusion: str | None = None
    csv_path: str | None = None
    train_speeds: list[float] | None = None
    test_speeds: list[float] | None = None
    train_forces: list[float] | None = None
    baseline: str = "keep"
    channels: int | None = None
    new_session: str | None = None
    train_profiles: tuple[str, ...] = ("slow", "medium")
    realtime_features: str = "windows"
    save_model: str | None = None
    model_variant: str = "speed_scaled"
    model_pcs: int = 25
    encode: bool = False
    progress: bool = True
    keep_nonfinite: bool = False
    variance: bool = False
    force_leak: str | None = None
    cv_groups: str | None = None
    textures: list[str] | None = None
    n_train: int = 75
    n_test: int = 25


def _plan(opts: AnalyzeOptions, fs):
    """The operator layer's :class:`rigctl.operations.AnalysisPlan` of these options."""
    from rigctl.analysis.params import CVParams, ExtrapolationParams, RealtimeParams, Repetitions
    from rigctl.operations import AnalysisPlan

    if opts.task == "speed-extrapolation":
        if not opts.train_speeds:
            raise click.UsageError("--task speed-extrapolation needs --train-speeds (e.g. 10,20,50)")
        extrapolation = ExtrapolationParams(train_speeds=opts.train_speeds, train_forces=opts.train_forces,
                                            test_speeds=opts.test_speeds, n_train=opts.n_train, n_test=opts.n_test)
    else:
        extrapolation = ExtrapolationParams(train_speeds=opts.train_speeds or (40, 60, 80),
                                            train_forces=opts.train_forces or (250, 500), test_speeds=opts.test_speeds,
                                            n_train=opts.n_train, n_test=opts.n_test)
    other = (_load(opts.new_session, opts.encode, fs.variants, opts.task)
             if opts.task == "realtime" and opts.new_session else None)
    return AnalysisPlan.for_task(
        opts.task, reps=Repetitions(n_pcs=opts.n_pcs, repeats=opts.repeats, seed=opts.seed, variants=opts.variants),
        cv=CVParams(per_texture=opts.per_texture, groups=opts.cv_groups), extrapolation=extrapolation,
        realtime=RealtimeParams(train_profiles=opts.train_profiles, features=opts.realtime_features),
        baseline=opts.baseline, channels=opts.channels,
        new_session=other, on_error="skip" if opts.task == "all" else "raise")


def _run(opts: AnalyzeOptions, execution=None):
    """Load, (variance), analyse, the extras (force leak, model), then write and print."""
    from rigctl.analysis.parallel import connected
    from rigctl.analysis.params import Execution
    from rigctl.analysis.variance import format_variance
    from rigctl.operations import BaselineError, run_analyses

    _check_variants(opts.file, opts.variants)
    fs = _load(opts.file, opts.encode, opts.variants, opts.task, opts.progress, opts.keep_nonfinite)
    _length_warning(opts.file)
    _import_flags_warning(opts.file)
    if opts.textures:
        try:
            fs = fs.select_textures(opts.textures)
        except ValueError as exc:
            raise click.ClickException(str(exc)) from None
    _check_pcs(fs, opts.n_pcs, opts.explicit_pcs)
    if opts.task == "variance":
        only = _variance(fs, opts.variants)
        if opts.as_json:
            click.echo(json_text({"source": str(opts.file), "variance": [r.as_dict() for r in only]}, indent=1))
        else:
            click.echo(format_variance(only))
        return
    shares = _variance(fs, opts.variants) if opts.variance else None
    if shares is not None and not opts.as_json:
        click.echo(format_variance(shares) + "\n")
    plan = _plan(opts, fs)
    execution = execution or Execution()
    with bars(opts.progress, leave=False) as bar, connected(execution.scheduler, execution.workers) as client:
        try:
            res = run_analyses(fs, plan, progress=bar,
                               execution=dataclasses.replace(execution, scheduler=client, workers=None))
        except BaselineError as exc:
            raise click.ClickException(f"--baseline remove: {exc}") from None
        except (ValueError, KeyError) as exc:
            raise click.ClickException(str(exc)) from None
    if not res.curves:  # --task all skipped every task: the reasons are the error
        raise click.ClickException("nothing could be analysed: " + "; ".join(res.warnings))
    leak = _extras(opts)
    _write_outputs(opts, res)
    _print_results(opts, res, shares, leak)


def _extras(opts: AnalyzeOptions):
    """--force-leak (the report) and --save-model (the file)."""
    leak = None
    if opts.force_leak:
        leak = _force_leak(opts.file, opts.force_leak, repeats=min(opts.repeats, 5), seed=opts.seed,
                           n_pcs=min(opts.table_pcs, opts.n_pcs))
    if opts.save_model:
        _save_model(opts.save_model, opts.model_variant, opts.model_pcs, max(opts.model_pcs, opts.n_pcs),
                    source=opts.file)
    return leak


def _write_outputs(opts: AnalyzeOptions, res) -> None:
    from rigctl.analysis import report

    if opts.csv_path:
        with replacing(opts.csv_path, kind="curves", option="--csv") as tmp:
            tmp.write_text(report.to_csv(res))
    if opts.plot:
        if not report.plottable(res):
            raise UsageProblem("--plot: no task has an accuracy curve (fewer than 2 PC counts); pass --pcs 1-N")
        with replacing(opts.plot, kind="figure", option="--plot") as tmp:
            report.plot_curves(res, tmp, title=Path(opts.file).name, compare_paper=opts.compare_paper)
    if opts.confusion:
        keys = list(res.curves)
        pick = next((k for k in keys if k.endswith("untrained_speed_force")), None) or next(
            (k for k in keys if "untrained" in k), keys[0])
        with replacing(opts.confusion, kind="figure", option="--confusion") as tmp:
            report.plot_confusions(res, tmp, pick)


def _print_results(opts: AnalyzeOptions, res, shares, leak) -> None:
    from rigctl.analysis import report

    if opts.as_json:
        if shares is None and leak is None:
            click.echo(report.to_json(res, opts.table_pcs, source=str(opts.file)))
        else:
            out = report.to_dict(res, opts.table_pcs, source=str(opts.file))
            if shares is not None:
                out["variance"] = [r.as_dict() for r in shares]
            if leak is not None:
                out["force_leak"] = leak
            click.echo(json_text(out, indent=1))
    else:
        click.echo(report.format_table1(res, min(opts.table_pcs, opts.n_pcs), compare_paper=opts.compare_paper))
        for extra in (report.format_ordering(res, opts.table_pcs), report.format_collapse(res)):
            if extra:
                click.echo(extra)
        if leak is not None:
            click.echo(_format_leak(leak))
    sys.stdout.flush()
