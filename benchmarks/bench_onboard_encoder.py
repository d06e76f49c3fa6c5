"""The on-board SA encoder on handheld sessions (issue 37, part 7): the real-time classifier on features the board
computes against features the host computes, on the same recorded scans.

For each block (training, calibration, real-time: session + its encoded file), every scan's 9 real-time taxels and
its window speeds (the tracker's velocity averaged per 100 ms window, as ``rigctl encode`` takes them, sent to the
board rounded to 0.01 mm/s) go through the firmware's encoder on the simulated ATmega328P
(:func:`rigctl.simulation.sa_board.run_scan`: ``sa_bench_uno.elf`` under simavr, avr-libc's float); the board's
scaled-window counts become SR features on the host (:func:`rigctl.encoding.features.realtime_rates`, the real-time
durations from the speeds it sent), checked bit for bit against the host's encoder (float32
:class:`~rigctl.encoding.izhikevich.StreamingEncoder`, :func:`~rigctl.encoding.speed.incremental_scale`,
:func:`~rigctl.encoding.features.realtime_features`) on the same samples and speeds. The host's features are the
encoded files' ``realtime_speed_scaled`` (speeds not rounded). The
paper's real-time classifier (:class:`rigctl.analysis.realtime_model.RealtimeClassifier`: LDA on 25 PCs of the
training block, re-centred on the calibration block) classifies the real-time block once on each.

Sessions (docs/results.md 3b)::

    rigctl acquire handheld_training --sim --seed 1 --out tr.h5
    rigctl acquire handheld_calibration --sim --out cal.h5
    rigctl acquire handheld_realtime --sim --seed 7 --out rt.h5
    rigctl encode tr.h5 --out tr.enc.h5 --variant realtime_original --variant realtime_speed_scaled   (cal, rt too)

``--kernel fixed`` runs the integer kernel (``sa_bench_fixed_uno.elf``, -DSA_FIXED) instead of the float32 one;
``--mirror`` runs the host's copy of the board's kernel (:class:`rigctl.encoding.fixed_sa.FixedSAEncoder`, or the
float32 :class:`~rigctl.encoding.izhikevich.StreamingEncoder`) instead of simavr: the same spikes
(tests/firmware/test_fw_sa_encoder.py holds them equal bit for bit), seconds instead of ~13 minutes.

``--live RT_HOST.h5 RT_BOARD.h5`` compares two live real-time blocks of the same scans instead (the same seed: the
simulated operator's passes are the same): one encoded on the host (``rigctl acquire handheld_realtime --sim --seed 7
--classify tr.enc.h5 --calibration cal.enc.h5``), one on the board in the loop (the same with ``--handheld --hil
--onboard-encoder``: ENCODE at the tracked entry, the tracker's velocity per window as SPEED, FINISH past the end;
the Uno encoder image under simavr): each block's logged predictions (accuracy at the PCs it was classified with),
the scans predicted alike, and the board's record (samples encoded against the scan's duration, held windows,
dropped samples).

Usage: python benchmarks/bench_onboard_encoder.py TR.h5 TR.enc.h5 CAL.h5 CAL.enc.h5 RT.h5 RT.enc.h5
       [--workers 2] [--n-pcs 25] [--kernel float32|fixed] [--mirror]
       python benchmarks/bench_onboard_encoder.py --live RT_HOST.h5 RT_BOARD.h5
"""

from __future__ import annotations

import argparse
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from rigctl import firmware
from rigctl.analysis.realtime_model import RealtimeClassifier
from rigctl.encoding.features import realtime_features, realtime_rates
from rigctl.encoding.fixed_sa import FixedSAEncoder
from rigctl.encoding.izhikevich import StreamingEncoder
from rigctl.encoding.normalise import TaxelRange
from rigctl.encoding.params import EncodeParams
from rigctl.encoding.speed import incremental_scale, window_speeds
from rigctl.encoding.spikes import SpikeTrains
from rigctl.simulation import sa_board
from rigctl.storage.encoded import open_encoded
from rigctl.storage.session import open_session

