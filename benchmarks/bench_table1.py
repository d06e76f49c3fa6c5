"""Benchmark: the whole Table 1 (6 tasks x 4 variants x 50 PCs x 20 repetitions) on paper-sized feature matrices.

Input: random float32 matrices of the paper's size (24,000 x 2160 for Original / Force Scaled, 24,000 x 720 for the
speed-scaled variants) with the paper's label layout, the unscaled variants zero-padded as the encoder pads them (a
trial at v mm/s fills 2400 / v of its 60 windows; ``--no-padding``: dense, as before issue 57), or an encoded file's
features (``--features FILE``); tasks A/B draw 8000-trial subsamples with 4-fold CV, the extrapolation task trains on
7200 trials.

Side by side in the same run (issue 57): one repetition on one core with every column in one Gram block (the dense
path) and with the zero padding's groups (:func:`rigctl.analysis.splitpca.zero_padding`), alternated, best of 2, with
the largest accuracy difference. Target (issue 12): under 3 minutes on 2 cores (was 7.8 min with one
scikit-learn randomized PCA per split).

Side by side in the same run: one repetition of the previous path (a scikit-learn randomized PCA per fold and split,
:func:`rigctl.analysis.classify.fit_pca`) against the fast path (shared Gram blocks + subspace iteration,
:mod:`rigctl.analysis.splitpca`), timed in CPU seconds, with the largest accuracy difference between the two.

Also, on a smaller case in the same run, the nested approach (one PCA per split, all 50 LDAs from one Cholesky
factor) against the naive one (a scikit-learn PCA(n) + LinearDiscriminantAnalysis refit for every n = 1..50),
reported side by side as a ratio, with a check that both give the same accuracies.

    python benchmarks/bench_table1.py                 # full Table 1, paper-sized
    python benchmarks/bench_table1.py --repeats 2     # quicker
    python benchmarks/bench_table1.py --jobs 1        # repetitions one at a time (BLAS threads on every core)
    python benchmarks/bench_table1.py --features paper.encoded.h5 --skip-naive   # the simulated paper's features
    python benchmarks/bench_table1.py --features paper.encoded.h5 --skip-naive --skip-full --against /tmp/prev
        # and the whole Table 1 against another commit's rigctl (git archive COMMIT rigctl | tar -x -C /tmp/prev)

Side by side in the same run (issue 57, second step): one repetition with every subspace iteration from a random
start and the extrapolation's Gram matrix from its training trials, against the later folds warm-started and the
extrapolation's Gram matrix as the trained cells' (formed once) less the held-out trials'.
"""

from __future__ import annotations

import argparse
import os
import time
import warnings

import numpy as np


