"""Reports of analysis results: the paper's Table 1 layout, JSON / CSV, and Fig. 3-like plots (matplotlib, Agg).

Table 1 of the paper: "Classification Accuracy with 50 PCs (%)", rows Individual Textures, Texture Groups,
Untrained Speed and Force, Untrained Force, Untrained Speed, Trained Speed and Force; columns mu / sigma (n = 20) for
Original, Speed Scaled, Force Scaled, Speed and Force Scaled (:data:`PAPER_TABLE1`).
"""

from __future__ import annotations

import csv
import io
import json
from dataclasses import dataclass
from typing import Any

import numpy as np

from rigctl.analysis.data import VARIANT_TITLES, VARIANTS
from rigctl.analysis.results import BASELINE_PREFIX, TaskResults, task_title
from rigctl.storage.outputs import CURVES_CSV_HEADER, figure_metadata

__all__ = [
    "PAPER_TABLE1",
    "TABLE1_ROWS",
    "table1",
    "format_table1",
    "to_json",
    "to_csv",
    "plot_curves",
    "plot_confusions",
    "paper_ordering",
    "format_ordering",
    "size_note",
    "PAPER_SIZE",
    "OrderingPair",
    "prediction_collapse",
    "format_collapse",
    "Collapse",
    "ERROR_BARS",
    "chance_pct",
    "mark",
    "plottable",
    "n_text",
    "task_title",
]

#: what the error bars and the sd columns are (Curve.sd)
ERROR_BARS = "error bars: +-1 SD over repetitions (sample SD)"


TABLE1_ROWS = ("textures", "groups", "untrained_speed_force", "untrained_force", "untrained_speed", "trained")

#: the paper's Table 1: task -> variant -> (mu %, sigma %) at 50 PCs
PAPER_TABLE1 = {
    "textures": {"original": (91.78, 0.55), "speed_scaled": (97.76, 0.14), "force_scaled": (96.84, 0.43),
                 "speed_force_scaled": (98.85, 0.16)},
    "groups": {"original": (81.83, 0.53), "speed_scaled": (95.89, 0.26), "force_scaled": (92.20, 0.43),
               "speed_force_scaled": (97.78, 0.19)},
    "untrained_speed_force": {"original": (37.44, 1.28), "speed_scaled": (69.98, 0.87), "force_scaled": (67.01, 0.85),
                              "speed_force_scaled": (83.15, 0.80)},
    "untrained_force": {"original": (57.35, 0.79), "speed_scaled": (64.18, 0.55), "force_scaled": (89.38, 0.43),
                        "speed_force_scaled": (88.73, 0.52)},
    "untrained_speed": {"original": (36.81, 0.66), "speed_scaled": (85.52, 0.34), "force_scaled": (67.53, 0.78),
                        "speed_force_scaled": (91.50, 0.27)},
    "trained": {"original": (99.93, 0.04), "speed_scaled": (99.95, 0.04), "force_scaled": (99.91, 0.06),
                "speed_force_scaled": (99.96, 0.04)},
}


def table1(res: TaskResults, n_pcs=50):
    """Table 1 values from results: ``{task: {variant: (mu %, sigma %)}}`` at ``n_pcs`` (or the largest available).

    Rows in Table 1 order first, then any other tasks present; missing variants are omitted.
    """
    out: dict[str, Any] = {}
    order = [t for t in TABLE1_ROWS if t in res.curves] + [t for t in res.curves if t not in TABLE1_ROWS]
    for task in order:
        out[task] = {}
        for v in [v for v in VARIANTS if v in res.curves[task]] + [v for v in res.curves[task] if v not in VARIANTS]:
            mu, sd = res.curves[task][v].at(n_pcs)
            out[task][v] = (100 * mu, 100 * sd)
    return out


def _pcs_used(res: TaskResults, n_pcs):
    return min([n_pcs] + [c.acc.shape[1] for by_v in res.curves.values() for c in by_v.values()])


