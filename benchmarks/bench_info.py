"""``rigctl info`` on a big session (issue 38: 4,800 trials took 84 s, a ``trial_attrs`` read per trial), side by side
with what it cannot do without, in one run:

- ``plain read``: plain h5py reading every recording array of the file once (``/recording/*[()]``): the floor of a
  validator that looks at every count, as ``info``'s does (ADC range, byte copies, sequence gaps, finite readings);
- ``per-trial attrs``: the old way, ``Session.trial_attrs`` of each trial (measured on a tenth of the trials and
  scaled: the whole would take minutes);
- ``info``: ``rigctl.cli.info.session_summary`` (the validator and the table: what ``rigctl info`` prints, in this
  process), on the file as its writer left it: sealed, the validator judges the trials on their trial facts
  (``/recording/facts``, docs/session-format.md) without reading their samples or opening their groups;
- ``info, no facts``: the same with the file's modification time moved (what a plain copy or an edit looks like:
  the seal no longer holds, the validator opens every group and reads every sample, as for files written before
  trial facts); the time is set back afterwards (the bytes were not touched);
- ``rigctl info``: the command end to end in a new process (interpreter start and imports included), sealed.

Each is given in wall seconds, CPU seconds (this process's, or the child's) and as a ratio to the plain read; the
target is ``rigctl info`` < 2 s for 4,800 trials. The session is made like ``rigctl sim dataset``'s (uncompressed,
the paper's durations 2-6 s at 1 kHz x 18 taxels, the dataset generator's trial attributes; distinct random counts)
and kept with ``--keep FILE`` for a second run.

Usage: python benchmarks/bench_info.py [--trials 4800] [--keep FILE] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

from rigctl.storage.session import SessionWriter, TrialData, open_session

DURATIONS_S = (6.0, 4.0, 3.0, 2.4, 2.0)  # 240 mm at 40-120 mm/s (the paper's trials)
TARGET_S = 2.0


def make_session(path: Path, n: int) -> None:
    """``n`` trials as the dataset generator writes them (uncompressed, its attributes), 256 per commit."""
    rng = np.random.default_rng(0)
    plan = [dict(trial_id=i, texture="ABCDEFGHIJKLMNOP"[i * 16 // n], speed_mm_s=40 + 20 * (i % 5),
                 force_g=(250, 500, 1000)[i // 5 % 3], duration_s=DURATIONS_S[i % 5]) for i in range(n)]
    base = rng.integers(100, 900, (6000 + n, 18)).astype(np.uint16)  # trial i starts at row i: no byte copies
    with SessionWriter.create(path, plan=plan, protocol_source="name = 'bench'", kind="simulated-dataset",
                              compression=None, durable=False, overwrite=True) as w:
        for lo in range(0, n, 256):
            items = []
            for i in range(lo, min(n, lo + 256)):
                m, k = int(DURATIONS_S[i % 5] * 1000), int(DURATIONS_S[i % 5] * 50)
                items.append((i, TrialData(
                    taxels=base[i:i + m], seq=np.arange(m) % 65536, force_g=np.full(k, 500.0),
                    force_time_s=np.arange(k) / 50, speed_mm_s=np.full(k, 80.0), speed_time_s=np.arange(k) / 50,
                    attrs={"aligned_to_index": True, "sensitivity": 1.0, "source": "simulated",
                           "start_phase_mm": 0.01, "started_utc": ""})))
            w.write_trials(items)


def timed(fn) -> tuple[float, float]:
    t, c = time.perf_counter(), time.process_time()
    fn()
    return time.perf_counter() - t, time.process_time() - c


def plain_read(path: Path) -> None:
    with h5py.File(path, "r") as f:
        for name in f["recording"]:
            f["recording"][name][()]


def per_trial_attrs(path: Path, share: int) -> None:
    with open_session(path) as s:
        for tid in s.completed_ids()[::share]:
            s.trial_attrs(tid)


def summary(path: Path) -> None:
    from rigctl.cli.info import session_summary

    session_summary(path)


def command(path: Path) -> tuple[float, float]:
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    subprocess.run([sys.executable, "-m", "rigctl", "info", str(path)], check=True, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def bench(path: Path, n: int, share: int = 10) -> dict:
    if not path.exists():
        make_session(path, n)
    summary(path)  # warm: the page cache and the imports, as for a second look at a file
    out = {"trials": n, "file_bytes": path.stat().st_size, "load_average": os.getloadavg()[0]}
    out["plain read"] = timed(lambda: plain_read(path))
    wall, cpu = timed(lambda: per_trial_attrs(path, share))
    out["per-trial attrs"] = (wall * share, cpu * share)
    with open_session(path) as s:
        out["sealed"] = bool(s.trusted_facts())
    out["info"] = timed(lambda: summary(path))
    st = path.stat()
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 1))  # unsealed
    try:
        summary(path)  # warm, as above
        out["info, no facts"] = timed(lambda: summary(path))
    finally:
        os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    out["rigctl info"] = command(path)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=4800)
    ap.add_argument("--keep", type=Path, default=None, help="Session file to make once and reuse.")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="rigctl-bench-info-") as tmp:
        r = bench(args.keep or Path(tmp) / "big.h5", args.trials)
    if args.json:
        print(json.dumps(r, indent=2))
        return
    print(f"{r['trials']} trials, {r['file_bytes'] / 1e6:.0f} MB, load average {r['load_average']:.1f}, "
          f"{'sealed with trial facts' if r['sealed'] else 'NO trusted trial facts (a file from before them?)'}")
    print(f"{'what':<16} {'wall s':>8} {'CPU s':>8} {'x plain read':>13}")
    base = r["plain read"][0]
    for name in ("plain read", "per-trial attrs", "info", "info, no facts", "rigctl info"):
        wall, cpu = r[name]
        print(f"{name:<16} {wall:8.2f} {cpu:8.2f} {wall / base:13.1f}")
    print(f"target: rigctl info < {TARGET_S:g} s ({'met' if r['rigctl info'][0] < TARGET_S else 'NOT met'} here)")


if __name__ == "__main__":
    main()
