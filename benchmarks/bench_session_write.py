"""Session-file write benchmark: what crash safety costs per trial, side by side in one run.

Writes the same paper-sized trials (3 s at 1 kHz x 18 taxels, traces at 50 Hz) four ways and prints ms per trial,
the ratio to the unsafe baseline, and how many times faster than real time the writer alone is:

- ``plain``: h5py straight into the file, kept open (the baseline: fast, but a kill -9 mid-write can corrupt it);
- ``trial``: :meth:`SessionWriter.write_trial` as ``rigctl acquire`` uses it (open, overlay, journaled commit with
  fsync, close, per trial);
- ``trial-nosync``: the same without fsync (``durable=False``: survives kill -9, not a power cut);
- ``batch``: :meth:`SessionWriter.write_trials` with 256 trials per commit, no fsync (the dataset generator's way).

Usage: python benchmarks/bench_session_write.py [--trials 200] [--json]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

from rigctl.storage.session import SessionWriter, TrialData


def make_trial(rng: np.random.Generator, duration_s: float = 3.0) -> TrialData:
    n = int(duration_s * 1000)
    t = np.arange(n) / 1000.0
    # a texture-like signal: periodic ridges plus noise, 10-bit
    base = 500 + 120 * np.sin(2 * np.pi * 80 / 5.0 * t)[:, None] * rng.uniform(0.5, 1, 18)[None, :]
    taxels = np.rint(np.clip(base + rng.normal(0, 4, (n, 18)), 0, 1023))  # integer counts
    m = int(duration_s * 50)
    return TrialData(taxels=taxels, force_g=rng.normal(500, 2, m), force_time_s=np.arange(m) / 50,
                     speed_mm_s=np.full(m, 80.0), speed_time_s=np.arange(m) / 50,
                     attrs={"started_utc": "2026-01-01T00:00:00+00:00", "settle_time_s": 0.3})


def plan(n: int) -> list[dict]:
    return [dict(trial_id=i, texture="B", speed_mm_s=80, force_g=500, duration_s=3.0) for i in range(n)]


def bench(n: int) -> dict:
    rng = np.random.default_rng(0)
    trials = [make_trial(rng) for _ in range(8)]
    out = {}
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        # baseline: plain h5py, file kept open, same group layout
        w = SessionWriter.create(d / "plain.h5", plan=plan(n), durable=False)
        t0 = time.perf_counter()
        with h5py.File(d / "plain.h5", "r+") as f:
            for i in range(n):
                w._write_group(f, w._plan[i], trials[i % 8])
                f["plan"][i] = w._plan[i]
        out["plain"] = (time.perf_counter() - t0) / n
        for name, durable in (("trial", True), ("trial-nosync", False)):
            w = SessionWriter.create(d / f"{name}.h5", plan=plan(n), durable=durable)
            t0 = time.perf_counter()
            for i in range(n):
                w.write_trial(i, trials[i % 8])
            out[name] = (time.perf_counter() - t0) / n
        w = SessionWriter.create(d / "batch.h5", plan=plan(n), durable=False)
        t0 = time.perf_counter()
        for lo in range(0, n, 256):
            w.write_trials((i, trials[i % 8]) for i in range(lo, min(n, lo + 256)))
        out["batch"] = (time.perf_counter() - t0) / n
        out["bytes_per_trial"] = (d / "batch.h5").stat().st_size / n
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    r = bench(args.trials)
    if args.json:
        print(json.dumps(r, indent=2))
        return
    print(f"{args.trials} trials of 3 s (54,000 ADC values each), {r['bytes_per_trial'] / 1e3:.0f} kB per trial on disk")
    print(f"{'way':<14} {'ms/trial':>9} {'x plain':>8} {'x real time':>12}")
    for name in ("plain", "trial", "trial-nosync", "batch"):
        s = r[name]
        print(f"{name:<14} {s * 1e3:9.2f} {s / r['plain']:8.2f} {3.0 / s:12.0f}")


if __name__ == "__main__":
    main()