def format_table1(res: TaskResults, n_pcs=50, *, compare_paper=False, stars=True) -> str:
    """Plain-text Table 1 layout for ``res``.

    Parameters
    ----------
    res : TaskResults
    n_pcs : int
        PC count of the table (clipped to the largest available; the title says which was used).
    compare_paper : bool
        Add a line with the paper's values under each row.
    stars : bool
        Mark scaled variants that differ from Original (Welch + Cohen's d: ``*``/``**``).

    Returns
    -------
    str
    """
    used = _pcs_used(res, n_pcs)
    tab = table1(res, used)
    variants = [v for v in VARIANTS if any(v in row for row in tab.values())]
    variants += sorted({v for row in tab.values() for v in row} - set(variants))
    w0 = max([len(task_title(t)) for t in tab] + [len("Paper")]) + 2
    wid = {v: max(19, len(VARIANT_TITLES.get(v, v)) + 2) for v in variants}
    head1 = " " * w0 + "".join(f"{VARIANT_TITLES.get(v, v):^{wid[v]}}" for v in variants)
    head2 = " " * w0 + "".join(f"{'mu (%)':>{wid[v] - 10}}{'sd (%)':>7}   " for v in variants)
    lines = [f"Classification accuracy with {used} PCs (%)" + (f" [asked for {n_pcs}]" if used != n_pcs else ""),
             head1, head2]
    for task, row in tab.items():
        marks = {}
        if stars:
            for c in res.comparisons(task, used):
                marks[c.variant] = mark(c.stars_d, c.mean_b - c.mean_a)
        cells = ""
        for v in variants:
            if v in row:
                mu, sd = row[v]
                cells += f"{_num(mu, wid[v] - 10)}{_num(sd, 7)}{marks.get(v, ''):<3}"
            else:
                cells += f"{'-':>{wid[v] - 10}}{'-':>7}   "
        lines.append(f"{task_title(task):<{w0}}{cells}")
        if compare_paper and task in PAPER_TABLE1:
            ref = PAPER_TABLE1[task]
            cells = "".join(f"{ref[v][0]:{wid[v] - 10}.2f}{ref[v][1]:7.2f}   " if v in ref else " " * wid[v]
                            for v in variants)
            lines.append(f"{'  paper (50 PCs)':<{w0}}{cells}")
    lines += format_counts(res.counts)
    for w in res.warnings:
        lines.append("warning: " + (f"baseline removed, {w[len(BASELINE_PREFIX):]}" if w.startswith(BASELINE_PREFIX)
                                    else w))
    reps = sorted({c.acc.shape[0] for by_v in res.curves.values() for c in by_v.values()})
    lines.append(f"mu, sd: mean and sample SD over {'/'.join(map(str, reps))} repetitions")
    if stars:
        lines.append("vs Original (Welch's t-test, Cohen's d): * p<0.05 and |d|>0.5, ** p<0.01 and |d|>1; "
                     "^ this variant higher, v lower")
    return "\n".join(lines)


def mark(stars: str, diff: float) -> str:
    """A significance mark that says which way: ``"**^"`` (the variant higher than Original), ``"*v"`` (lower),
    ``""`` (no mark); ``diff`` = variant - Original."""
    return f"{stars}{'^' if diff > 0 else 'v'}" if stars else ""


def _num(x: float, width: int) -> str:
    """``x`` to 2 decimals in ``width`` columns; a non-finite value (no test trials) as ``-``, never ``nan``."""
    return f"{x:{width}.2f}" if np.isfinite(x) else f"{'-':>{width}}"


def _value(v: object) -> str:
    if isinstance(v, float):
        return f"{v:g}" if np.isfinite(v) else "n/a"
    if isinstance(v, (list, tuple)):
        return ",".join(_value(x) for x in v) or "none"
    if isinstance(v, dict):
        return "; ".join(f"{k} {_value(x)}" for k, x in v.items())
    return "none" if v is None else str(v)


def format_counts(counts: dict[str, Any]) -> list[str]:
    """The trial counts of each analysis as text lines (``counts, cv: per_texture 75, ...``): no JSON, no NaN (a
    non-finite number reads ``n/a``, a missing one ``none``)."""
    return [f"counts, {task_title(k)}: " + ", ".join(f"{k2} {_value(v)}" for k2, v in c.items())
            if isinstance(c, dict) else f"counts, {task_title(k)}: {_value(c)}" for k, c in counts.items()]


#: paper values closer than this (percentage points) set no ordering to check
ORDERING_MARGIN_PCT = 3.0
#: our values closer than this (percentage points, half the table's last digit) are a tie, not an ordering
TIE_PCT = 0.005


