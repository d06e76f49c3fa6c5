"""The whole paper from nothing, stage by stage: ``rigctl sim dataset`` -> ``rigctl encode`` -> ``rigctl analyze --table1``
-> ``rigctl export nwb`` (with the encoded spike trains), and the encoder's floor in the same run.

Runs the three commands as a user would (each its own process, default options: all cores) on the paper's protocol
(``protocols/paper_dataset.toml``: 16 textures x 5 speeds x 3 forces x 100 trials = 24,000 trials), or on a stated
fraction of it (``--fraction 0.1``: 10 trials per condition), and prints per stage: wall and CPU seconds (the stage's
process and its children), peak resident memory of the process tree, trials/s, MB/s (of the file the stage writes, or
reads for the analysis), neuron-steps/s for the encoder (samples x taxels x SA/RA, the paper's 3e9), and the
machine's load average; then issue 57's targets as ratios (encode <= 2x its floor in wall and CPU time, peak RSS
< 1.5 GB; Table 1 <= 30 s; the export's peak RSS < 1 GB; sim dataset >= 500 trials/s; the whole paper < 120 s). The
stages run with their byte code kept (``CHILD_ENV``), compiled before the first stage (``WARM``), and numba's kernels
in its cache (``scripts/compile_kernels.py``, as the test command does). With a fraction,
the linear extrapolation of the trial-bound stages (simulation, encoding) to 24,000 trials is printed beside the
total (the analysis is full size from 1/3 on: its textures/groups draws are 500 per texture).

The **floor** of the encoder (issue 57, the lead's decision of 2026-11-28) is what any encoder of ``rigctl
encode``'s outputs must do, as a plain process: read every trial's taxels once with h5py (``/recording/taxels`` of a
schema-4 session, in blocks of a million samples), the per-taxel range taken as given (the session's
``/calibration`` extremes, which for a simulated dataset are the encode's normalisation: the run says whether they
were), and the plain fused kernel once over every sample with the **three** SA populations the encode's outputs need
(C = 1, the per-texture and the label-free force coefficients) and the RA one, spike times kept; no validation, force
fit, speed scaling, features or writing. Until then the floor was one SA population and RA, after a read of every
sample for the range: it still runs, right after, and the encode's ratio to it is printed beside, for the record
(docs/results.md 5ab).

    python benchmarks/bench_paper.py --fraction 0.1          # 2,400 trials
    python benchmarks/bench_paper.py                          # the paper: 24,000 trials (~3 GB of session)
    python benchmarks/bench_paper.py --keep DIR               # keep the files in DIR
    python benchmarks/bench_paper.py --session DIR/paper.h5 --stages floor,encode,export   # reuse a dataset
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PAPER_TRIALS = 24_000
STAGES = ("sim", "floor", "encode", "analyze", "export")
TARGET_S = 300.0


def _tree_rss(proc) -> int:
    try:
        procs = [proc] + proc.children(recursive=True)
    except Exception:  # the process ended
        return 0
    total = 0
    for p in procs:
        try:
            total += p.memory_info().rss
        except Exception:
            pass
    return total


#: the trials in blocks of about a million samples, in file order (shared by both floors below)
_FLOOR_BLOCKS = """
import sys, h5py, numpy as np
from rigctl.encoding.fused import run_fused
from rigctl.encoding.normalise import TaxelRange
f = h5py.File(sys.argv[1], "r")
ds, idx = f["recording/taxels"], f["recording/index"][()]
order = np.argsort(idx["sample_start"])
starts, lengths = idx["sample_start"][order], idx["n_samples"][order]
blocks, i = [], 0
while i < len(order):
    j, n = i, 0
    while j < len(order) and (j == i or n + lengths[j] <= 1 << 20):
        n += int(lengths[j]); j += 1
    blocks.append((int(starts[i]), n, np.concatenate([[0], np.cumsum(lengths[i:j])])))
    i = j
"""

#: the floor (issue 57's decision, 2026-11-28): what any encoder of ``rigctl encode``'s outputs must do. Every
#: trial's taxels read once; the normalisation's per-taxel range taken as given (the session's ``/calibration``
#: extremes: a simulated dataset's are the per-taxel minimum and maximum of its trials, the encode's normalisation),
#: so no sample is read for it; the fused kernel once over every sample with the three SA populations the encode's
#: outputs need (C = 1, the per-texture and the label-free force coefficients: here all C = 1, the encode's are
#: 0.5-2) and the RA one, spike times kept
FLOOR = _FLOOR_BLOCKS + """
if "calibration/taxel_min" in f:
    rng = TaxelRange()
    rng.fold(f["calibration/taxel_min"][()], f["calibration/taxel_max"][()], int(lengths.sum()))
    given = "range from /calibration"
