"""Where the on-board encoder starts, against the host's cut, on the simulated operator's scans (issue 78 item 4).

The host's cut (rigctl.acquisition.handheld.cut_scan) starts a scan at the finger's entry into the plate's used part,
interpolated from the tracker. The board learns of the entry only when the host's tracker has shown it: its first
sample past the entry (the operator's tracker: 90-120 Hz), then the host's own lateness (``--late-ms``, uniform:
0-15 ms by default, its 5 ms poll and its scheduling; issue 78 measured 5-30 ms from the entry in all).
For each scan of the real-time block (``--scans``, the simulated operator, ``--seed``) the board's own C
(rigctl.simulation.onboard_c: common/sa_ring.c and the integer encoder, through cffi) encodes it twice from the
same ARM: starting at ENCODE's arrival (the board before its ring: ``encode``), and from the entry's sample out of its
ring (``entry``); each window's tracker speed is given 50 ms after the window (as the host sends it). The live
classifier (ScanClassifier: the training block, re-centred on the calibration block) classifies the host's cut scan
(its float32 live encoder) and the two board encodings (their counts frames).

Usage: python scripts/onboard_entry.py TR.enc.h5 CAL.enc.h5 [--scans 100] [--seed 7] [--late-ms 0 15]
(the blocks as in docs/results.md 3b: rigctl acquire handheld_training --sim --seed 1, handheld_calibration --sim,
rigctl encode ... --variant realtime_original --variant realtime_speed_scaled).
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from rigctl.acquisition.builtin import find_protocol
from rigctl.acquisition.handheld import cut_scan
from rigctl.acquisition.protocol import load_protocol
from rigctl.core.handheld import ScanError
from rigctl.devices.onboard_finger import WINDOW_S, _entered, window_speed_mm_s
from rigctl.encoding.features import counted_realtime_features
from rigctl.operations import ScanClassifier
from rigctl.rigs import board_range
from rigctl.simulation.onboard_c import BoardModel
from rigctl.simulation.operator import SimulatedOperator, plate_axis_of

RATE_HZ = 1000
#: the board's main loop encodes this many waiting samples per tick while it catches up (~0.45 spare a tick measured
#: under simavr, docs/firmware.md: 1.45)
CATCH_UP = 1.45
#: a window's SPEED reaches the board this long after the window ended, samples
SPEED_AFTER = 50


def board_features(board, x, rng_range, t, along, encode_at: int, from_sample: int, exit_row: int):
    """One scan on the board model: ARM at row 0, ENCODE(from_sample) arriving at row encode_at, speeds 50 ms after
    each window, FINISH at exit_row. Returns (features, the sample it began at, samples dropped)."""
    board.arm(rng_range.taxel_min, rng_range.taxel_max, rng_range.k)
    start, speeds = None, []
    for r in range(min(exit_row, x.shape[0])):
        if r == encode_at:
            start = board.begin(from_sample)
        board.tick(x[r], 2 if r % 20 < 9 else 1)  # CATCH_UP: 1.45 a tick
        if start is not None and r >= start + 100 * (len(speeds) + 1) + SPEED_AFTER:
            w = len(speeds)
            t0 = (start + 100 * w) / RATE_HZ
            speeds.append(window_speed_mm_s(t, along, t0, t0 + WINDOW_S, speeds[-1] if speeds else 0.0))
            board.speed(int(round(speeds[-1] * 100)))
    assert start is not None
    while len(speeds) < math.ceil((board.samples + 40) / 100):  # FINISH encodes what waits: its windows' speeds
        w = len(speeds)
        t0 = (start + 100 * w) / RATE_HZ
        speeds.append(window_speed_mm_s(t, along, t0, t0 + WINDOW_S, speeds[-1]))
        board.speed(int(round(speeds[-1] * 100)))
    res = board.finish(int(round(speeds[-1] * 100)))
    applied = np.round(np.asarray(speeds[:math.ceil(res.raster.shape[0] / 100)]), 2)
    return counted_realtime_features(res.counts, applied), res.start, res.dropped


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("training")
    ap.add_argument("calibration")
    ap.add_argument("--scans", type=int, default=100)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--late-ms", type=float, nargs=2, default=(0.0, 15.0))
    ap.add_argument("--n-pcs", type=int, default=25)
    a = ap.parse_args()
    clf = ScanClassifier(a.training, calibration=a.calibration, n_pcs=a.n_pcs)
    rng_range = board_range(a.training)
    plan = load_protocol(find_protocol("handheld_realtime")).plan()
    op = SimulatedOperator(seed=a.seed)
    axis = plate_axis_of(op)
    late = np.random.default_rng([a.seed, 78, 4])
    board = BoardModel()
    right = {"host": 0, "encode": 0, "entry": 0}
    same = {"encode": 0, "entry": 0}
    starts = {"encode": [], "entry": []}
    dropped = refused = 0
    t_begin = time.process_time()
    n = 0
    while n < a.scans:
        planned = plan[n % len(plan)]
        t_origin = op.clock_s
        raw = op.scan(planned)
        truth = str(planned.texture)
        ok = np.all(np.isfinite(raw.tracker_xyz), axis=1)
        t = np.asarray(raw.tracker_time_s, np.float64)[ok] - t_origin
        along = axis.along_mm(raw.tracker_xyz[ok])
        try:
            host = str(clf.model.predict(clf.features(cut_scan(raw, op.layout, axis)))[0])
        except ScanError:  # refused (the tracker lost the finger, ...): the operator scans again, as on the rig
            refused += 1
            continue
        i_out = int(np.flatnonzero(along > 250.0)[0])
        t_in = _entered(t[:i_out + 1], along[:i_out + 1])  # the last entry before the exit, as the host's cut
        seen = t[np.searchsorted(t, t_in)] + late.uniform(*a.late_ms) / 1000.0
        encode_at = math.ceil(seen * RATE_HZ)
        entry = math.ceil(t_in * RATE_HZ - 1e-6)
        t_out = t[i_out]
        exit_row = math.ceil((t_out + 0.03) * RATE_HZ)
        right["host"] += host == truth
        for mode, frm in (("encode", encode_at), ("entry", entry)):
            x = np.clip(raw.taxels[:, :9], 0, 1023).astype(np.uint16)
            feats, start, d = board_features(board, x, rng_range, t, along, encode_at, frm, exit_row)
            pred = str(clf.model.predict(feats)[0])
            right[mode] += pred == truth
            same[mode] += pred == host
            starts[mode].append(start - entry)
            dropped += d
        n += 1
    print(f"{n} scans (seed {a.seed}, the host {a.late_ms[0]:g}-{a.late_ms[1]:g} ms late after the tracker's "
          f"first sample past the entry; {time.process_time() - t_begin:.0f} s CPU)")
    print(f"host's cut, float32 live encoder: {right['host']}/{n} correct")
    for mode, what in (("encode", "board from ENCODE's arrival (before the ring)"),
                       ("entry", "board from the entry, out of its ring")):
        s = np.asarray(starts[mode])
        print(f"{what}: {right[mode]}/{n} correct, the host's prediction on {same[mode]}; start - entry "
              f"{s.min()}..{s.max()} samples (mean {s.mean():.1f}, {int(np.sum(s != 0))} scans not at the entry)")
    print(f"samples dropped by the board: {dropped}; scans refused by the host's cut and repeated: {refused}")


if __name__ == "__main__":
    main()