@dataclass(frozen=True)
class OrderingPair:
    """One pair of variants in a Table 1 row whose paper values differ by more than the margin.

    ``paper_diff`` and ``our_diff`` are ``mu(first) - mu(second)`` in percentage points (paper at 50 PCs, ours at the
    table's PC count); ``holds`` is whether they have the same sign. ``identical``: the two variants scored the same
    on every repetition and PC count (e.g. Force Scaled with every force coefficient C = 1 is Original); a pair that
    is identical or tied (``|our_diff|`` under :data:`TIE_PCT`) is neither held nor reversed."""

    first: str
    second: str
    paper_diff: float
    our_diff: float
    identical: bool = False

    @property
    def tied(self) -> bool:
        return self.identical or abs(self.our_diff) < TIE_PCT

    @property
    def holds(self) -> bool:
        return self.paper_diff * self.our_diff > 0 and not self.tied

    @property
    def reversed(self) -> bool:
        return not self.holds and not self.tied

    def describe(self) -> str:
        """``"Force Scaled > Original (paper +10.4, here -3.1)"``, in the paper's direction."""
        hi, lo = (self.first, self.second) if self.paper_diff > 0 else (self.second, self.first)
        sign = 1 if self.paper_diff > 0 else -1
        return (f"{VARIANT_TITLES.get(hi, hi)} > {VARIANT_TITLES.get(lo, lo)} "
                f"(paper {sign * self.paper_diff:+.1f}, here {sign * self.our_diff:+.1f})")


def paper_ordering(res: TaskResults, n_pcs=50, *, margin=ORDERING_MARGIN_PCT) -> dict[str, list[OrderingPair]]:
    """Whether each Table 1 row orders the variants as the paper's does.

    Every pair of variants present in a row whose paper values (:data:`PAPER_TABLE1`) differ by more than ``margin``
    percentage points must differ the same way here. Rows with a prefix (e.g. ``baseline_removed:``) are not the
    paper's and are skipped.

    Returns
    -------
    dict
        task -> the pairs checked (:class:`OrderingPair`; ``all(p.holds for p in pairs)`` is the row's verdict);
        rows with no pair to check are left out.
    """
    tab = table1(res, _pcs_used(res, n_pcs))
    out: dict[str, list[OrderingPair]] = {}
    for task, row in tab.items():
        ref = PAPER_TABLE1.get(task)
        if ref is None:
            continue
        present = [v for v in VARIANTS if v in row and v in ref]
        curves = res.curves[task]
        pairs = [OrderingPair(a, b, ref[a][0] - ref[b][0], row[a][0] - row[b][0],
                              np.array_equal(curves[a].acc, curves[b].acc))
                 for i, a in enumerate(present) for b in present[i + 1:] if abs(ref[a][0] - ref[b][0]) > margin]
        if pairs:
            out[task] = pairs
    return out


#: the paper's size (Methods, statistical analysis): trials drawn per texture in the CV rows, training trials per
#: texture and trained cell in the extrapolation rows, repetitions
PAPER_SIZE = {"per_texture": 500, "train_per_cell": 75, "repeats": 20}
#: below this fraction of the paper's size (any of the three), a table's ordering is not expected to reproduce
SMALL_FRACTION = 0.2


def size_note(res: TaskResults) -> str | None:
    """One line when the results come from far fewer trials or repetitions than the paper's (:data:`PAPER_SIZE`,
    under :data:`SMALL_FRACTION` of any of them): what such a table can and cannot show. None at a size near the
    paper's, or when the results say nothing of their size."""
    cv = res.counts.get("cv") or {}
    ex = res.counts.get("extrapolation") or {}
    here = {"per_texture": cv.get("per_texture"), "train_per_cell": ex.get("train_per_cell"),
            "repeats": cv.get("repeats", ex.get("repeats"))}
    small = [k for k, v in here.items() if v is not None and v < SMALL_FRACTION * PAPER_SIZE[k]]
    if not small:
        return None
    words = {"per_texture": "trials per texture in the cross-validated rows",
             "train_per_cell": "training trials per texture and trained cell in the extrapolation rows",
             "repeats": "repetitions"}
    drawn = list((cv.get("drawn_per_texture") or {}).values())
    shown = {**here, "per_texture": f"{min(drawn)}-{max(drawn)} (each texture weighted equally)"
             if drawn and min(drawn) < max(drawn) else here["per_texture"]}
    have = ", ".join(f"{shown[k]} {words[k]} (paper: {PAPER_SIZE[k]})" for k in PAPER_SIZE if here[k] is not None)
    return (f"size: {have}. At this size the accuracies are noisy and the PCA/LDA is fitted on few trials, so the "
            "paper's values and ordering are not expected to reproduce: a first try of every step, not a test of the "
            "paper's claims (those need its size: docs/guides/reproducing-the-paper.md)")