else:  # a session without a calibration: the range read too (the old floor's pass)
    rng = TaxelRange()
    for lo, n, st in blocks:
        rng.update(ds[lo:lo + n])
    given = "range read (no /calibration)"
offset, scale = rng.offset_scale()
spikes = 0
for lo, n, st in blocks:
    res = run_fused(ds[lo:lo + n], st, offset=offset, scale=scale, sa_gains=[1.0, 1.0, 1.0])
    spikes += sum(int(s.spike_times.size) for s in res.sa) + int(res.ra.spike_times.size)
print(f"floor: {int(lengths.sum())} samples read once, 3 SA + RA, {spikes} spikes, {given}")
"""

#: the floor before issue 57's decision (issues 26 and 57 until 2026-11-28), printed beside for the record: every
#: sample read for the per-taxel range, then read again for the kernel with ONE SA population (C = 1) and RA
FLOOR_ONE_SA = _FLOOR_BLOCKS + """
rng = TaxelRange()
for lo, n, st in blocks:  # the range pass: every sample read once
    rng.update(ds[lo:lo + n])
offset, scale = rng.offset_scale()
spikes = 0
for lo, n, st in blocks:  # the kernel: one SA population and RA over every sample
    res = run_fused(ds[lo:lo + n], st, offset=offset, scale=scale, sa_gains=[1.0])
    spikes += sum(int(s.spike_times.size) for s in res.sa) + int(res.ra.spike_times.size)
