"""Probe which of the simulated rig's physical levers move Table 1's far cells (issue 13).

Usage (from the repository root; ~1 CPU-minute per lever at 10 trials per condition)::

    python scripts/probe_table1.py --out-dir /tmp/probe [--trials-per-condition 10] [--seed 1] [--repeats 3]
                                   [--lever model --lever soft-pad --lever fine-plates --lever random-phase]

For each lever it renders the paper's protocol (``protocols/paper_dataset.toml``) from the model with that one
change, encodes it (``rigctl encode --no-spikes``), runs ``rigctl analyze --table1 --json`` and prints, per Table 1
row, the four variants' accuracies at 50 PCs and whether the paper's ordering holds; then two diagnostics of the
rows with untrained speeds:

- **collapse**: the share of the untrained-speed test trials that the classifier puts on its single most-chosen
  texture (``rigctl analyze`` prints it as "most-predicted class"; 1/16 = 6 % for an even spread; the model's
  unscaled variants put most of them on one or two plates);
- **first 20 windows**: PCA (50) + LDA on the unscaled variants' first 20 windows only, which every trial fills
  (no zero padding), on the untrained-speed trials: the share on the most-predicted plate and the accuracy;
- **trial means**: LDA on each trial's 36 per-train means (SA rate, and RA count per mm of travel) over its own
  windows, trained on the trained cells and tested on the untrained ones: how much speed-invariant texture
  information the trials carry, whatever the windowed features make of it.

Levers (each one change to the fitted model, nothing tuned to the table):

``model``
    the model as it is (:class:`rigctl.simulation.model.SensorConfig` defaults).
``soft-pad``
    a pad 3.3 x softer (``indentation_ref_mm`` 1.0 instead of 0.3): the pad conforms to the ridges, so the
    modulation is shallower and the level carries more of the texture.
``fine-plates``
    every ridged plate's spacing x 0.4 (base 6 mm, half space 3 mm, double space 12 mm; ridge width capped at
    0.6 x the spacing): each 100 ms window averages over one or more periods at every speed.
``random-phase``
    each trial starts at an arbitrary drum angle instead of at the index mark (``DrumConfig.start_at_index`` False,
    ``rigctl sim dataset --start-at any-angle``): the windows' modulation is no longer phase-locked to the trial
    start.
``drift``
    the fabric's sensitivity drifts by 10 % (sd) from trial to trial instead of 1 % (``sensitivity_drift``): a
    condition's trials recorded over hours rather than within a minute.
``strong-plates``
    plates whose per-taxel level patterns differ 4 x more than FabricSlide's fabrics (``plate_level_spread`` 0.1
    instead of 0.026), trials still phase-locked: a speed-invariant texture signature strong enough to put the
    pooled rows near 100 %.
``level-signature``
    not one lever but the combination that moves the texture information out of the phase-locked modulation into
    speed-invariant per-taxel levels: random phase, the soft pad, plates whose per-taxel level patterns differ 4 x
    more (``plate_level_spread`` 0.1 instead of FabricSlide's 0.026) and the 10 % drift. Only with it does Force
    Scaled beat Original at untrained speeds (the paper's +30 points), and then nearly every cell is near 100 %.
``level-signature-fabricslide``
    the same combination with FabricSlide's plate level spread (0.026): the pooled unscaled rows fall far below
    the paper's.

Output files go to ``--out-dir`` (``<lever>.h5``, ``<lever>.enc.h5``, ``<lever>.json``, and ``fine-plates.toml``);
an existing file there is refused, before anything is rendered, unless ``--overwrite``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np

REPO = Path(__file__).resolve().parents[1]
PROTOCOL = REPO / "protocols" / "paper_dataset.toml"
VARIANTS = ("original", "speed_scaled", "force_scaled", "speed_force_scaled")
ROWS = ("textures", "groups", "untrained_speed_force", "untrained_force", "untrained_speed", "trained")
LEVERS = ("model", "soft-pad", "fine-plates", "random-phase", "drift", "strong-plates", "level-signature",
          "level-signature-fabricslide")
TRAINED_SPEEDS, TRAINED_FORCES = (40.0, 60.0, 80.0), (250.0, 500.0)


def _fine_plates_protocol(out_dir: Path, scale: float = 0.4) -> Path:
    """The paper's protocol with a [texture_set] whose A-P plates have their spacing scaled by ``scale``."""
    from rigctl.simulation.textures import TEXTURES

    lines = [line for line in PROTOCOL.read_text().splitlines() if not line.startswith("#")]
    geo, groups = [], {}
    for label, t in TEXTURES.items():
        groups.setdefault(t.group, []).append(label)
        if t.kind == "smooth":
            geo.append(f'{label} = {{ kind = "smooth" }}')
            continue
        p = t.period_mm * scale
        w = p if t.kind == "wave" else min(t.width_mm, 0.6 * p)
        geo.append(f'{label} = {{ kind = "{t.kind}", height_mm = {t.height_mm}, period_mm = {p}, width_mm = {w} }}')
    group_items = ", ".join(f'"{g}" = {json.dumps(labels)}' for g, labels in groups.items())
    lines += ["", "[texture_set]", 'name = "paper A-P, spacing x 0.4"',
              f"textures = {json.dumps(list(TEXTURES))}", f"groups = {{ {group_items} }}",
              "[texture_set.geometry]", *geo]
    path = out_dir / "fine-plates.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