def format_ordering(res: TaskResults, n_pcs=50) -> str:
    """One line per Table 1 row: whether the paper's ordering of the variants holds, and the pairs that break it;
    first, for results far below the paper's size, what they cannot show (:func:`size_note`)."""
    lines = []
    for task, pairs in paper_ordering(res, n_pcs).items():
        broken = [p for p in pairs if p.reversed]
        ties = [p for p in pairs if p.tied]
        checked = len(pairs) - len(ties)
        verdict = ("" if not checked else f"holds ({checked} pairs)" if not broken else
                   f"NOT held: {len(broken)} of {checked} pairs reversed: " + "; ".join(p.describe() for p in broken))
        if ties:
            same = "; ".join(f"{VARIANT_TITLES.get(p.first, p.first)} and {VARIANT_TITLES.get(p.second, p.second)} "
                             f"{'identical' if p.identical else 'tied'}" for p in ties)
            verdict = f"{verdict}{'; ' if verdict else ''}not compared: {same}"
        lines.append(f"paper's ordering, {task_title(task)}: {verdict}")
    note = size_note(res) if lines else None
    return "\n".join(([note] if note else []) + lines)


#: the extrapolation rows, whose test conditions the classifier never saw
EXTRAPOLATION_ROWS = ("untrained_speed_force", "untrained_force", "untrained_speed")


@dataclass(frozen=True)
class Collapse:
    """How far a classifier piles its predictions on one class (from a confusion matrix).

    ``top_class`` is the most-predicted class, ``top_share`` its share of all predictions (0-1) and ``even_share``
    1 / n_classes, the share of every class when the test set is balanced and the predictions follow it."""

    top_class: str
    top_share: float
    even_share: float

    @property
    def ratio(self) -> float:
        """``top_share / even_share``: 1 = no class favoured; 16 = every trial on one of 16 classes."""
        return self.top_share / self.even_share if self.even_share else float("nan")


def prediction_collapse(res: TaskResults, tasks=EXTRAPOLATION_ROWS) -> dict[str, dict[str, Collapse]]:
    """Per task and variant, the class the classifier predicts most and its share (the confusion matrix at its PC
    count, summed over repetitions).

    A classifier that meets test data off its training manifold (e.g. the unscaled windows of an untrained speed,
    whose modulation lands in other windows) tends to put most trials on one or two classes, typically the least
    modulated plate; a high share names that failure, which the accuracy alone does not (issue 13).

    Returns
    -------
    dict
        task -> variant -> :class:`Collapse`; tasks not in ``res`` are left out.
    """
    out: dict[str, dict[str, Collapse]] = {}
    for task in tasks:
        by_v = res.curves.get(task)
        if not by_v:
            continue
        out[task] = {}
        for v, c in by_v.items():
            predicted = np.asarray(c.confusion).sum(axis=0)
            total = predicted.sum()
            if total == 0:
                continue
            k = int(np.argmax(predicted))
            out[task][v] = Collapse(str(c.classes[k]), float(predicted[k] / total), 1.0 / len(c.classes))
    return out


def format_collapse(res: TaskResults) -> str:
    """One line per extrapolation row: each variant's most-predicted class and its share of the test trials."""
    lines = []
    for task, by_v in prediction_collapse(res).items():
        if not by_v:
            continue
        even = next(iter(by_v.values())).even_share
        cells = "; ".join(f"{VARIANT_TITLES.get(v, v)} {100 * c.top_share:.0f} % ({c.top_class})"
                          for v, c in by_v.items())
        lines.append(f"most-predicted class, {task_title(task)} (even: {100 * even:.0f} %): {cells}")
    return "\n".join(lines)