def naive_vs_nested(n_trials=2400, n_features=720, n_pcs=50, seed=0):
    from sklearn.decomposition import PCA
    from sklearn.discriminant_analysis import LinearDiscriminantAnalysis

    from rigctl.analysis.classify import nested_pc_predictions
    from rigctl.analysis.synthetic import random_features

    fs = random_features(n_trials, (n_features,) * 4, seed=seed)
    x, y = fs.features["speed_scaled"], fs.texture
    n_trials = len(y)
    rng = np.random.default_rng(seed)
    perm = rng.permutation(n_trials)
    tr, te = perm[: 3 * n_trials // 4], perm[3 * n_trials // 4 :]
    t0 = time.perf_counter()
    pred, _ = nested_pc_predictions(x[tr], y[tr], x[te], n_pcs, random_state=0)
    t_nested = time.perf_counter() - t0
    # the equality check uses the exact (full SVD) PCA: the randomized one differs slightly in the trailing PCs
    from rigctl.analysis.classify import fit_pca

    exact = fit_pca(x[tr], n_pcs, svd_solver="full")
    acc_nested = (nested_pc_predictions(x[tr], y[tr], x[te], n_pcs, pca=exact)[0] == y[te]).mean(axis=1)
    t0 = time.perf_counter()
    acc_naive = []
    for n in range(1, n_pcs + 1):
        pca = PCA(n, svd_solver="full").fit(x[tr])  # what a straightforward implementation does
        lda = LinearDiscriminantAnalysis().fit(pca.transform(x[tr]), y[tr])
        acc_naive.append(np.mean(lda.predict(pca.transform(x[te])) == y[te]))
    t_naive = time.perf_counter() - t0
    return t_nested, t_naive, float(np.max(np.abs(acc_nested - np.asarray(acc_naive))))


def one_repetition_side_by_side(fs, n_pcs, r=0):
    """CPU seconds of repetition ``r`` (CV folds + extrapolation split, every variant) by the previous per-split
    scikit-learn PCA and by the fast path, and the largest accuracy difference between them."""
    from rigctl.analysis.classify import NestedLDA, fit_pca
    from rigctl.analysis.splitpca import split_scores
    from rigctl.analysis.tasks import cv_split, extrapolation_split

    idx, folds = cv_split(fs.texture, 500, 4, seed=0, repeat=r)
    tr_x, te_x, _ = extrapolation_split(fs, seed=0, repeat=r)
    rows = np.concatenate([tr_x, te_x])
    ext = [(np.arange(len(tr_x)), np.arange(len(tr_x), len(rows)))]
    acc = {"sklearn": [], "fast": []}
    cpu = {}
    for name in acc:
        c0 = time.process_time()
        for x in fs.features.values():
            for sub, splits, kfold in ((idx, folds, True), (rows, ext, False)):
                xs, y = x[sub], fs.texture[sub]
                if name == "sklearn":
                    pcas = [fit_pca(xs[tr], n_pcs, random_state=r) for tr, _ in splits]
                    scores = [(p.transform(xs[tr]), p.transform(xs[te])) for p, (tr, te) in zip(pcas, splits)]
                else:
                    scores = split_scores(xs, splits, n_pcs, random_states=[r] * len(splits), kfold=kfold)
                for (tr, te), (z_tr, z_te) in zip(splits, scores):
                    pred = NestedLDA().fit(z_tr, y[tr]).predict_all(z_te)
                    acc[name].append((pred == y[te]).mean(axis=1))
        cpu[name] = time.process_time() - c0
    diff = max(float(np.abs(a - b).max()) for a, b in zip(acc["sklearn"], acc["fast"]))
    return cpu, diff


def dense_vs_grouped(fs, n_pcs, r=0):
    """CPU seconds of repetition ``r`` (CV folds + extrapolation split, every variant) with every column in one Gram
    block (the dense path, as before issue 57) and with the zero padding's groups
    (:func:`rigctl.analysis.splitpca.zero_padding`), alternated, best of 2; and the largest accuracy difference."""
    from rigctl.analysis.classify import NestedLDA
    from rigctl.analysis.splitpca import split_scores, zero_padding
    from rigctl.analysis.tasks import cv_split, extrapolation_split

    idx, folds = cv_split(fs.texture, 500, 4, seed=0, repeat=r)
    tr_x, te_x, _ = extrapolation_split(fs, seed=0, repeat=r)
    rows = np.concatenate([tr_x, te_x])
    ext = [(np.arange(len(tr_x)), np.arange(len(tr_x), len(rows)))]
    from rigctl.analysis.tasks import _padding_labels

    pads = {v: zero_padding(x, _padding_labels(fs)) for v, x in fs.features.items()}
    acc = {"dense": [], "grouped": []}
    cpu = {"dense": np.inf, "grouped": np.inf}
    for turn in range(2):
        for name in acc:
            c0 = time.process_time()
            for v, x in fs.features.items():
                for sub, splits, kfold in ((idx, folds, True), (rows, ext, False)):
                    xs, y = x[sub], fs.texture[sub]
                    pad = ((np.arange(x.shape[1]), np.full(len(sub), x.shape[1])) if name == "dense"
                           else (pads[v][0], pads[v][1][sub]))
                    scores = split_scores(xs, splits, n_pcs, random_states=[r] * len(splits), kfold=kfold,
                                          padding=pad)
                    for (tr, te), (z_tr, z_te) in zip(splits, scores):
                        pred = NestedLDA().fit(z_tr, y[tr]).predict_all(z_te)
                        if turn == 0:
                            acc[name].append((pred == y[te]).mean(axis=1))
            cpu[name] = min(cpu[name], time.process_time() - c0)
    diff = max(float(np.abs(a - b).max()) for a, b in zip(acc["dense"], acc["grouped"]))
    return cpu, diff


def cold_vs_warm(fs, n_pcs, r=0):
    """CPU seconds of repetition ``r`` (CV folds + extrapolation split, every variant) by the path before issue 57's
    second step (every subspace iteration from a random start, the extrapolation's Gram matrix from its 7,200
    training trials) and the fast path (the later folds warm-started from the first, the extrapolation from the
    trained cells' Gram matrix, formed once, less the held-out trials': :class:`rigctl.analysis.splitpca.GramBase`),
    alternated, best of 2; the bases' one-off CPU seconds (per variant, for all 20 repetitions); the largest
    accuracy difference. Both with the same NestedLDA."""
    from rigctl.analysis.classify import NestedLDA
    from rigctl.analysis.splitpca import split_scores
    from rigctl.analysis.tasks import _extrapolation_plan, _paddings, _trained_bases, cv_split, extrapolation_split

    idx, folds = cv_split(fs.texture, 500, 4, seed=0, repeat=r)
    tr_x, te_x, _ = extrapolation_split(fs, seed=0, repeat=r)
    pads = _paddings(fs, list(fs.features))
    cells, trained_cells, *_ = _extrapolation_plan(fs, (40, 60, 80), (250, 500), None, None, 75, 25)
    c0 = time.process_time()
    bases = _trained_bases(fs, list(fs.features), pads, cells, trained_cells, 75, 20, n_pcs, 0)
    cpu_bases = time.process_time() - c0
    rows = np.concatenate([tr_x, te_x])
    if bases:
        rows = np.concatenate([rows, np.setdiff1d(next(iter(bases.values())).rows, rows)])
    ext = [(np.arange(len(tr_x)), np.arange(len(tr_x), len(tr_x) + len(te_x)))]
    acc = {"previous": [], "fast": []}
    cpu = {"previous": np.inf, "fast": np.inf}
    for turn in range(2):
        for name in acc:
            fast = name == "fast"
            c0 = time.process_time()
            for v, x in fs.features.items():
                for sub, splits, kfold in ((idx, folds, True), (rows, ext, False)):
                    y = fs.texture[sub]
                    scores = split_scores(x, splits, n_pcs, random_states=[r] * len(splits), kfold=kfold,
                                          padding=(pads[v][0], pads[v][1][sub]), rows=sub, warm_start=fast,
                                          base=bases.get(v) if fast else None)
                    for (tr, te), (z_tr, z_te) in zip(splits, scores):
                        pred = NestedLDA().fit(z_tr, y[tr]).predict_all(z_te)
                        if turn == 0:
                            acc[name].append((pred == y[te]).mean(axis=1))
            cpu[name] = min(cpu[name], time.process_time() - c0)
    diff = max(float(np.abs(a - b).max()) for a, b in zip(acc["previous"], acc["fast"]))
    return cpu, cpu_bases, diff


def whole_table_against(features, checkout, rounds, args=()):
    """The whole Table 1 (``rigctl analyze FEATURES --table1 --json``, one process each, as a user runs it) by this
    checkout's rigctl and by ``checkout``'s (a directory holding another commit's ``rigctl`` package: put first on
    PYTHONPATH), alternated ``rounds`` times: wall, CPU seconds of the process, its peak RSS, the load average, and
    how far the accuracy curves (mean over the repetitions at PCs 1..50, every task and variant) moved, in units of
    their repetition SD. ``args``: more options of ``rigctl analyze`` (e.g. ``--repeats 2 --pcs 5`` on a small file:
    the start alone, docs/results.md 5q)."""
    import json
    import subprocess
    import sys
    import tempfile

    runs = {"previous": [], "this": []}
    curves = {}
    envs = {}
    cache = tempfile.mkdtemp(prefix="bench_table1_pycache_")  # byte code written and reused, as an installed package's
    for name in runs:
        env = dict(os.environ, PYTHONPYCACHEPREFIX=cache)
        env.pop("PYTHONDONTWRITEBYTECODE", None)
        if name == "previous":
            env["PYTHONPATH"] = os.pathsep.join([os.path.abspath(checkout)] + env.get("PYTHONPATH", "").split(
                os.pathsep)).rstrip(os.pathsep)
        subprocess.run([sys.executable, "-c", "import rigctl.cli, rigctl.analysis.tasks, rigctl.operations"], env=env,
                       check=True, cwd=tempfile.gettempdir())  # (compiled once, not timed)
        envs[name] = env
    for _ in range(rounds):
        for name in runs:
            env = envs[name]
            load0 = os.getloadavg()[0]
            with tempfile.TemporaryFile("w+") as out:
                t0 = time.perf_counter()
                proc = subprocess.Popen([sys.executable, "-m", "rigctl", "analyze", features, "--table1", "--json",
                                         *args], stdout=out, stderr=subprocess.DEVNULL, env=env, cwd=tempfile.gettempdir())
                _, status, ru = os.wait4(proc.pid, 0)
                wall = time.perf_counter() - t0
                out.seek(0)
                if status != 0:
                    raise SystemExit(f"{name}: rigctl analyze failed (status {status})")
                curves[name] = json.load(out)["tasks"]
            runs[name].append((wall, ru.ru_utime + ru.ru_stime, ru.ru_maxrss / 1e6, load0, os.getloadavg()[0]))
            print(f"  {name}: {wall:.1f} s wall, {runs[name][-1][1]:.1f} CPU-s, peak RSS {runs[name][-1][2]:.2f} GB, "
                  f"load {load0:.1f} -> {runs[name][-1][4]:.1f}", flush=True)
    worst, worst_at = 0.0, None
    for task, t in curves["this"].items():
        for v, c in t["variants"].items():
            p = curves["previous"][task]["variants"][v]
            m, mp, sd = np.array(c["mean"]), np.array(p["mean"]), np.array(p["sd"])
            z = np.abs(m - mp) / np.maximum(sd, 1e-12)
            if z.max() > worst:
                worst, worst_at = float(z.max()), (task, v, int(z.argmax()) + 1, 100 * mp[z.argmax()],
                                                   100 * m[z.argmax()], 100 * sd[z.argmax()])
    return runs, worst, worst_at


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trials", type=int, default=24_000)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--pcs", type=int, default=50)
    ap.add_argument("--threads", type=int, default=None, help="BLAS threads (default: library default)")
    ap.add_argument("--jobs", type=int, default=None, help="repetitions side by side (default: one per core)")
    ap.add_argument("--skip-full", action="store_true",
                    help="only the dense vs grouped repetition (no scikit-learn repetition, no whole Table 1)")
    ap.add_argument("--skip-naive", action="store_true", help="skip the naive per-PC-count refit comparison")
    ap.add_argument("--features", help="an encoded file (rigctl encode): its features instead of random ones")
    ap.add_argument("--against", metavar="DIR",
                    help="with --features: the whole Table 1 by this checkout and by DIR's rigctl package (another "
                         "commit's, e.g. `git archive COMMIT rigctl | tar -x -C DIR`), alternated, one process each")
    ap.add_argument("--rounds", type=int, default=1, help="alternations of --against")
    ap.add_argument("--analyze-args", default="", help="more options of the --against runs' `rigctl analyze`, e.g. "
                    "'--repeats 2 --pcs 5' (with a small --features file: the start alone)")
    ap.add_argument("--no-padding", action="store_true",
                    help="random features without the unscaled variants' zero padding (as before issue 57)")
    args = ap.parse_args()

    from threadpoolctl import threadpool_info, threadpool_limits

    if args.threads:
        threadpool_limits(args.threads)
    from rigctl.analysis.synthetic import random_features
    from rigctl.analysis.tasks import run_table1
    from rigctl.cli.progress import TqdmProgress

    print(f"cores: {os.cpu_count()}, BLAS: {[(i['internal_api'], i['num_threads']) for i in threadpool_info()]}, "
          f"load average at start: {os.getloadavg()}")
    if not args.skip_naive:
        t_nested, t_naive, dmax = naive_vs_nested(n_pcs=args.pcs)
        print(f"one split, 1800 train / 600 test x 720 features, PCs 1..{args.pcs}: nested {t_nested:.2f} s, "
              f"naive per-PC refit {t_naive:.2f} s, ratio naive/nested = {t_naive / t_nested:.1f}x, "
              f"max accuracy difference {dmax:.4f}", flush=True)
    t0 = time.perf_counter()
    if args.features:
        from rigctl.analysis.data import default_variants, list_variants, load_features

        fs = load_features(args.features, default_variants(list_variants(args.features)))  # Table 1's variants
    else:
        fs = random_features(args.trials, seed=1, zero_pad=not args.no_padding)
    t_gen = time.perf_counter() - t0
    print(f"features: {', '.join(f'{k} {v.shape}' for k, v in fs.features.items())} "
          f"({'read' if args.features else 'made'} in {t_gen:.1f} s; non-zero: "
          f"{', '.join(f'{k} {np.count_nonzero(v) / v.size:.2f}' for k, v in fs.features.items())})")
    with threadpool_limits(1):  # CPU seconds of one core each (a spinning second BLAS thread would count too)
        cpu_g, diff_g = dense_vs_grouped(fs, args.pcs)
    print(f"one repetition on one core, dense Gram blocks {cpu_g['dense']:.2f} CPU-s, zero padding's groups "
          f"{cpu_g['grouped']:.2f} CPU-s: ratio {cpu_g['dense'] / cpu_g['grouped']:.2f}x (best of 2, alternated); "
          f"largest accuracy difference {100 * diff_g:.2f} points (load average {os.getloadavg()[0]:.2f})",
          flush=True)
    with threadpool_limits(1):
        cpu_w, cpu_b, diff_w = cold_vs_warm(fs, args.pcs)
    print(f"one repetition on one core, random starts and the extrapolation's own Gram matrix {cpu_w['previous']:.2f} "
          f"CPU-s, warm starts and the trained cells' base {cpu_w['fast']:.2f} CPU-s (+ {cpu_b:.2f} CPU-s once for the "
          f"bases, {cpu_b / 20:.2f} a repetition of 20): ratio {cpu_w['previous'] / (cpu_w['fast'] + cpu_b / 20):.2f}x "
          f"(best of 2, alternated); largest accuracy difference {100 * diff_w:.2f} points "
          f"(load average {os.getloadavg()[0]:.2f})", flush=True)
    if args.against:
        if not args.features:
            raise SystemExit("--against needs --features FILE")
        runs, worst, at = whole_table_against(args.features, args.against, args.rounds, args.analyze_args.split())
        best = {k: min(r, key=lambda t: t[1]) for k, r in runs.items()}
        print(f"whole Table 1, `rigctl analyze --table1` (best of {args.rounds}): previous {best['previous'][0]:.1f} s "
              f"wall, {best['previous'][1]:.1f} CPU-s, {best['previous'][2]:.2f} GB; this {best['this'][0]:.1f} s, "
              f"{best['this'][1]:.1f} CPU-s, {best['this'][2]:.2f} GB: CPU ratio "
              f"{best['previous'][1] / best['this'][1]:.2f}x, wall ratio {best['previous'][0] / best['this'][0]:.2f}x; "
              f"largest accuracy change {worst:.3f} repetition SD"
              + (f" ({at[0]} / {at[1]} at {at[2]} PCs: {at[3]:.2f} -> {at[4]:.2f} %, SD {at[5]:.2f})" if at else ""))
    if args.skip_full:
        return
    with threadpool_limits(1):
        cpu1, diff = one_repetition_side_by_side(fs, args.pcs)
    print(f"one repetition on one core (4 CV folds + 1 extrapolation split x {len(fs.features)} variants): per-split "
          f"scikit-learn "
          f"randomized PCA {cpu1['sklearn']:.1f} CPU-s, fast path {cpu1['fast']:.1f} CPU-s, ratio "
          f"{cpu1['sklearn'] / cpu1['fast']:.1f}x; largest accuracy difference {100 * diff:.2f} points "
          f"(load average {os.getloadavg()[0]:.2f})")
    t0, c0 = time.perf_counter(), time.process_time()
    with warnings.catch_warnings(), TqdmProgress(leave=False) as bar:
        warnings.simplefilter("ignore")
        res = run_table1(fs, n_pcs=args.pcs, repeats=args.repeats, progress=bar, n_jobs=args.jobs)
    t, cpu = time.perf_counter() - t0, time.process_time() - c0
    n_fits = args.repeats * 4 * (4 + 1)  # per variant: 4 CV folds (shared by A and B) + 1 extrapolation split
    print(f"Table 1: {len(res.curves)} tasks x {len(fs.features)} variants x {res.settings['n_pcs']} PCs x "
          f"{args.repeats} repetitions in {t:.1f} s wall ({t / 60:.2f} min; target < 3 min: {t / 180:.2f} of it; "
          f"{n_fits} PCA fits), "
          f"{cpu:.1f} CPU-s (all threads; on an idle 2-core machine wall ~ CPU-s / 2 at best, CPU-s at worst); "
          f"load average now {os.getloadavg()}")
    if args.repeats != 20:
        print(f"  scaled to 20 repetitions: ~{t * 20 / args.repeats / 60:.2f} min wall, "
              f"~{cpu * 20 / args.repeats / 60:.2f} CPU-min")
    for task, by_v in res.curves.items():
        print(f"  {task:24s}" + "".join(f" {v}={100 * c.at(args.pcs)[0]:.1f}%" for v, c in by_v.items()))


if __name__ == "__main__":
    main()
