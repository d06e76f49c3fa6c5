"""docs/results.md section 6: the spiking-network guide's rate-coded stand-in beside PCA + LDA on one split.

    python scripts/spike_split_compare.py ENC.h5 EVENTS_DIR [EVENTS_DIR ...] [--task untrained_speed] [--pcs 50]

EVENTS_DIR: folders of ``rigctl export events`` (the first one's ``splits.json`` is the split); each is scored with
the guide's stand-in (docs/guides/spiking-networks.md: per-neuron spike counts in 100 ms windows, log1p, logistic
regression), and the encoded file's features of the same variants with PCA (``--pcs``) + LDA, on exactly the same
training and test trials.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from sklearn.decomposition import PCA
from sklearn.discriminant_analysis import LinearDiscriminantAnalysis
from sklearn.linear_model import LogisticRegression
from sklearn.pipeline import make_pipeline

from rigctl.storage import open_encoded


def rate_code(folder: Path, ids: list[int], window_us: int = 100_000, n_windows: int = 20) -> tuple[np.ndarray, np.ndarray]:
    xs, ys = [], []
    for trial_id in ids:
        z = np.load(folder / f"trial_{trial_id:06d}.npz")
        ev, (w, h, p) = z["events"], z["sensor_size"]
        neuron = (ev["p"] * h + ev["y"]) * w + ev["x"]
        window = np.minimum(ev["t"] // window_us, n_windows - 1)
        counts = np.zeros((w * h * p, n_windows))
        np.add.at(counts, (neuron, window), 1)
        xs.append(counts.ravel())
        ys.append(str(z["texture"]))
    return np.log1p(np.asarray(xs)), np.asarray(ys)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("encoded")
    ap.add_argument("events", nargs="+")
    ap.add_argument("--task", default="untrained_speed")
    ap.add_argument("--pcs", type=int, default=50)
    a = ap.parse_args()
    split = json.loads((Path(a.events[0]) / "splits.json").read_text())["tasks"][a.task]["folds"][0]
    with open_encoded(a.encoded) as enc:
        row = {int(t): i for i, t in enumerate(enc.trials["trial_id"])}
        texture = enc.trials["texture"].astype(str)
        tr = np.asarray([row[i] for i in split["train"]])
        te = np.asarray([row[i] for i in split["test"]])
        print(f"{a.task}: {tr.size} training trials, {te.size} test trials, {len(set(texture))} textures")
        for folder in map(Path, a.events):
            variant = json.loads((folder / "rigctl_export.json").read_text())["variant"]
            x_tr, y_tr = rate_code(folder, split["train"])
            x_te, y_te = rate_code(folder, split["test"])
            stand_in = LogisticRegression(max_iter=2000).fit(x_tr, y_tr).score(x_te, y_te)
            f = enc.features(variant)
            n_pcs = min(a.pcs, tr.size - 1, f.shape[1])
            lda = make_pipeline(PCA(n_pcs, random_state=0), LinearDiscriminantAnalysis()).fit(f[tr], texture[tr])
            print(f"{variant}: rate-coded stand-in {stand_in:.1%}, PCA ({n_pcs} PCs) + LDA "
                  f"{lda.score(f[te], texture[te]):.1%}")


if __name__ == "__main__":
    main()
