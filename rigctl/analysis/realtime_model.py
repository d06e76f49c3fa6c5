"""The paper's real-time classifier (Methods, "Real-time Texture Classification - Protocol"): LDA on the first 25 PCs
of the mean-centred training features, the mean vector re-calibrated on a calibration block recorded just before
the real-time block ("the mean vector is calculated from a new set of 10 trials for each texture ... used to
mean-center the real-time feature data before calculating the first 25 PCs").
"""

from __future__ import annotations

import numpy as np

from rigctl.analysis.classify import NestedLDA, fit_pca

__all__ = ["RealtimeClassifier"]


class RealtimeClassifier:
    """PCA + LDA trained on a training block's features; :meth:`calibrate` moves the centre to a calibration
    block's mean; :meth:`predict` classifies scans.

    Parameters
    ----------
    features : (n_trials, n_features) the training block's features (e.g. ``realtime_speed_scaled``: 180 per scan).
    labels : (n_trials,) texture labels.
    n_pcs : principal components (the paper: 25; clipped to ``n_trials - 1`` and ``n_features``).

    Raises
    ------
    ValueError
        Fewer than two trials or classes, or features and labels of different lengths.
    """

    def __init__(self, features: np.ndarray, labels: np.ndarray, *, n_pcs: int = 25) -> None:
        x = np.asarray(features, np.float64)
        y = np.asarray(labels).astype(str)
        if x.ndim != 2 or x.shape[0] != y.size or x.shape[0] < 2 or np.unique(y).size < 2:
            raise ValueError(f"need (n, f) features of >= 2 trials of >= 2 textures with one label each, got "
                             f"{x.shape} and {y.size} labels")
        self.pca = fit_pca(x, n_pcs)
        self.n_pcs = int(self.pca.n_components_)
        self.centre = np.asarray(self.pca.mean_, np.float64)  # the training mean until calibrated
        self.lda = NestedLDA().fit(self._project(x), y)
        self.classes = self.lda.classes_

    def _project(self, x: np.ndarray) -> np.ndarray:
        comps = np.asarray(self.pca.components_, np.float64)
        return (np.asarray(x, np.float64) - self.centre) @ comps.T

    def calibrate(self, features: np.ndarray) -> None:
        """Re-centre on a calibration block: its mean feature vector ((m, n_features), m >= 1)."""
        x = np.asarray(features, np.float64)
        if x.ndim != 2 or x.shape[1] != self.centre.size or x.shape[0] == 0:
            raise ValueError(f"calibration features must be (m, {self.centre.size}), got {x.shape}")
        self.centre = x.mean(axis=0)

    def predict(self, features: np.ndarray) -> np.ndarray:
        """(m,) texture labels of (m, n_features) or (n_features,) features."""
        x = np.atleast_2d(np.asarray(features, np.float64))
        return np.asarray(self.lda.predict_all(self._project(x), self.n_pcs)[-1])
