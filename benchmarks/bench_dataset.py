"""Dataset generator benchmark: `generate_dataset` on a reduced paper protocol, real-time factor side by side.

Runs ``protocols/paper_dataset.toml`` (16 textures x 5 speeds x 3 forces) with a reduced number of trials per
condition, rendering in the writing process (0 workers), with the default (cores - 1 render processes) and with one
per core, and prints per run: simulated trial seconds, wall time, the real-time
factor (trial seconds / wall seconds; target >= 1000x), CPU seconds of the writing process and of the workers, bytes
per trial, and the extrapolation to the paper's 24,000 trials (wall time and file size). The machine's load average
is printed too: on a shared machine the wall-clock numbers fall with the load, the CPU seconds per trial do not.

    python benchmarks/bench_dataset.py [--trials-per-condition 5] [--out-dir /tmp]
"""

from __future__ import annotations

import argparse
import os
import resource
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PAPER_TRIALS = 24_000


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def run(trials_per_condition: int, workers: int, out_dir: Path, compression=None) -> dict:
    from rigctl.acquisition.protocol import load_protocol
    from rigctl.simulation.dataset import generate_dataset

    out = out_dir / f"bench_dataset_w{workers}_{compression or 'none'}.h5"
    cpu0, child0 = time.process_time(), _children_cpu()
    summary = generate_dataset(load_protocol(REPO / "protocols" / "paper_dataset.toml"), out, trials_per_condition=trials_per_condition,
                               workers=workers, progress=False, overwrite=True, compression=compression, seed=1)
    summary["parent_cpu_s"] = time.process_time() - cpu0
    summary["workers_cpu_s"] = _children_cpu() - child0
    summary["compression"] = compression or "none"
    out.unlink()
    return summary


def render_only(trials_per_condition: int) -> dict:
    """The model alone: render_trial for the same plan in this process, nothing written (CPU seconds)."""
    import dataclasses

    import numpy as np

    from rigctl.acquisition.protocol import load_protocol
    from rigctl.simulation.dataset import render_trial
    from rigctl.simulation.model import RigConfig, SensorModel

    proto = dataclasses.replace(load_protocol(REPO / "protocols" / "paper_dataset.toml"),
                                trials_per_condition=trials_per_condition)
    cfg = RigConfig()
    sensor = SensorModel(cfg.sensor)
    rng = np.random.default_rng(0)
    render_trial("A", 120, 500, config=cfg, rng=rng, sensor=sensor)  # compile / load the kernel
    cpu0 = time.process_time()
    samples = 0
    for p in proto.plan():
        samples += render_trial(p.texture, p.speed_mm_s, p.force_g, config=cfg, rng=rng, duration_s=p.duration_s,
                                sensor=sensor).n_samples
    cpu = time.process_time() - cpu0
    return {"n_trials": len(proto.plan()), "trial_seconds": samples / 1000, "cpu_s": cpu}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials-per-condition", type=int, default=5)
    ap.add_argument("--out-dir", default=None)
    args = ap.parse_args()
    out_dir = Path(args.out_dir or tempfile.mkdtemp(prefix="bench_dataset_"))
    cores = os.cpu_count() or 1
    default = max(1, cores - 1)  # generate_dataset's default: the writer keeps a core of its own
    configs = [(0, None), (default, None), (cores, None), (default, "lzf")]
    configs = list(dict.fromkeys(configs))
    print(f"paper_dataset.toml, {args.trials_per_condition} trials per condition ({240 * args.trials_per_condition} "
          f"trials), {cores} cores, load average {os.getloadavg()[0]:.1f}")
    print(f"{'workers':>7} {'compr':>5} {'trial_s':>8} {'wall_s':>7} {'RTF':>7} {'RTF/1000':>8} {'parent_cpu':>10} "
          f"{'workers_cpu':>11} {'ms/trial':>8} {'kB/trial':>8} {'24k: wall_s':>11} {'24k: GB':>7} {'RTF(cpu)':>8}")
    for workers, comp in configs:
        r = run(args.trials_per_condition, workers, out_dir, comp)
        n = r["n_trials"]
        print(f"{r['workers']:>7} {r['compression']:>5} {r['trial_seconds']:>8.0f} {r['wall_s']:>7.2f} "
              f"{r['realtime_factor']:>7.0f} {r['realtime_factor'] / 1000:>8.2f} {r['parent_cpu_s']:>10.2f} "
              f"{r['workers_cpu_s']:>11.2f} {1000 * r['wall_s'] / n:>8.2f} {r['bytes'] / n / 1e3:>8.1f} "
              f"{r['wall_s'] / n * PAPER_TRIALS:>11.0f} {r['bytes'] / n * PAPER_TRIALS / 1e9:>7.2f} "
              f"{r['trial_seconds'] / _idle_wall(r, cores):>8.0f}")
    r = render_only(args.trials_per_condition)
    print(f"model only (render_trial, no file), 1 process: {r['cpu_s']:.2f} CPU s for {r['n_trials']} trials, "
          f"{1000 * r['cpu_s'] / r['n_trials']:.2f} ms/trial, {r['trial_seconds'] / r['cpu_s']:.0f}x real time per "
          f"core; 24k trials: {r['cpu_s'] / r['n_trials'] * PAPER_TRIALS:.0f} CPU s")
    print(f"load average after: {os.getloadavg()[0]:.1f}")
    print("RTF(cpu): real-time factor the measured CPU seconds allow on idle cores: trial seconds / "
          "max(parent CPU, all CPU / usable cores). A loaded machine inflates CPU seconds too (shared caches).")
    if args.out_dir is None:
        out_dir.rmdir()


def _idle_wall(r: dict, cores: int) -> float:
    usable = min(cores, r["workers"] + 1)
    return max(r["parent_cpu_s"], (r["parent_cpu_s"] + r["workers_cpu_s"]) / usable)


if __name__ == "__main__":
    main()
