"""The paper's real-time classifier (Methods, "Real-time Texture Classification - Protocol"): LDA on the first 25 PCs
of the mean-centred training features, the mean vector re-calibrated on a calibration block recorded just before
the real-time block ("the mean vector is calculated from a new set of 10 trials for each texture ... used to
mean-center the real-time feature data before calculating the first 25 PCs").

Alignment (issue 78 item 2; :mod:`rigctl.encoding.alignment`): a new session's plate axis may read the finger a few
mm off (calibration touches, a re-strapped tracker), which moves every scan's windows along the plate. ``alignment``:

- ``"none"``: the paper's classifier, on the windows themselves;
- ``"session"``: :meth:`RealtimeClassifier.calibrate` with the calibration block's textures finds its shift against
  the training block's per-texture means (:func:`rigctl.encoding.alignment.session_shift`) and every scan is
  shifted back by it before the PCs;
- ``"statistics"``: each train's mean, spread and mean change over its windows
  (:func:`rigctl.encoding.alignment.window_statistics`: a place-free feature), 3 x n_trains features.

With every alignment, a calibration block with its textures is measured against the training block
(:attr:`RealtimeClassifier.shift_mm`) and :attr:`RealtimeClassifier.alignment_note` names a session outside
:data:`rigctl.encoding.alignment.ALIGNMENT_TOLERANCE_MM`. Compared on a new session (docs/results.md 3b; an
augmentation with shifted copies and the windows' Fourier magnitudes were tried too and did not survive 2 mm).
"""

from __future__ import annotations

import numpy as np

from rigctl.analysis.classify import NestedLDA, fit_pca
from rigctl.encoding.alignment import (
    ALIGNMENT_TOLERANCE_MM,
    WINDOW_MM,
    session_shift,
    shift_windows,
    window_statistics,
)
from rigctl.encoding.features import N_WINDOWS_REALTIME

__all__ = ["ALIGNMENTS", "RealtimeClassifier"]

#: the classifier's alignments (module docstring)
ALIGNMENTS = ("none", "session", "statistics")


class RealtimeClassifier:
    """PCA + LDA trained on a training block's features; :meth:`calibrate` moves the centre to a calibration
    block's mean; :meth:`predict` classifies scans.

    Parameters
    ----------
    features : (n_trials, n_features) the training block's features (e.g. ``realtime_speed_scaled``: 180 per scan).
    labels : (n_trials,) texture labels.
    n_pcs : principal components (the paper: 25; clipped to ``n_trials - 1`` and ``n_features``).
    alignment : one of :data:`ALIGNMENTS` (module docstring; ``"none"``: the paper's).
    n_windows : windows per train (the real-time features: 20).

    Raises
    ------
    ValueError
        Fewer than two trials or classes, features and labels of different lengths, an unknown alignment, or
        features that are not whole trains of ``n_windows``.
    """

    def __init__(self, features: np.ndarray, labels: np.ndarray, *, n_pcs: int = 25, alignment: str = "none",
                 n_windows: int = N_WINDOWS_REALTIME) -> None:
        x = np.asarray(features, np.float64)
        y = np.asarray(labels).astype(str)
        if x.ndim != 2 or x.shape[0] != y.size or x.shape[0] < 2 or np.unique(y).size < 2:
            raise ValueError(f"need (n, f) features of >= 2 trials of >= 2 textures with one label each, got "
                             f"{x.shape} and {y.size} labels")
        if alignment not in ALIGNMENTS:
            raise ValueError(f"unknown alignment {alignment!r}: one of {', '.join(ALIGNMENTS)}")
        if alignment != "none" and x.shape[1] % n_windows:
            raise ValueError(f"{x.shape[1]} features are not trains of {n_windows} windows")
        self.alignment = alignment
        self.n_trains = max(1, x.shape[1] // n_windows)
        #: the training block's mean per texture, in its own alignment
        self.templates = {c: x[y == c].mean(axis=0) for c in np.unique(y)}
        #: the session's shift against the training block (mm of plate; 0 until a calibration block is seen)
        self.shift_mm = 0.0
        #: why the session's scans sit outside the training's alignment ("" when they do not)
        self.alignment_note = ""
        self._shift = 0.0
        self.pca = fit_pca(self._transform(x), n_pcs)
        self.n_pcs = int(self.pca.n_components_)
        self.centre = np.asarray(self.pca.mean_, np.float64)  # the training mean until calibrated
        self.lda = NestedLDA().fit(self._project(self._transform(x)), y)
        self.classes = self.lda.classes_

    def _transform(self, x: np.ndarray) -> np.ndarray:
        """The features the PCs see: shifted by the session's shift, or their window spectra."""
        if self.alignment == "statistics":
            return window_statistics(x, self.n_trains)
        if self.alignment == "session" and self._shift:
            return shift_windows(x, self.n_trains, self._shift)
        return np.asarray(x, np.float64)

    def _project(self, x: np.ndarray) -> np.ndarray:
        comps = np.asarray(self.pca.components_, np.float64)
        return (np.asarray(x, np.float64) - self.centre) @ comps.T

    def measure_shift(self, features: np.ndarray, labels: np.ndarray) -> float:
        """A labelled block's shift against the training block, mm of plate (positive: its scans start earlier on
        the plate; :func:`rigctl.encoding.alignment.session_shift`). Raises ValueError for features of another
        shape or no trained texture."""
        return session_shift(self.templates, features, labels, self.n_trains) * WINDOW_MM

    def calibrate(self, features: np.ndarray, labels: np.ndarray | None = None) -> None:
        """Re-centre on a calibration block: its mean feature vector ((m, n_features), m >= 1). With its textures
        ``labels`` ((m,)): measure its shift against the training block (:attr:`shift_mm`,
        :attr:`alignment_note`) and, with ``alignment="session"``, shift every scan back by it. Raises ValueError
        (shapes; ``alignment="session"`` without labels)."""
        x = np.asarray(features, np.float64)
        size = next(iter(self.templates.values())).size
        if x.ndim != 2 or x.shape[1] != size or x.shape[0] == 0:
            raise ValueError(f"calibration features must be (m, {size}), got {x.shape}")
        if labels is None and self.alignment == "session":
            raise ValueError("the session alignment needs the calibration block's textures")
        self.shift_mm = 0.0 if labels is None else self.measure_shift(x, np.asarray(labels))
        self._shift = self.shift_mm / WINDOW_MM if self.alignment == "session" else 0.0
        self.alignment_note = ""
        if abs(self.shift_mm) > ALIGNMENT_TOLERANCE_MM:
            done = ("the scans are shifted back by it" if self.alignment == "session" else
                    "the classifier does not correct it (alignment 'session' does)")
            self.alignment_note = (f"the calibration block sits {self.shift_mm:+.1f} mm along the plate from the "
                                   f"training block (tolerance {ALIGNMENT_TOLERANCE_MM:g} mm: the plate axis or the "
                                   f"tracker moved between the sessions): {done}")
        self.centre = self._transform(x).mean(axis=0)

    def predict(self, features: np.ndarray) -> np.ndarray:
        """(m,) texture labels of (m, n_features) or (n_features,) features."""
        x = np.atleast_2d(np.asarray(features, np.float64))
        return np.asarray(self.lda.predict_all(self._project(self._transform(x)), self.n_pcs)[-1])