def render(lever: str, out: Path, out_dir: Path, tpc: int, seed: int) -> None:
    """Render the paper's protocol with one lever applied into the session file ``out`` (``tpc`` trials per
    condition, dataset ``seed``); ``fine-plates`` also writes its protocol, ``out_dir/fine-plates.toml``."""
    from rigctl.acquisition.protocol import load_protocol
    from rigctl.simulation.dataset import generate_dataset
    from rigctl.simulation.model import RigConfig

    cfg, protocol = RigConfig(), PROTOCOL
    if lever == "soft-pad":
        cfg.sensor = dataclasses.replace(cfg.sensor, indentation_ref_mm=1.0)
    elif lever == "drift":
        cfg.sensor = dataclasses.replace(cfg.sensor, sensitivity_drift=0.1)
    elif lever == "strong-plates":
        cfg.sensor = dataclasses.replace(cfg.sensor, plate_level_spread=0.1)
    elif lever == "level-signature":
        cfg.sensor = dataclasses.replace(cfg.sensor, indentation_ref_mm=1.0, plate_level_spread=0.1,
                                         sensitivity_drift=0.1)
        cfg.drum.start_at_index = False
    elif lever == "fine-plates":
        protocol = _fine_plates_protocol(out_dir)
    elif lever == "random-phase":
        cfg.drum.start_at_index = False
    elif lever == "level-signature-fabricslide":
        cfg.sensor = dataclasses.replace(cfg.sensor, indentation_ref_mm=1.0, sensitivity_drift=0.1)
        cfg.drum.start_at_index = False
    generate_dataset(load_protocol(protocol), out, trials_per_condition=tpc, seed=seed, config=cfg, overwrite=True)


