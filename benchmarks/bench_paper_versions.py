"""The encoder's floor, ``rigctl encode`` and ``rigctl export nwb`` of two rigctl versions side by side on one session.

For a regression seen between two days' ``bench_paper.py`` runs: is it the code or the machine? Runs, for this checkout
and an older commit (``git archive`` of ``--before`` into a scratch folder, imported through ``PYTHONPATH``; each
version its own numba cache and byte-code prefix, warmed first), bench_paper's floor, the encode and the export (with
that version's own encoded file), each stage its own process, the versions alternated (before, after, after, before,
...), and prints per run the wall and CPU seconds, peak RSS, MB/s of the export, and the after / before ratios of the
CPU seconds (the medians): the load moves the wall figures, the CPU figures much less, their ratio least.

The session must be readable by both versions (one written by ``rigctl sim dataset`` of the older version; schema 5
sessions are refused by rigctl before 29aed66). The outputs go to ``--work`` (default: a temporary folder).

    python benchmarks/bench_paper_versions.py --before 84bfba6 --session OLD_SCHEMA.h5 [--stages floor,encode,export]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_paper import CHILD_ENV, FLOOR, REPO, WARM, run_stage  # noqa: E402

STAGES = ("floor", "encode", "export")


def _tree(rev: str, scratch: Path) -> Path:
    """The source of ``rev`` (the rigctl package and the launcher module, where it has one) in ``scratch``."""
    scratch.mkdir(parents=True)
    names = subprocess.run(["git", "-C", str(REPO), "ls-tree", "--name-only", rev], check=True, capture_output=True,
                           text=True).stdout.split()
    wanted = [n for n in ("rigctl", "rigctl_launch.py") if n in names]
    archive = subprocess.run(["git", "-C", str(REPO), "archive", rev, *wanted], check=True,
                             capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(scratch)], input=archive, check=True)
    return scratch


def _env(tree: Path, scratch: Path, name: str) -> dict[str, str]:
    return {**CHILD_ENV, "PYTHONPATH": str(tree), "NUMBA_CACHE_DIR": str(scratch / f"numba-{name}"),
            "PYTHONPYCACHEPREFIX": str(scratch / f"pycache-{name}")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--before", required=True, help="the older commit")
    ap.add_argument("--session", required=True, help="a session both versions read")
    ap.add_argument("--stages", default=",".join(STAGES), help=f"comma-separated, of {','.join(STAGES)}")
    ap.add_argument("--rounds", type=int, default=2, help="rounds of both versions, alternated (default 2)")
    ap.add_argument("--work", default=None, help="folder for the encoded and NWB files (default: temporary)")
    args = ap.parse_args()
    stages = [s for s in STAGES if s in args.stages.split(",")]
    session = Path(args.session).resolve()
    with tempfile.TemporaryDirectory(prefix="bench_paper_versions_") as tmp:
        scratch = Path(tmp)
        work = Path(args.work) if args.work else scratch
        work.mkdir(parents=True, exist_ok=True)
        trees = {"before": _tree(args.before, scratch / "before"), "after": REPO}
        envs = {name: _env(tree, scratch, name) for name, tree in trees.items()}
        for env in envs.values():  # byte code and numba's kernels compiled before the timed runs
            subprocess.run([sys.executable, "-c", WARM], env=env, check=True, capture_output=True)
            subprocess.run([sys.executable, "-c", FLOOR, str(session)], env=env, check=True, capture_output=True)
        print(f"{session.name}, before = {args.before}, after = this checkout; {os.cpu_count()} cores, load average "
              f"{' '.join(f'{x:.1f}' for x in os.getloadavg())}", flush=True)
        cpu: dict[tuple[str, str], list[float]] = {}
        for r in range(args.rounds):
            for name in (("before", "after") if r % 2 == 0 else ("after", "before")):
                encoded, nwb = work / f"{name}.encoded.h5", work / f"{name}.nwb"
                for stage in stages:
                    if stage == "floor":
                        st = run_stage(["-c", FLOOR, str(session)], python=True, env=envs[name])
                    elif stage == "encode":
                        st = run_stage(["encode", str(session), "--out", str(encoded), "--overwrite", "--quiet"],
                                       env=envs[name])
                    else:
                        st = run_stage(["export", "nwb", str(session), "--encoded", str(encoded), "--out", str(nwb),
                                        "--overwrite"], env=envs[name])
                    cpu.setdefault((stage, name), []).append(st["cpu"])
                    rate = f", {nwb.stat().st_size / 1e6 / st['wall']:.1f} MB/s" if stage == "export" else ""
                    print(f"round {r} {name:>6} {stage:>6}: {st['wall']:7.1f} s wall, {st['cpu']:7.1f} CPU-s, peak "
                          f"RSS {st['rss'] / 1e9:.2f} GB{rate}; load {st['load'][0]:.1f} -> {st['load'][1]:.1f}",
                          flush=True)
        for stage in stages:
            b, a = statistics.median(cpu[(stage, "before")]), statistics.median(cpu[(stage, "after")])
            print(f"{stage}: median CPU {b:.1f} -> {a:.1f} CPU-s, after / before {a / b:.2f}")
        print(f"load average after: {' '.join(f'{x:.1f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