VARIANT = "realtime_speed_scaled"


def host_raster(x: np.ndarray, rng: TaxelRange, p: EncodeParams, kernel: str) -> np.ndarray:
    """(n, 9) uint8 spike raster of the host's copy of the board's ``kernel`` ("float32" or "fixed")."""
    if kernel == "fixed":
        return FixedSAEncoder(rng, k_sa=p.k_sa).raster(x)
    sa = StreamingEncoder(x.shape[1], normalise=rng, k_sa=p.k_sa, dtype=np.float32).process(x).sa
    out = np.zeros(x.shape, np.uint8)
    for k in range(x.shape[1]):
        out[np.rint(sa.train(0, k) * p.fs_hz).astype(np.int64), k] = 1
    return out


def board_block(session: str, encoded: str, build, workers: int, kernel: str = "float32",
                mirror: bool = False) -> dict:
    """The block's host features, board features, labels and the board's agreement figures."""
    with open_encoded(encoded) as f:
        p = EncodeParams.from_dict(f.parameters)
        host = f.features(VARIANT)
        ids = [int(t) for t in f.trials["trial_id"]]
        labels = np.asarray(f.trials["texture"]).astype(str)
        norm = f.normalisation
    taxels = list(p.realtime_taxels or range(9))
    lo, hi = norm["taxel_min"][taxels], norm["taxel_max"][taxels]
    with open_session(session) as s:
        blk = s.read_taxels(ids, traces=True)
    per = int(round(p.window_s * p.fs_hz))

    def one(i: int):
        x = np.ascontiguousarray(blk.data[blk.starts[i]:blk.starts[i + 1]][:, taxels])
        t, v = blk.speed_traces[i]
        ws = window_speeds(t, v, x.shape[0] / p.fs_hz, p.window_s)
        cmm = np.clip(np.round(ws * 100.0), 0, 0xFFFF).astype(np.uint16)
        rng = TaxelRange(lo, hi)
        if mirror:
            raster, counts, cycles = host_raster(x, rng, p, kernel), None, 0
        else:
            scan = sa_board.run_scan(x, lo, hi, cmm, board="uno", build=build, kernel=kernel)
            raster, counts, cycles = scan.raster, scan.counts, scan.cycles_mean
            assert scan.held_windows == 0
        trains = SpikeTrains.from_lists([[np.flatnonzero(raster[:, k]) / p.fs_hz for k in range(len(taxels))]])
        scaled, edges = incremental_scale(trains, [cmm / 100.0], p.realtime_reference_speed_mm_s, p.window_s)
        # the board's counts are the host's map of its own spikes with the speeds it was sent
        host_counts = scaled.window_counts(p.window_s, p.n_windows_realtime)[0]
        assert counts is None or np.array_equal(host_counts, counts)
        assert per == 100
        board = realtime_rates(host_counts[None], edges, window_s=p.window_s)[0]
        # the host's copy of the kernel on the same samples and the same (rounded) speeds: the board's features
        sa = SpikeTrains.from_lists([[np.flatnonzero(r) / p.fs_hz for r in host_raster(x, rng, p, kernel).T]])
        same = realtime_features(*incremental_scale(sa, [cmm / 100.0], p.realtime_reference_speed_mm_s, p.window_s),
                                 n_windows=p.n_windows_realtime, window_s=p.window_s)[0]
        return board, cycles, bool(np.array_equal(board, same))

    with ThreadPoolExecutor(workers) as pool:
        res = list(pool.map(one, range(len(ids))))
    board = np.stack([r[0] for r in res])
    near = np.abs(board - host) <= 0.01 * np.maximum(np.abs(host), 1e-9)
    return {"host": host, "board": board, "labels": labels, "cycles": float(np.mean([r[1] for r in res])),
            "same": float(np.mean([r[2] for r in res])), "near": float(np.mean(near)),
            "max_diff": float(np.max(np.abs(board - host)))}


