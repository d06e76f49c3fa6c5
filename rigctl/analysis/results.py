"""What the analyses (:mod:`rigctl.analysis.tasks`) return: accuracy curves over PC counts and the rows' names.

Kept apart from the tasks (scikit-learn, scipy) on purpose: a face that shows results (the GUI's Analysis tab
receives a pickled :class:`TaskResults` from its job process on the GUI thread) or writes them
(:mod:`rigctl.analysis.report`) imports only numpy here, never the classifiers. ``rigctl.analysis.tasks`` re-exports
every name.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["TASK_TITLES", "BASELINE_PREFIX", "SPEED_PREFIX", "task_title", "Curve", "TaskResults"]

#: task key -> the paper's row title (Table 1 / Fig. 3 panel)
TASK_TITLES = {
    "textures": "Individual Textures (Fig. 3A)",
    "groups": "Texture Groups (Fig. 3B)",
    "textures_blocked": "Individual Textures, time blocks held out",
    "groups_blocked": "Texture Groups, time blocks held out",
    "untrained_speed_force": "Untrained Speed and Force (Fig. 3C)",
    "untrained_force": "Untrained Force (Fig. 3D)",
    "untrained_speed": "Untrained Speed (Fig. 3E)",
    "trained": "Trained Speed and Force (Fig. 3F)",
    "rt_offline": "Real-time offline, k=4 CV (Fig. 4B blue)",
    "rt_new_session": "Real-time new session, calibrated (Fig. 4B green)",
    "rt_trained": "Real-time trained profiles (Fig. 4C blue)",
    "rt_untrained": "Real-time untrained profiles (Fig. 4C green)",
}
#: the prefix ``operations.run_analyses`` gives the rows of baseline-removed data (``--baseline remove|both``)
BASELINE_PREFIX = "baseline_removed:"
#: the prefix of the speed-only extrapolation rows (``--task speed-extrapolation``)
SPEED_PREFIX = "speed_"


def task_title(key: str) -> str:
    """A row's name for a reader (``"baseline_removed:speed_untrained_speed"`` -> ``"Untrained Speed, speed-only
    extrapolation, baseline removed"``); :data:`TASK_TITLES` for the paper's rows, the key itself if unknown."""
    suffix = ""
    if key.startswith(BASELINE_PREFIX):
        key, suffix = key[len(BASELINE_PREFIX):], ", baseline removed"
    if key not in TASK_TITLES and key.startswith(SPEED_PREFIX) and key[len(SPEED_PREFIX):] in TASK_TITLES:
        plain = TASK_TITLES[key[len(SPEED_PREFIX):]].split(" (Fig.")[0]  # not the paper's figure panel
        return f"{plain}, speed-only extrapolation{suffix}"
    return TASK_TITLES.get(key, key) + suffix


@dataclass
class Curve:
    """Accuracy over PC counts for one task and one variant.

    Attributes
    ----------
    task, variant : str
    acc : ndarray (n_repeats, n_pcs) float64
        Fraction correct per repetition; column ``j`` uses PCs ``1..j+1``.
    n_tested : int
        Test trials per repetition.
    classes : list of str
    confusion : ndarray (n_classes, n_classes) int64
        Rows true, columns predicted, summed over repetitions, at :attr:`confusion_pcs` PCs.
    confusion_pcs : int
    """

    task: str
    variant: str
    acc: np.ndarray
    n_tested: int
    classes: list
    confusion: np.ndarray
    confusion_pcs: int

    @property
    def pcs(self):
        return np.arange(1, self.acc.shape[1] + 1)

    @property
    def mean(self):
        return self.acc.mean(axis=0)

    @property
    def sd(self):
        """Sample standard deviation over repetitions (``ddof=1``; 0 for one repetition)."""
        return self.acc.std(axis=0, ddof=1) if self.acc.shape[0] > 1 else np.zeros(self.acc.shape[1])

    def at(self, n_pcs):
        """(mean, sd) of the accuracy with ``n_pcs`` PCs (clipped to the largest available)."""
        j = min(int(n_pcs), self.acc.shape[1]) - 1
        return float(self.mean[j]), float(self.sd[j])


@dataclass
class TaskResults:
    """Results of one or more tasks: ``curves[task][variant] -> Curve``, plus the counts actually used."""

    curves: dict = field(default_factory=dict)
    counts: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)
    settings: dict = field(default_factory=dict)

    def add(self, curve: Curve):
        self.curves.setdefault(curve.task, {})[curve.variant] = curve

    def merge(self, other: "TaskResults"):
        for by_v in other.curves.values():
            for c in by_v.values():
                self.add(c)
        self.counts.update(other.counts)
        self.warnings.extend(other.warnings)
        self.settings.update(other.settings)
        return self

    @property
    def tasks(self):
        return list(self.curves)

    def comparisons(self, task, n_pcs=None, baseline="original"):
        """Original vs each other variant for ``task``: list of :class:`~rigctl.analysis.stats.Comparison`.

        Parameters
        ----------
        n_pcs : int or None
            One PC count, or None for every PC count.
        """
        from rigctl.analysis.stats import Comparison  # scipy.stats (~0.5 s of imports): only when comparing

        by_v = self.curves[task]
        if baseline not in by_v:  # real-time variants: compare against realtime_original
            baseline = "realtime_" + baseline
        if baseline not in by_v:
            return []
        base = by_v[baseline]
        out = []
        for v, c in by_v.items():
            if v == baseline:
                continue
            n_max = min(base.acc.shape[1], c.acc.shape[1])
            pcs = range(1, n_max + 1) if n_pcs is None else [min(int(n_pcs), n_max)]
            for n in pcs:
                if base.acc.shape[0] < 2:
                    continue
                out.append(Comparison.of(v, n, base.acc[:, n - 1], c.acc[:, n - 1], base.n_tested, c.n_tested))
        return out