def to_dict(res: TaskResults, n_pcs=50, *, source=None):
    """JSON-able dict: settings, counts, warnings, per task and variant the mean/sd curves (fractions), the table at
    ``n_pcs`` (percent), the comparisons vs Original at ``n_pcs`` and the confusion matrices."""
    used = _pcs_used(res, n_pcs)
    out = {"source": source, "table_pcs": used, "settings": res.settings, "counts": res.counts,
           "warnings": res.warnings, "tasks": {}, "ordering": {
               t: {"holds": not any(p.reversed for p in pairs),
                   "pairs": [{"first": p.first, "second": p.second, "paper_diff_pct": p.paper_diff,
                              "our_diff_pct": p.our_diff, "holds": p.holds, "tied": p.tied,
                              "identical": p.identical} for p in pairs]}
               for t, pairs in paper_ordering(res, used).items()},
           "collapse": {t: {v: {"top_class": c.top_class, "top_share": c.top_share, "even_share": c.even_share}
                            for v, c in by_v.items()} for t, by_v in prediction_collapse(res).items()}}
    for task, by_v in res.curves.items():
        out["tasks"][task] = {
            "title": task_title(task),
            "variants": {
                v: {"mean": c.mean.round(6).tolist(), "sd": c.sd.round(6).tolist(), "n_repeats": int(c.acc.shape[0]),
                    "n_tested": c.n_tested, "table": dict(zip(("mu_pct", "sd_pct"), (100 * x for x in c.at(used)))),
                    "classes": [str(k) for k in c.classes], "confusion_pcs": c.confusion_pcs,
                    "confusion": c.confusion.tolist()}
                for v, c in by_v.items()
            },
            "comparisons": [c.to_dict() for c in res.comparisons(task, used)],
        }
    return out


def to_json(res: TaskResults, n_pcs=50, *, source=None) -> str:
    """:func:`to_dict` as a JSON string."""
    return json.dumps(to_dict(res, n_pcs, source=source), indent=1)


def to_csv(res: TaskResults) -> str:
    """Long-format CSV: task, variant, n_pcs, mean, sd, n_repeats, n_tested (accuracies as fractions)."""
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(CURVES_CSV_HEADER)
    for task, by_v in res.curves.items():
        for v, c in by_v.items():
            for n, m, s in zip(c.pcs, c.mean, c.sd):
                w.writerow([task, v, int(n), f"{m:.6f}", f"{s:.6f}", c.acc.shape[0], c.n_tested])
    return buf.getvalue()


_COLOURS = {"original": "black", "force_scaled": "tab:red", "speed_scaled": "tab:blue", "realtime_original": "black",
            "realtime_speed_scaled": "tab:blue", "force_scaled_label_free": "tab:orange",
            "speed_force_scaled_label_free": "tab:olive",
            "speed_force_scaled": "tab:green"}


def chance_pct(res: TaskResults, task: str) -> float:
    """Chance level of ``task`` in percent: 100 / the number of classes (textures or groups) it tells apart."""
    return 100.0 / max(len(next(iter(res.curves[task].values())).classes), 1)


def plottable(res: TaskResults, tasks=None) -> list[str]:
    """The tasks of ``res`` with an accuracy-vs-PCs curve to draw (at least 2 PC counts with a finite mean)."""
    tasks = tasks or ([t for t in TABLE1_ROWS if t in res.curves] + [t for t in res.curves if t not in TABLE1_ROWS])
    return [t for t in tasks if any(np.isfinite(c.mean).sum() >= 2 for c in res.curves.get(t, {}).values())]


def n_text(res: TaskResults, task: str) -> str:
    """``"n = 120 test trials x 20 repetitions, 16 classes"``: what one panel's accuracies rest on."""
    by_v = res.curves[task].values()
    tested = sorted({c.n_tested for c in by_v})
    reps = sorted({c.acc.shape[0] for c in by_v})
    return (f"n = {'/'.join(map(str, tested))} test trials x {'/'.join(map(str, reps))} repetitions, "
            f"{len(next(iter(by_v)).classes)} classes")


