"""Encoder benchmark: the same input through our numba encoder, a per-sample Python loop and Brian2, side by side.

Input: ``--trials`` trials x ``--seconds`` s at 1 kHz x 18 taxels of texture-like normalised readings (float64),
SA encoding (tonic spiking, k = 100; paper eqs. 3-5). A neuron-step = one neuron advanced by one 1 ms sample.

- ours: ``run_izhikevich`` (counts only) and ``encode_sa`` (spike times, NWB layout) on all cores (2 here);
  best of ``--repeats`` runs after a warm-up (compilation excluded; the numba cache makes it a one-off anyway);
- per-sample loop: plain Python, one neuron and sample at a time (on a slice; its rate is per neuron-step);
- Brian2: ``brian2_izhikevich.py`` run with benchmarks/.venv-brian2/bin/python (``bash benchmarks/brian2_venv.sh``
  makes it) or this Python if it imports brian2; Brian2's default runtime target (cython when it compiles); Euler
  at dt = 0.5 ms; compile time reported separately.

Targets (issue 3): >= 1e9 neuron-steps/s on 2 cores, >= 20x Brian2. The spike counts of the three are compared
(mean rate per neuron) so that the speed figures are for the same work.

Usage: python benchmarks/bench_encoder.py [--trials 128] [--seconds 6] [--repeats 5] [--no-brian2] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from rigctl.encoding.izhikevich import encode_sa, run_izhikevich  # noqa: E402


def make_input(n_trials: int, n_samples: int, n_ch: int = 18, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.arange(n_samples)[None, :, None] / 1000.0
    f = rng.uniform(2, 20, size=(n_trials, 1, n_ch))
    base = rng.uniform(0.1, 0.6, size=(n_trials, 1, n_ch))
    x = base + 0.3 * np.sin(2 * np.pi * f * t) + 0.02 * rng.standard_normal((n_trials, n_samples, n_ch))
    return np.clip(x, 0.0, 1.0)


def python_loop(x2d: np.ndarray, k: float = 100.0) -> np.ndarray:
    """Per-sample reference: (n_samples, n_neurons) -> spike counts."""
    a, b, c, d = 0.02, 0.2, -65.0, 6.0
    counts = np.zeros(x2d.shape[1], dtype=int)
    for j in range(x2d.shape[1]):
        v, u = c, b * c
        col = x2d[:, j].tolist()
        for i_in in col:
            i_in *= k
            v = v + 0.5 * (0.04 * v * v + 5 * v + 140 - u + i_in)
            v = v + 0.5 * (0.04 * v * v + 5 * v + 140 - u + i_in)
            u = u + a * (b * v - u)
            if v >= 30:
                v = c
                u += d
                counts[j] += 1
    return counts


def best_rate(fn, steps: int, repeats: int) -> tuple[float, float, float]:
    """(best wall rate, median wall rate, rate per CPU-second of this process) in neuron-steps/s.

    On a shared machine the wall-clock rate drops with other load; steps per CPU-second does not (much), and times
    the core count it estimates what the cores give when they are free.
    """
    fn()  # warm-up (compile / cache load)
    times, cpu = [], []
    for _ in range(repeats):
        c0 = time.process_time()
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return steps / min(times), steps / float(np.median(times)), steps / float(np.median(cpu))


def brian2_python() -> str | None:
    venv = HERE / ".venv-brian2" / "bin" / "python"
    if venv.exists():
        return str(venv)
    try:
        import brian2  # noqa: F401

        return sys.executable
    except ImportError:
        return None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=128)
    ap.add_argument("--seconds", type=float, default=6.0)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--loop-neurons", type=int, default=4)
    ap.add_argument("--no-brian2", action="store_true")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)

    n_samples = int(args.seconds * 1000)
    x = make_input(args.trials, n_samples)
    steps = x.size
    res = {"trials": args.trials, "samples": n_samples, "neurons": args.trials * 18, "neuron_steps": steps,
           "cores": os.cpu_count(), "load_avg": os.getloadavg()[0]}

    best, med, per_cpu = best_rate(lambda: run_izhikevich(x, k=100.0, want_raster=False), steps, args.repeats)
    res["ours_counts_steps_per_s"], res["ours_counts_steps_per_s_median"] = best, med
    res["ours_counts_steps_per_cpu_s"] = per_cpu
    best, med, per_cpu = best_rate(lambda: encode_sa(x), steps, args.repeats)
    res["ours_spike_times_steps_per_s"], res["ours_spike_times_steps_per_s_median"] = best, med
    res["ours_spike_times_steps_per_cpu_s"] = per_cpu
    ours_counts = run_izhikevich(x, k=100.0, want_raster=False)[0].reshape(-1)
    res["ours_mean_rate_hz"] = float(ours_counts.mean() / args.seconds)

    # per-sample loop on a slice of the same input (trial 0, first loop_neurons taxels)
    sl = x[0][:, : args.loop_neurons]
    t0, c0 = time.perf_counter(), time.process_time()
    loop_counts = python_loop(sl)
    res["loop_steps_per_s"] = sl.size / (time.perf_counter() - t0)
    res["loop_steps_per_cpu_s"] = sl.size / (time.process_time() - c0)
    res["loop_counts_equal_ours"] = bool(np.array_equal(loop_counts, ours_counts[: args.loop_neurons]))

    py = None if args.no_brian2 else brian2_python()
    if py is None:
        res["brian2"] = "not run (bash benchmarks/brian2_venv.sh makes benchmarks/.venv-brian2)"
    else:
        with tempfile.TemporaryDirectory() as d:
            inp = Path(d) / "x.npy"
            out = Path(d) / "out.json"
            # neurons = trials x taxels, in the same order as ours
            np.save(inp, np.ascontiguousarray(x.transpose(1, 0, 2).reshape(n_samples, -1)))
            env = dict(os.environ, PYTHONPATH="")
            p = subprocess.run([py, str(HERE / "brian2_izhikevich.py"), str(inp), str(out)], capture_output=True,
                               text=True, env=env, cwd=d)
            if p.returncode != 0:
                res["brian2"] = "failed: " + p.stderr[-800:]
            else:
                b = json.loads(out.read_text())
                res["brian2_version"] = b["brian2_version"]
                res["brian2_target"] = b["target"]
                res["brian2_compile_s"] = b["compile_s"]
                res["brian2_steps_per_s"] = b["neuron_steps"] / b["run_s"]
                res["brian2_steps_per_cpu_s"] = b["neuron_steps"] / b["run_cpu_s"]
                res["brian2_mean_rate_hz"] = float(np.mean(b["spike_counts"]) / args.seconds)

    if not args.json:
        print(f"input: {args.trials} trials x {n_samples} samples x 18 taxels = {steps:.3g} neuron-steps "
              f"({res['cores']} cores, load average {res['load_avg']:.1f})")
        print(f"{'implementation':38s} {'neuron-steps/s':>15s} {'vs Brian2':>10s} {'vs loop':>9s}")
        ref_b = res.get("brian2_steps_per_s")
        rows = [("ours, counts (best)", res["ours_counts_steps_per_s"]),
                ("ours, counts (median)", res["ours_counts_steps_per_s_median"]),
                ("ours, spike times NWB (best)", res["ours_spike_times_steps_per_s"]),
                ("ours, spike times NWB (median)", res["ours_spike_times_steps_per_s_median"]),
                ("per-sample Python loop", res["loop_steps_per_s"])]
        if ref_b:
            rows.append((f"Brian2 {res['brian2_version']} ({res['brian2_target']})", ref_b))
        for name, r in rows:
            vb = f"{r / ref_b:9.1f}x" if ref_b else "       -"
            print(f"{name:38s} {r:15.3g} {vb:>10s} {r / res['loop_steps_per_s']:8.0f}x")
        print("per CPU-second (insensitive to other load on a shared machine; x cores = capacity):")
        cpu_rows = [("ours, counts", res["ours_counts_steps_per_cpu_s"]),
                    ("ours, spike times NWB", res["ours_spike_times_steps_per_cpu_s"]),
                    ("per-sample Python loop", res["loop_steps_per_cpu_s"])]
        ref_bc = res.get("brian2_steps_per_cpu_s")
        if ref_bc:
            cpu_rows.append(("Brian2", ref_bc))
        for name, r in cpu_rows:
            vb = f"{r / ref_bc:9.1f}x" if ref_bc else "       -"
            print(f"  {name:36s} {r:15.3g} {vb:>10s} {r / res['loop_steps_per_cpu_s']:8.0f}x")
        print(f"  ours, counts x {res['cores']} cores: {res['ours_counts_steps_per_cpu_s'] * res['cores']:.3g} "
              "neuron-steps/s when the cores are free")
        print(f"mean SA rate: ours {res['ours_mean_rate_hz']:.1f} Hz"
              + (f", Brian2 {res['brian2_mean_rate_hz']:.1f} Hz" if ref_b else "")
              + f"; loop counts == ours: {res['loop_counts_equal_ours']}")
        if ref_b:
            print(f"Brian2 compile (first run) {res['brian2_compile_s']:.1f} s")
        else:
            print("Brian2:", res["brian2"])
        ok1 = res["ours_counts_steps_per_s"] >= 1e9
        line = f"target >= 1e9 neuron-steps/s (wall): {'met' if ok1 else 'NOT met'}"
        if ref_b:
            ok2 = res["ours_counts_steps_per_s"] >= 20 * ref_b
            line += f"; target >= 20x Brian2 (wall): {'met' if ok2 else 'NOT met'}"
        print(line)
    else:
        print(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