def live_blocks(host_path: str, board_path: str) -> None:
    """``--live``: the two real-time blocks' logged predictions and the board's record (module docstring)."""
    preds = {}
    for who, path in (("host", host_path), ("board", board_path)):
        with open_session(path) as s:
            ev = {int(e["trial_id"]): e for e in s.events if e.get("kind") == "prediction"}
            preds[who] = ev
            n_pcs = {e.get("n_pcs") for e in ev.values()}
            acc = float(np.mean([bool(e["correct"]) for e in ev.values()])) if ev else float("nan")
            print(f"{who}-encoded live block {path}: {len(ev)} scans, {100 * acc:.1f} % correct at {n_pcs} PCs")
            if who == "board":
                trials = [s.trial(t) for t in s.completed_ids()]
                rec = [d.onboard for d in trials if d.onboard is not None]
                lag = [o.samples / o.rate_hz - d.attrs["scan_duration_s"] for d, o in zip(trials, rec)]
                held = [len(o.held_windows) / max(o.speeds_mm_s.size, 1) for o in rec]
                print(f"  the board's record: {len(rec)}/{len(trials)} trials encoded on board; encoded span minus the "
                      f"scan's duration {np.mean(lag) * 1000:.0f} ms mean ({np.min(lag) * 1000:.0f} to "
                      f"{np.max(lag) * 1000:.0f}); windows held {100 * np.mean(held):.1f} %; samples dropped "
                      f"{sum(o.dropped_samples for o in rec)}")
    both = sorted(set(preds["host"]) & set(preds["board"]))
    alike = sum(preds["host"][t]["predicted"] == preds["board"][t]["predicted"] for t in both)
    print(f"predicted alike: {alike}/{len(both)} scans")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("files", nargs="*", metavar="FILE")
    ap.add_argument("--live", nargs=2, metavar=("RT_HOST", "RT_BOARD"), default=None)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--n-pcs", type=int, default=25)
    ap.add_argument("--kernel", choices=sorted(sa_board.KERNELS), default="float32")
    ap.add_argument("--mirror", action="store_true", help="the host's copy of the kernel instead of simavr")
    a = ap.parse_args()
    if a.live is not None:
        live_blocks(*a.live)
        return
    if len(a.files) != 6:
        ap.error("give the six files TR.h5 TR.enc.h5 CAL.h5 CAL.enc.h5 RT.h5 RT.enc.h5 (or --live RT_HOST RT_BOARD)")
    build = None if a.mirror else firmware.build(targets=("sa-bench",))
    t0 = time.monotonic()
    blocks = {}
    for name, (sess, enc) in zip(("training", "calibration", "realtime"), zip(a.files[::2], a.files[1::2])):
        blocks[name] = b = board_block(sess, enc, build, a.workers, a.kernel, a.mirror)
        print(f"{name}: {b['labels'].size} scans; {100 * b['same']:.1f} % of them with features bit for bit the host "
              f"encoder's on the speeds sent (0.01 mm/s); against the encoded file's (unrounded speeds): "
              f"{100 * b['near']:.2f} % of features within 1 %, largest difference {b['max_diff']:.2f} spikes/s; "
              f"{b['cycles']:.0f} cycles per 1 ms step on the ATmega328P")
    tr, cal, rt = blocks["training"], blocks["calibration"], blocks["realtime"]
    for who in ("host", "board"):
        clf = RealtimeClassifier(tr[who], tr["labels"], n_pcs=a.n_pcs)
        clf.calibrate(cal[who])
        acc = float(np.mean(clf.predict(rt[who]) == rt["labels"]))
        print(f"{who}-encoded: real-time block {100 * acc:.1f} % correct at {clf.n_pcs} PCs ({VARIANT})")
    print(f"({time.monotonic() - t0:.0f} s)")


if __name__ == "__main__":
    main()