def trial_mean_lda(enc: Path) -> dict:
    """Diagnostics of the unscaled variants: LDA on per-trial train means (trained cells -> untrained cells, %), and
    PCA + LDA on the first 20 windows only (``first20``: accuracy and the top class's share on untrained speeds)."""
    from sklearn.decomposition import PCA
    from sklearn.discriminant_analysis import LinearDiscriminantAnalysis

    with h5py.File(enc, "r") as f:
        tr = f["trials"][...]
        out = {}
        label = np.asarray([t.decode() if isinstance(t, bytes) else str(t) for t in tr["texture"]])
        v, force = tr["speed_mm_s"].astype(float), tr["force_g"].astype(float)
        n_win = np.round(tr["duration_s"] / 0.1).astype(int)
        trained = np.isin(v, TRAINED_SPEEDS) & np.isin(force, TRAINED_FORCES)
        us, uf = ~np.isin(v, TRAINED_SPEEDS), ~np.isin(force, TRAINED_FORCES)
        for var in ("original", "force_scaled"):
            x = f["features/" + var][...]
            n_trains = x.shape[1] // 60
            x = x.reshape(len(tr), n_trains, 60)
            m = np.stack([x[i, :, : n_win[i]].mean(axis=1) for i in range(len(tr))])
            m[:, n_trains // 2:] *= (0.1 * v[:, None]) ** -1  # RA: spikes per mm of travel, not per window
            ok = LinearDiscriminantAnalysis().fit(m[trained], label[trained]).predict(m) == label
            out[var] = {"untrained_speed": 100 * ok[us & ~uf].mean(), "untrained_force": 100 * ok[~us & uf].mean(),
                        "untrained_speed_force": 100 * ok[us & uf].mean()}
            w20 = x[:, :, :20].reshape(len(tr), -1).astype(np.float64)
            pca = PCA(50, random_state=0).fit(w20[trained])
            pred = LinearDiscriminantAnalysis().fit(pca.transform(w20[trained]), label[trained]).predict(
                pca.transform(w20[us & ~uf]))
            _, counts = np.unique(pred, return_counts=True)
            out[var]["first20"] = {"accuracy": 100 * (pred == label[us & ~uf]).mean(),
                                   "top_share": 100 * counts.max() / counts.sum()}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out-dir", type=Path, required=True)
    ap.add_argument("--trials-per-condition", type=int, default=10)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--lever", action="append", choices=LEVERS)
    ap.add_argument("--overwrite", action="store_true")
    a = ap.parse_args(argv)
    levers = a.lever or list(LEVERS)
    a.out_dir.mkdir(parents=True, exist_ok=True)
    planned = [a.out_dir / f"{lv}{ext}" for lv in levers for ext in (".h5", ".enc.h5", ".json")]
    if "fine-plates" in levers:
        planned.append(a.out_dir / "fine-plates.toml")
    existing = [p for p in planned if p.exists()]
    if existing and not a.overwrite:
        print(f"refusing to overwrite {', '.join(map(str, existing))} (use --overwrite)", file=sys.stderr)
        return 2
    rigctl = [sys.executable, "-m", "rigctl"]
    for lv in levers:
        h5, enc, js = (a.out_dir / f"{lv}{ext}" for ext in (".h5", ".enc.h5", ".json"))
        for p in (h5, enc, js):
            p.unlink(missing_ok=True)
        render(lv, h5, a.out_dir, a.trials_per_condition, a.seed)
        subprocess.run([*rigctl, "encode", str(h5), "--out", str(enc), "--no-spikes", "--quiet"], check=True,
                       stdout=subprocess.DEVNULL)
        res = subprocess.run([*rigctl, "analyze", str(enc), "--table1", "--json", "--repeats",
                              str(a.repeats), "--variants", ",".join(VARIANTS)], check=True, capture_output=True,
                             text=True)
        report = json.loads(res.stdout)
        report["trial_means"] = trial_mean_lda(enc)
        js.write_text(json.dumps(report))
        print(f"\n== {lv} ({a.trials_per_condition} per condition, seed {a.seed}, {a.repeats} repetitions; 50 PCs:"
              f" {' / '.join(VARIANTS)})")
        for row in ROWS:
            task = report["tasks"][row]
            cells = " / ".join(f"{task['variants'][v]['table']['mu_pct']:5.1f}" for v in VARIANTS)
            order = report["ordering"].get(row)
            held = "" if order is None else ("ordering holds" if order["holds"] else "ordering NOT held")
            collapse = ""
            if row in report.get("collapse", {}) and row != "untrained_force":
                shares = [100 * report["collapse"][row][v]["top_share"] for v in VARIANTS]
                collapse = "  collapse " + " / ".join(f"{s:3.0f}%" for s in shares)
            print(f"  {task['title'][:36]:36s} {cells}  {held}{collapse}")
        tm = report["trial_means"]
        keys = ("untrained_speed", "untrained_force", "untrained_speed_force")
        print("  trial means (LDA, original / force_scaled): " + "; ".join(
            f"{k.replace('_', ' ')} {tm['original'][k]:.0f} / {tm['force_scaled'][k]:.0f}" for k in keys))
        print("  first 20 windows, untrained speed (original / force_scaled): accuracy "
              f"{tm['original']['first20']['accuracy']:.0f} / {tm['force_scaled']['first20']['accuracy']:.0f}, "
              f"top class {tm['original']['first20']['top_share']:.0f} / {tm['force_scaled']['first20']['top_share']:.0f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
