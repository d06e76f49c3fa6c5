"""docs/results.md section 3b: the handheld system with the tracker on the wrist (its velocity error swept) and
Fig. 4C on a new session, as the paper's design.

    python scripts/handheld_tracker_error.py OUT_DIR [--errors 0,0.05,0.1] [--scale 1.0] [--pcs 25]

For each tracker velocity error e (rigctl.simulation.operator.OperatorConfig.tracker_speed_error: a per-scan bias of
standard deviation e and a slow drift of e / 2), the three blocks of docs/results.md 3b are recorded with the
simulated operator (training seed 1, calibration seed 0, real-time seed 7; ``--scale`` scales their trial counts),
each normalised with the training block's range (one normalisation, as the paper). Then, for both real-time
variants, with LDA on ``--pcs`` PCs:

- Fig. S5: trained on every training scan, re-centred on the calibration block's mean, tested on the real-time block
  (the live classifier's features: equal offline and live, tests/encoding/test_one_normalisation.py);
- Fig. 4C on a new session: trained on the training block's slow and medium scans, re-centred on the calibration
  block (another session), tested on the real-time block's slow and medium scans (trained profiles) and its other
  three profiles (untrained).

One classifier per task (no resampling: each number is one session's, as the paper's real-time block).
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np

from rigctl.acquisition.builtin import find_protocol
from rigctl.acquisition.handheld import HandheldRig
from rigctl.acquisition.protocol import Protocol, load_protocol
from rigctl.acquisition.runner import run_protocol
from rigctl.analysis.realtime_model import RealtimeClassifier
from rigctl.core.handheld import PlateAxis
from rigctl.encoding.normalise import TaxelRange
from rigctl.encoding.pipeline import encode_session
from rigctl.simulation.operator import OperatorConfig, SimulatedOperator
from rigctl.storage.encoded import open_encoded

VARIANTS = ("realtime_original", "realtime_speed_scaled")
BLOCKS = (("tr", "handheld_training", 1), ("cal", "handheld_calibration", 0), ("rt", "handheld_realtime", 7))
TRAINED = ("slow", "medium")


def record(folder: Path, error: float, scale: float) -> dict[str, Path]:
    """The three blocks at tracker error ``error``, encoded (the training block's range for all): name -> .enc.h5."""
    folder.mkdir(parents=True, exist_ok=True)
    out: dict[str, Path] = {}
    taxel_range = None
    for name, protocol, seed in BLOCKS:
        proto = load_protocol(find_protocol(protocol))
        assert isinstance(proto, Protocol)  # the built-in TOML protocols
        proto = replace(proto, trials_per_condition=max(1, round(proto.trials_per_condition * scale)))
        session = folder / f"{name}.h5"
        if not session.exists():
            op = SimulatedOperator(OperatorConfig(tracker_speed_error=error), seed=seed)
            rig = HandheldRig(op, axis=PlateAxis.from_touches(*op.touch_ends()), host_config_path=str(folder / "rig.json"))
            try:
                summary = run_protocol(proto, session, rig=rig)
            finally:
                rig.close()
            assert summary.ok, summary.failures
        enc = folder / f"{name}.enc.h5"
        if not enc.exists():
            encode_session(session, enc, variants=list(VARIANTS), taxel_range=taxel_range)
        if taxel_range is None:
            with open_encoded(enc) as f:
                n = f.normalisation
            taxel_range = TaxelRange(np.asarray(n["taxel_min"], np.float64), np.asarray(n["taxel_max"], np.float64),
                                     source=str(enc))
        out[name] = enc
    return out


def features(path: Path, variant: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    with open_encoded(path) as f:
        return f.features(variant), np.asarray(f.trials["texture"]), np.asarray(f.trials["profile"])


def scores(files: dict[str, Path], variant: str, n_pcs: int) -> dict[str, float]:
    """Accuracy (%) of S5, 4C trained and 4C untrained for one variant."""
    x_tr, y_tr, p_tr = features(files["tr"], variant)
    x_cal, _, _ = features(files["cal"], variant)
    x_rt, y_rt, p_rt = features(files["rt"], variant)
    s5 = RealtimeClassifier(x_tr, y_tr, n_pcs=n_pcs)
    s5.calibrate(x_cal)
    sel = np.isin(p_tr, TRAINED)
    c4 = RealtimeClassifier(x_tr[sel], y_tr[sel], n_pcs=min(n_pcs, int(sel.sum()) - 1))
    c4.calibrate(x_cal)
    trained = np.isin(p_rt, TRAINED)
    return {"S5": 100 * float(np.mean(s5.predict(x_rt) == y_rt)),
            "4C trained": 100 * float(np.mean(c4.predict(x_rt[trained]) == y_rt[trained])),
            "4C untrained": 100 * float(np.mean(c4.predict(x_rt[~trained]) == y_rt[~trained]))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path)
    ap.add_argument("--errors", default="0,0.05,0.1")
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--pcs", type=int, default=25)
    args = ap.parse_args()
    print("| tracker error | task | Original (%) | Speed Scaled (%) |")
    print("|---|---|---|---|")
    for error in (float(e) for e in args.errors.split(",")):
        files = record(args.out / f"err{error:g}", error, args.scale)
        got = {v: scores(files, v, args.pcs) for v in VARIANTS}
        for task in ("S5", "4C trained", "4C untrained"):
            print(f"| {100 * error:g} % | {task} | {got['realtime_original'][task]:.1f} | "
                  f"{got['realtime_speed_scaled'][task]:.1f} |", flush=True)


if __name__ == "__main__":
    main()
