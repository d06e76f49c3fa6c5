"""`rigctl sim dataset` of two rigctl versions side by side: trials/s of this checkout against an older commit's.

Runs ``generate_dataset`` on ``protocols/paper_dataset.toml`` with a reduced number of trials per condition, once per
version and worker count, alternating the versions (each run its own process; the older version from ``git archive``
of ``--before`` into a scratch folder, its render workers importing it too), and prints per run the wall time,
trials/s, the CPU seconds of the writing process and of its workers, and the ratio after / before of each worker
count. The load average is printed before and after: on a shared machine the wall-clock numbers fall with the load,
their ratio much less. Each version's numba kernels are compiled (into ``$NUMBA_CACHE_DIR``) before the timed runs.

    python benchmarks/bench_dataset_versions.py --before 60840c4 [--trials-per-condition 4] [--workers 0,1] [--repeat 2]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

_RUN = r"""
import json, os, resource, sys, time
from pathlib import Path
import rigctl
from rigctl.acquisition.protocol import load_protocol
from rigctl.simulation.dataset import generate_dataset

def main():
    tpc, workers, out, proto = int(sys.argv[1]), int(sys.argv[2]), Path(sys.argv[3]), Path(sys.argv[4])
    protocol = load_protocol(proto)
    if tpc == 0:  # warm-up: this version's kernels compiled into numba's cache (one short trial rendered)
        from rigctl.simulation.dataset import render_trial
        import numpy as np
        render_trial("A", 120, 500, rng=np.random.default_rng(0), duration_s=0.05)
        print(json.dumps({"rigctl": rigctl.__file__}))
        return
    c0 = time.process_time()
    t0 = time.perf_counter()
    s = generate_dataset(protocol, out, trials_per_condition=tpc, workers=workers, progress=False, overwrite=True,
                         seed=1)
    wall = time.perf_counter() - t0
    ch = resource.getrusage(resource.RUSAGE_CHILDREN)
    with __import__("h5py").File(out, "r") as f:
        schema = int(f.attrs["schema_version"])
    out.unlink()
    print(json.dumps({"rigctl": rigctl.__file__, "n_trials": s["n_trials"], "workers": s["workers"], "wall_s": wall,
                      "parent_cpu_s": time.process_time() - c0, "workers_cpu_s": ch.ru_utime + ch.ru_stime,
                      "bytes": s["bytes"], "schema": schema}))

if __name__ == "__main__":
    main()
"""


def _tree(rev: str, scratch: Path) -> Path:
    """The source of ``rev`` (rigctl and protocols) extracted into ``scratch / rev``."""
    dst = scratch / rev
    dst.mkdir(parents=True)
    archive = subprocess.run(["git", "-C", str(REPO), "archive", rev, "rigctl", "protocols"], check=True,
                             capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(dst)], input=archive, check=True)
    return dst


def _run(tree: Path, script: Path, tpc: int, workers: int, out: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": str(tree), "PYTHONDONTWRITEBYTECODE": "1"}
    res = subprocess.run([sys.executable, str(script), str(tpc), str(workers), str(out),
                          str(tree / "protocols" / "paper_dataset.toml")], env=env, capture_output=True, text=True,
                         cwd=str(out.parent))
    if res.returncode != 0:
        raise SystemExit(f"run failed ({tree}):\n{res.stderr[-2000:]}")
    got = json.loads(res.stdout.strip().splitlines()[-1])
    if not got["rigctl"].startswith(str(tree)):
        raise SystemExit(f"imported {got['rigctl']}, not the tree {tree}")
    return got


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", required=True, help="the older commit (e.g. main before the change)")
    ap.add_argument("--trials-per-condition", type=int, default=4, help="x 240 trials per run (default 4: 960)")
    ap.add_argument("--workers", default="0,1", help="worker counts, comma-separated (default 0,1: 1 is the "
                    "default on 2 cores)")
    ap.add_argument("--repeat", type=int, default=2, help="alternated runs of each version (the best is kept)")
    args = ap.parse_args()
    workers = [int(w) for w in args.workers.split(",")]
    with tempfile.TemporaryDirectory(prefix="bench_dataset_versions_") as tmp:
        scratch = Path(tmp)
        script = scratch / "run.py"
        script.write_text(_RUN)
        trees = {"before": _tree(args.before, scratch / "src"), "after": _tree("HEAD", scratch / "src2")}
        dirty = subprocess.run(["git", "-C", str(REPO), "status", "--porcelain", "rigctl"], capture_output=True,
                               text=True).stdout.strip()
        if dirty:
            trees["after"] = REPO  # uncommitted changes: this checkout itself
        for tree in trees.values():
            _run(tree, script, 0, 0, scratch / "warm.h5")
        print(f"paper_dataset.toml, {240 * args.trials_per_condition} trials a run, before = {args.before}, after = "
              f"{'this checkout' if dirty else 'HEAD'}; {os.cpu_count()} cores, load average "
              f"{' '.join(f'{x:.1f}' for x in os.getloadavg())}")
        print(f"{'version':>7} {'workers':>7} {'schema':>6} {'wall_s':>7} {'trials/s':>8} {'parent_cpu':>10} "
              f"{'workers_cpu':>11} {'CPU ms/trial':>12} {'kB/trial':>8}")
        best: dict[tuple[str, int], dict] = {}
        for _ in range(args.repeat):
            for w in workers:
                for name, tree in trees.items():
                    r = _run(tree, script, args.trials_per_condition, w, scratch / f"{name}.h5")
                    n = r["n_trials"]
                    cpu = r["parent_cpu_s"] + r["workers_cpu_s"]
                    print(f"{name:>7} {r['workers']:>7} {r['schema']:>6} {r['wall_s']:>7.2f} {n / r['wall_s']:>8.0f} "
                          f"{r['parent_cpu_s']:>10.2f} {r['workers_cpu_s']:>11.2f} {1000 * cpu / n:>12.2f} "
                          f"{r['bytes'] / n / 1e3:>8.1f}", flush=True)
                    key = (name, w)
                    if key not in best or r["wall_s"] < best[key]["wall_s"]:
                        best[key] = r
        for w in workers:
            b, a = best[("before", w)], best[("after", w)]
            rate_b, rate_a = b["n_trials"] / b["wall_s"], a["n_trials"] / a["wall_s"]
            cpu_b = (b["parent_cpu_s"] + b["workers_cpu_s"]) / b["n_trials"]
            cpu_a = (a["parent_cpu_s"] + a["workers_cpu_s"]) / a["n_trials"]
            wcpu_b, wcpu_a = b["parent_cpu_s"] / b["n_trials"], a["parent_cpu_s"] / a["n_trials"]
            print(f"workers {w}: best {rate_b:.0f} -> {rate_a:.0f} trials/s (x{rate_a / rate_b:.2f}); CPU "
                  f"{1000 * cpu_b:.2f} -> {1000 * cpu_a:.2f} ms/trial (x{cpu_b / cpu_a:.2f} less); the writing "
                  f"process {1000 * wcpu_b:.2f} -> {1000 * wcpu_a:.2f} ms/trial")
        print(f"load average after: {' '.join(f'{x:.1f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