def plot_curves(res: TaskResults, path, *, tasks=None, title=None, compare_paper=False):
    """Fig. 3-like figure: accuracy (%) vs number of PCs, mean +- 1 SD over repetitions (:data:`ERROR_BARS`, said in
    the figure), one panel per task with its chance level (1 / classes) and n (test trials x repetitions), to PNG.

    Parameters
    ----------
    res : TaskResults
    path : str or Path
        Output image (format from the suffix, e.g. ``.png``).
    tasks : sequence of str, optional
        Panels (default: every task with a curve, Table 1 order first).
    compare_paper : bool
        Also draw the paper's Table 1 values (:data:`PAPER_TABLE1`, mean +- SD at 50 PCs) as hollow diamonds.

    Raises
    ------
    ValueError
        If no task has a curve to draw (fewer than 2 PC counts): nothing is written.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    tasks = plottable(res, tasks)
    if not tasks:
        raise ValueError("no accuracy curve to draw (one PC count or none); pass --pcs 1-N")
    n = len(tasks)
    cols = min(n, 2 if n <= 4 else 3)
    rows = int(np.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(5.2 * cols, 3.8 * rows + 0.4), squeeze=False)
    for ax, task in zip(axes.ravel(), tasks):
        for v, c in res.curves[task].items():
            ax.errorbar(c.pcs, 100 * c.mean, yerr=100 * c.sd, label=VARIANT_TITLES.get(v, v),
                        color=_COLOURS.get(v), capsize=2, lw=1.2, elinewidth=0.8)
            ref = PAPER_TABLE1.get(task, {}).get(v) if compare_paper else None
            if ref is not None:
                ax.errorbar([50], [ref[0]], yerr=[ref[1]], fmt="D", mfc="white", ms=6, color=_COLOURS.get(v),
                            label="paper (Table 1, 50 PCs)" if v == "original" else None, zorder=5)
        chance = chance_pct(res, task)
        ax.axhline(chance, color="grey", ls=":", lw=1.0, label="chance")
        ax.annotate(f"chance {chance:.1f} %", (1.0, chance), xycoords=("axes fraction", "data"), xytext=(-2, 2),
                    textcoords="offset points", ha="right", va="bottom", fontsize=7, color="dimgrey")
        ax.set_title(f"{task_title(task)}\n{n_text(res, task)}", fontsize=9)
        ax.set_xlabel("number of PCs")
        ax.set_ylabel("accuracy (%)")
        ax.set_ylim(0, 100)
        ax.grid(alpha=0.3)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    handles, labels = axes.ravel()[0].get_legend_handles_labels()
    keep = [(h, lab) for h, lab in zip(handles, labels) if lab != "chance"]
    axes.ravel()[0].legend(*zip(*keep), fontsize=7, loc="lower right")
    fig.suptitle((f"{title}: " if title else "") + f"mean, {ERROR_BARS}; dotted: chance (1 / classes)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110, metadata=figure_metadata(path))
    plt.close(fig)
    return path


def plot_confusions(res: TaskResults, path, task, *, normalise=True):
    """Confusion matrices of one task, one panel per variant (like Figs. S1-S4), to PNG.

    Raises
    ------
    KeyError
        If ``task`` is not in ``res``.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    by_v = res.curves[task]
    # whole labels (never cut): the panel grows with the longest label and the class count
    longest = max((len(str(k)) for c in by_v.values() for k in c.classes), default=1)
    n_cls = max((len(c.classes) for c in by_v.values()), default=1)
    side = max(4.0, 1.6 + 0.16 * n_cls + 0.06 * longest)
    fig, axes = plt.subplots(1, len(by_v), figsize=(side * len(by_v), side), squeeze=False)
    for ax, (v, c) in zip(axes[0], by_v.items()):
        cm = c.confusion.astype(float)
        if normalise:
            cm = 100 * cm / np.maximum(cm.sum(axis=1, keepdims=True), 1)
        ax.imshow(cm, cmap="Blues", vmin=0, vmax=100 if normalise else None)
        ax.set_xticks(range(len(c.classes)), [str(k) for k in c.classes], fontsize=7, rotation=90)
        ax.set_yticks(range(len(c.classes)), [str(k) for k in c.classes], fontsize=7)
        acc = np.trace(c.confusion) / max(c.confusion.sum(), 1)
        ax.set_title(f"{VARIANT_TITLES.get(v, v)}\n{100 * acc:.1f}% at {c.confusion_pcs} PCs", fontsize=9)
        ax.set_xlabel("predicted")
        ax.set_ylabel("true")
    fig.suptitle(task_title(task), fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110, metadata=figure_metadata(path))
    plt.close(fig)
    return path
