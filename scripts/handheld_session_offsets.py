"""docs/results.md section 3b, "A new session with a real operator's errors": the live block and Fig. 4C on a new
session whose plate axis is off, for each alignment of the real-time classifier (issue 78 item 2).

    python scripts/handheld_session_offsets.py OUT_DIR [--offsets 0,2,4,6,8] [--scale 0.5] [--pcs 25]

Two designs, recorded with the simulated operator (``--scale`` scales the protocols' trial counts: 0.5 gives 50
training, 25 calibration and 50 real-time scans):

- the realistic session: every block with the operator's default session errors (rigctl.simulation.operator,
  "A session": calibration touches 1.5 mm sd per end, the tracker re-strapped 2 mm / 0.5 degree sd, a 2 % tracked
  velocity bias, hesitations); training seed 1 (its own session), calibration seed 0 and real-time seed 7 in one new
  session (session seed 7), each block's plate axis from its own session's touches;
- the sweep: exact sessions (the four errors 0) whose calibration and real-time blocks' plate axis is moved by d mm
  (the rig reads the finger d mm farther along than it is: it cuts d mm early), d in ``--offsets``.

All blocks normalised with their training block's range. For each alignment of
:class:`rigctl.analysis.realtime_model.RealtimeClassifier` and both real-time variants: S5 (trained on every
training scan, re-centred on the calibration block, tested on the real-time block) and Fig. 4C on the new session
(trained on the slow and medium training scans, tested on the real-time block's trained and untrained profiles).
"""

from __future__ import annotations

import argparse
import os
import resource
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from rigctl.acquisition.builtin import find_protocol
from rigctl.acquisition.handheld import HandheldRig
from rigctl.acquisition.protocol import Protocol, load_protocol
from rigctl.acquisition.runner import run_protocol
from rigctl.analysis.realtime_model import ALIGNMENTS, RealtimeClassifier
from rigctl.core.handheld import PlateAxis
from rigctl.encoding.normalise import TaxelRange
from rigctl.encoding.pipeline import encode_session
from rigctl.simulation.operator import OperatorConfig, SimulatedOperator
from rigctl.storage.encoded import open_encoded

VARIANTS = ("realtime_original", "realtime_speed_scaled")
TRAINED = ("slow", "medium")
EXACT = OperatorConfig(touch_error_mm=0.0, strap_offset_mm=0.0, strap_rotation_deg=0.0, session_speed_error=0.0)


def record_block(folder: Path, name: str, protocol: str, op: SimulatedOperator, axis: PlateAxis, scale: float,
                 taxel_range: TaxelRange | None) -> Path:
    """One block recorded and encoded (``taxel_range``: the training block's; None: its own). Returns the .enc.h5."""
    folder.mkdir(parents=True, exist_ok=True)
    proto = load_protocol(find_protocol(protocol))
    assert isinstance(proto, Protocol)
    proto = replace(proto, trials_per_condition=max(1, round(proto.trials_per_condition * scale)))
    session, enc = folder / f"{name}.h5", folder / f"{name}.enc.h5"
    if not session.exists():
        rig = HandheldRig(op, axis=axis, host_config_path=str(folder / f"{name}.rig.json"))
        try:
            summary = run_protocol(proto, session, rig=rig)
        finally:
            rig.close()
        assert summary.ok, summary.failures
    if not enc.exists():
        encode_session(session, enc, variants=list(VARIANTS), taxel_range=taxel_range)
    return enc


def range_of(enc: Path) -> TaxelRange:
    with open_encoded(enc) as f:
        n = f.normalisation
    return TaxelRange(np.asarray(n["taxel_min"], np.float64), np.asarray(n["taxel_max"], np.float64), source=str(enc))


def moved(axis: PlateAxis, d_mm: float) -> PlateAxis:
    """The axis moved back by d mm along itself: it reads every point d mm farther along."""
    u = axis.unit * d_mm
    return PlateAxis(tuple(map(float, np.subtract(axis.start_xyz, u))),  # type: ignore[arg-type]
                     tuple(map(float, np.subtract(axis.end_xyz, u))), axis.length_mm)  # type: ignore[arg-type]