print(f"floor (one SA population): {int(lengths.sum())} samples, {spikes} spikes")
"""


#: the children's environment: byte code compiled once and kept (as a pip install keeps it): uv installs none, and an
#: environment with PYTHONDONTWRITEBYTECODE=1 (this machine's) has every stage compile every module it imports from
#: source (measured: 1.2-1.7 CPU-s of a 960-trial encode's ~6), which is no cost of rigctl's
CHILD_ENV = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
CHILD_ENV.setdefault("PYTHONPYCACHEPREFIX", os.path.join(tempfile.gettempdir(), "bench_paper_pycache"))

#: imported once before the stages (its output discarded): every stage then starts with its byte code compiled, as
#: in an installation that has run before (a stage's first run on a fresh prefix compiled ~1-4 CPU-s of it)
WARM = ("import h5py, numpy, pynwb, hdmf, sklearn, scipy.stats, rigctl.cli, rigctl.encoding.pipeline, "
        "rigctl.storage.nwb, rigctl.simulation.dataset, rigctl.operations._analysis")

#: issue 57's targets: (what, the figure's name in the summary, the limit, "<=" or ">=")
TARGETS = (("encode / floor, wall", "encode_floor_wall", 2.0, "<="),
           ("encode / floor, CPU", "encode_floor_cpu", 2.0, "<="),
           ("encode peak RSS, GB", "encode_rss_gb", 1.5, "<"),
           ("analyze --table1, s wall", "table1_s", 30.0, "<="),
           ("export nwb peak RSS, GB", "export_rss_gb", 1.0, "<"),
           ("sim dataset, trials/s", "sim_trials_s", 500.0, ">="),
           ("the whole paper, s wall", "total_s", 120.0, "<"))


def run_stage(args: list[str], python: bool = False, env: dict[str, str] | None = None) -> dict:
    """Run ``python -m rigctl ARGS`` (``python``: ``python ARGS``) in ``env`` (default :data:`CHILD_ENV`); wall, CPU
    (process + children), peak tree RSS."""
    import psutil

    before = os.times()
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, *([] if python else ["-m", "rigctl"]), *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=CHILD_ENV if env is None else env)
    peak = [0]
    ps = psutil.Process(proc.pid)

    def watch():
        while proc.poll() is None:
            peak[0] = max(peak[0], _tree_rss(ps))
            time.sleep(0.1)

    th = threading.Thread(target=watch, daemon=True)
    th.start()
    out, err = proc.communicate()
    wall = time.perf_counter() - t0
    th.join()
    after = os.times()
    cpu = (after.children_user - before.children_user) + (after.children_system - before.children_system)
    if proc.returncode != 0:
        raise SystemExit(f"rigctl {' '.join(args)} failed ({proc.returncode}):\n{err[-3000:]}")
    return {"wall": wall, "cpu": cpu, "rss": peak[0], "out": out, "load": (load0, os.getloadavg()[0])}


def session_size(path: Path) -> tuple[int, int, int]:
    """(trials, samples summed over trials, taxels) of a session file."""
    from rigctl.storage.session import open_session

    with open_session(path) as s:
        ids = s.completed_ids()
        samples = sum(int(c["n_samples"]) for c in s.trial_counts(ids))
        return len(ids), samples, s.layout.n_channels


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fraction", type=float, default=1.0, help="of the paper's 100 trials per condition")
    ap.add_argument("--repeats", type=int, default=20, help="Table 1 repetitions (the paper: 20)")
    ap.add_argument("--keep", default=None, help="folder to keep the files in (default: a temporary one)")
    ap.add_argument("--session", default=None, help="an existing session of the paper's protocol: no sim dataset stage "
                                                    "(the other files go beside it unless --keep)")
    ap.add_argument("--stages", default=",".join(STAGES),
                    help=f"comma-separated stages to run, of {','.join(STAGES)} (encode must have run, or its file "
                         "be in the folder, for analyze and export)")
    args = ap.parse_args()
    stages_wanted = set(args.stages.split(","))
    if stages_wanted - set(STAGES):
        raise SystemExit(f"unknown stages {sorted(stages_wanted - set(STAGES))}; choose from {','.join(STAGES)}")
    if args.session:
        stages_wanted.discard("sim")
    tpc = max(1, round(100 * args.fraction))
    n_expected = 240 * tpc
    work = Path(args.keep) if args.keep else (Path(args.session).resolve().parent if args.session else
                                               Path(tempfile.mkdtemp(prefix="bench_paper_")))
    work.mkdir(parents=True, exist_ok=True)
    session = Path(args.session) if args.session else work / "paper.h5"
    encoded = work / "paper.encoded.h5"
    print(f"the paper from nothing: {tpc} trials per condition ({n_expected} trials, {n_expected / PAPER_TRIALS:.3g} "
          f"of the paper), {os.cpu_count()} cores, load average at start {os.getloadavg()}", flush=True)
    stages = []
    floor = floor_one = None
    subprocess.run([sys.executable, "-c", WARM], env=CHILD_ENV, check=True, capture_output=True)
    # numba's kernels compiled into its cache as the test command does (a fresh cache made the first stage that ran
    # a kernel, the floor, compile it: 17.8 s against 8.9 s warm, 2026-11-28, docs/results.md 5z)
    subprocess.run([sys.executable, str(REPO / "scripts" / "compile_kernels.py")], env=CHILD_ENV, check=True,
                   capture_output=True)
    try:
        if "sim" in stages_wanted:
            st = run_stage(["sim", "dataset", str(REPO / "protocols" / "paper_dataset.toml"), "--out", str(session),
                            "--trials-per-condition", str(tpc), "--overwrite", "--quiet"])
        n, samples, taxels = session_size(session)
        if "sim" in stages_wanted:
            st.update(name="sim dataset", trials=n, mb=session.stat().st_size / 1e6, mb_what="written")
            stages.append(st)
            _print(st)
        else:
            print(f"session {session}: {n} trials (reused; no sim dataset stage)", flush=True)
        if "floor" in stages_wanted:
            st = run_stage(["-c", FLOOR, str(session)], python=True)
            st.update(name="floor (3 SA + RA)", trials=n, mb=session.stat().st_size / 1e6, mb_what="read",
                      neuron_steps=samples * taxels * 4)
            floor = st
            _print(st)
            print(f"{'':>17}  {st['out'].strip()}", flush=True)
            st = run_stage(["-c", FLOOR_ONE_SA, str(session)], python=True)
            st.update(name="old floor (1 SA)", trials=n, mb=session.stat().st_size / 1e6, mb_what="read",
                      neuron_steps=samples * taxels * 2)
            floor_one = st
            _print(st)
        if "encode" in stages_wanted:
            st = run_stage(["encode", str(session), "--out", str(encoded), "--overwrite", "--quiet"])
            st.update(name="encode", trials=n, mb=session.stat().st_size / 1e6, mb_what="read",
                      neuron_steps=samples * taxels * 2)
            stages.append(st)
            _print(st)
            if floor and floor_one:
                print(f"{'':>17}  encode / floor (3 SA + RA, one read; the target, <= 2): {st['wall'] / floor['wall']:.2f}"
                      f" wall, {st['cpu'] / floor['cpu']:.2f} CPU | encode / old floor (1 SA + RA, for the record): "
                      f"{st['wall'] / floor_one['wall']:.2f} wall, {st['cpu'] / floor_one['cpu']:.2f} CPU", flush=True)
            print(f"{'':>17}  peak RSS {st['rss'] / 1e9:.2f} GB (target < 1.5); normalisation "
                  f"{_same_range(session, encoded)}", flush=True)
        if "analyze" in stages_wanted:
            st = run_stage(["analyze", str(encoded), "--table1", "--repeats", str(args.repeats), "--no-progress"])
            st.update(name="analyze --table1", trials=n, mb=encoded.stat().st_size / 1e6, mb_what="read")
            stages.append(st)
            _print(st)
            print(st["out"])
        if "export" in stages_wanted:
            nwb = work / "paper.nwb"
            st = run_stage(["export", "nwb", str(session), "--encoded", str(encoded), "--out", str(nwb),
                            "--overwrite"])
            st.update(name="export nwb", trials=n, mb=nwb.stat().st_size / 1e6, mb_what="written")
            stages.append(st)
            _print(st)
    finally:
        if not args.keep and not args.session:
            shutil.rmtree(work, ignore_errors=True)
    if not stages:
        return
    total = sum(s["wall"] for s in stages)
    scale = PAPER_TRIALS / n
    # simulation, encoding and export scale with the trials; the analysis draws 500 per texture from 1/3 of the paper on
    full = sum(s["wall"] * (scale if s["name"] != "analyze --table1" else min(scale, 3.0)) for s in stages)
    figures = {"total_s": total if n == PAPER_TRIALS else None}
    for st in stages:
        if st["name"] == "encode" and floor and floor_one:
            figures.update(encode_floor_wall=st["wall"] / floor["wall"], encode_floor_cpu=st["cpu"] / floor["cpu"],
                           encode_floor1_wall=st["wall"] / floor_one["wall"],
                           encode_floor1_cpu=st["cpu"] / floor_one["cpu"])
        if st["name"] == "encode":
            figures["encode_rss_gb"] = st["rss"] / 1e9
        if st["name"] == "analyze --table1" and n == PAPER_TRIALS:
            figures["table1_s"] = st["wall"]
        if st["name"] == "export nwb":
            figures["export_rss_gb"] = st["rss"] / 1e9
        if st["name"] == "sim dataset":
            figures["sim_trials_s"] = st["trials"] / st["wall"]
    print("issue 57's targets (ratio = figure / limit; the paper-size ones only at 24,000 trials):")
    for what, key, limit, op in TARGETS:
        got = figures.get(key)
        if got is None:
            continue
        met = {"<=": got <= limit, "<": got < limit, ">=": got >= limit}[op]
        print(f"  {what} {op} {limit:g}: {got:.2f} = {got / limit:.2f} of the limit ({'met' if met else 'NOT met'})")
    if "encode_floor1_cpu" in figures:
        print(f"  (for the record, not a target: encode / the old one-SA floor {figures['encode_floor1_wall']:.2f} wall, "
              f"{figures['encode_floor1_cpu']:.2f} CPU)")
    print(f"total: {total:.1f} s wall, {sum(s['cpu'] for s in stages):.1f} CPU-s for {n} trials "
          f"({total / TARGET_S:.2f} of issue 12's 5 min target" + (")" if n == PAPER_TRIALS else
          f"; extrapolated to {PAPER_TRIALS} trials: ~{full:.0f} s = {full / TARGET_S:.2f} of the target, the "
          "analysis scaled by at most 3x)") + f"; load average now {os.getloadavg()}")


def _same_range(session: Path, encoded: Path) -> str:
    """Whether the encoded file's normalisation is the session's ``/calibration`` range the floor took as given."""
    import h5py
    import numpy as np

    with h5py.File(session, "r") as s, h5py.File(encoded, "r") as e:
        if "calibration/taxel_min" not in s:
            return "(the session has no /calibration: the floor read its range)"
        same = all(np.array_equal(s[f"calibration/taxel_{m}"][()], e[f"normalisation/taxel_{m}"][()])
                   for m in ("min", "max"))
    return "= the session's /calibration range (the floor's)" if same else \
        "DIFFERS from the session's /calibration range the floor took (the floor's ratio is off)"


def _print(st: dict) -> None:
    extra = f", {st['neuron_steps'] / st['wall']:.3g} neuron-steps/s" if "neuron_steps" in st else ""
    print(f"{st['name']:>17}: {st['wall']:7.1f} s wall, {st['cpu']:7.1f} CPU-s, peak RSS {st['rss'] / 1e9:.2f} GB, "
          f"{st['trials'] / st['wall']:8.1f} trials/s, {st['mb'] / st['wall']:7.1f} MB/s {st['mb_what']} "
          f"({st['mb']:.0f} MB){extra}; load average {st['load'][0]:.2f} -> {st['load'][1]:.2f}", flush=True)


if __name__ == "__main__":
    main()