def features(path: Path, variant: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    with open_encoded(path) as f:
        return f.features(variant), np.asarray(f.trials["texture"]), np.asarray(f.trials["profile"])


def scores(tr: Path, cal: Path, rt: Path, variant: str, alignment: str, n_pcs: int) -> dict[str, float]:
    """Accuracy (%) of S5, 4C trained and 4C untrained, and the calibration block's measured shift (mm)."""
    x_tr, y_tr, p_tr = features(tr, variant)
    x_cal, y_cal, _ = features(cal, variant)
    x_rt, y_rt, p_rt = features(rt, variant)
    s5 = RealtimeClassifier(x_tr, y_tr, n_pcs=n_pcs, alignment=alignment)
    s5.calibrate(x_cal, y_cal)
    sel = np.isin(p_tr, TRAINED)
    c4 = RealtimeClassifier(x_tr[sel], y_tr[sel], n_pcs=min(n_pcs, int(sel.sum()) - 1), alignment=alignment)
    c4.calibrate(x_cal, y_cal)
    trained = np.isin(p_rt, TRAINED)
    return {"S5": 100 * float(np.mean(s5.predict(x_rt) == y_rt)),
            "4C trained": 100 * float(np.mean(c4.predict(x_rt[trained]) == y_rt[trained])),
            "4C untrained": 100 * float(np.mean(c4.predict(x_rt[~trained]) == y_rt[~trained])),
            "shift_mm": s5.shift_mm}


def report(label: str, tr: Path, cal: Path, rt: Path, n_pcs: int, t0: float) -> None:
    for alignment in ALIGNMENTS:
        got = {v: scores(tr, cal, rt, v, alignment, n_pcs) for v in VARIANTS}
        ss, orig = got["realtime_speed_scaled"], got["realtime_original"]
        print(f"| {label} | {alignment} | {ss['shift_mm']:+.1f} | {orig['S5']:.1f} | **{ss['S5']:.1f}** | "
              f"{orig['4C trained']:.1f} / {orig['4C untrained']:.1f} | {ss['4C trained']:.1f} / "
              f"{ss['4C untrained']:.1f} |", flush=True)
    ru = resource.getrusage(resource.RUSAGE_SELF)
    print(f"<!-- {label}: wall {time.monotonic() - t0:.0f} s, CPU {ru.ru_utime + ru.ru_stime:.0f} s, "
          f"load {os.getloadavg()[0]:.1f} -->", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path)
    ap.add_argument("--offsets", default="0,2,4,6,8")
    ap.add_argument("--scale", type=float, default=0.5)
    ap.add_argument("--pcs", type=int, default=25)
    ap.add_argument("--only", choices=("realistic", "sweep", "both"), default="both")
    args = ap.parse_args()
    t0 = time.monotonic()
    print("| session | alignment | cal. shift (mm) | S5 Original | S5 Speed Scaled | 4C Original trained / untrained "
          "| 4C Speed Scaled trained / untrained |")
    print("|---|---|---|---|---|---|---|")
    if args.only in ("realistic", "both"):
        f = args.out / "realistic"
        op = SimulatedOperator(seed=1)
        tr = record_block(f, "tr", "handheld_training", op, PlateAxis.from_touches(*op.touch_ends()), args.scale, None)
        rng = range_of(tr)
        blocks = []
        for name, proto, seed in (("cal", "handheld_calibration", 0), ("rt", "handheld_realtime", 7)):
            op = SimulatedOperator(seed=seed, session_seed=7)
            blocks.append(record_block(f, name, proto, op, PlateAxis.from_touches(*op.touch_ends()), args.scale, rng))
        s1, s7 = SimulatedOperator(seed=1).session_errors(), SimulatedOperator(seed=7).session_errors()
        print(f"<!-- training session offset {s1['plate_offset_mm']:+.2f} mm, new session {s7['plate_offset_mm']:+.2f}"
              f" mm: {s7} -->")
        report(f"realistic (new session {float(s7['plate_offset_mm']) - float(s1['plate_offset_mm']):+.1f} mm "
               "from training's)", tr, *blocks, args.pcs, t0)
    if args.only in ("sweep", "both"):
        f = args.out / "exact"
        op = SimulatedOperator(EXACT, seed=1)
        tr = record_block(f, "tr", "handheld_training", op, PlateAxis.from_touches(*op.touch_ends()), args.scale, None)
        rng = range_of(tr)
        for d in (float(x) for x in args.offsets.split(",")):
            blocks = []
            for name, proto, seed in (("cal", "handheld_calibration", 0), ("rt", "handheld_realtime", 7)):
                op = SimulatedOperator(EXACT, seed=seed)
                axis = moved(PlateAxis.from_touches(*op.touch_ends()), d)
                blocks.append(record_block(f / f"d{d:g}", name, proto, op, axis, args.scale, rng))
            report(f"exact, axis +{d:g} mm", tr, *blocks, args.pcs, t0)


if __name__ == "__main__":
    main()
