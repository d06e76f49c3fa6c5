"""Real-time classification view (paper Fig. 4A): with a texture classifier trained in the analysis tab
(:class:`rigctl.analysis.classify.TextureClassifier`), every trial the protocol runner finishes is encoded the way
the training file was (:func:`rigctl.encoding.pipeline.encode_batch`) and classified; each trial becomes a tile with
the predicted texture, green when it matches the ground truth and red when not."""

from __future__ import annotations

import collections

import numpy as np
from PySide6 import QtCore, QtWidgets

from rigctl_gui.workers import Job

MAX_TILES = 60


def classify_trial(clf, taxel_min, taxel_max, taxels: np.ndarray, speed_mm_s: float,
                   rate_hz: float | None = None) -> str:
    """Predicted texture of one trial: encode ``taxels`` ``(n_samples, n_channels)`` counts (any channel count: the
    training file's sensor; ``taxel_min``/``taxel_max`` are ``(n_channels,)``) at ``rate_hz`` (None: the training
    file's rate) with the training normalisation, the training file's encoding parameters (``clf.encode_params``:
    windows, taxels, constants, so the feature columns match) and the trial's speed (eq. 2) into ``clf.variant``
    features, then :meth:`TextureClassifier.predict`.

    Raises ValueError when the trial's channel count differs from the training normalisation's."""
    from rigctl.encoding.izhikevich import as_ragged
    from rigctl.encoding.normalise import TaxelRange
    from rigctl.encoding.pipeline import EncodeParams, encode_batch

    taxels = np.asarray(taxels)
    if taxels.ndim != 2 or taxels.shape[1] != np.asarray(taxel_min).size:
        raise ValueError(f"trial readings {taxels.shape} do not match the classifier's {np.asarray(taxel_min).size} "
                         "taxels (trained on another sensor)")
    params = EncodeParams.from_dict(getattr(clf, "encode_params", None))
    layout = getattr(clf, "layout", None)
    if rate_hz is None and layout is not None:
        rate_hz = layout.sample_rate_hz
    offset, scale = TaxelRange(np.asarray(taxel_min, float), np.asarray(taxel_max, float)).offset_scale()
    feats, _ = encode_batch(as_ragged([taxels]), offset=offset, scale=scale, speed_mm_s=[float(speed_mm_s)],
                            variants=[clf.variant], store_spikes=(), params=params, rate_hz=rate_hz)
    return str(clf.predict(feats[clf.variant])[0])


class ClassifyView(QtWidgets.QWidget):
    """The real-time classification tab; ``main`` is the :class:`rigctl_gui.app.MainWindow`."""

    def __init__(self, main, parent=None):
        super().__init__(parent)
        self.main = main
        self.model = None
        self._norm = None
        self._pending: collections.deque = collections.deque()
        self._job: Job | None = None
        self.results: list[tuple[int, str, str]] = []  # (trial_id, truth, predicted)

        self.model_label = QtWidgets.QLabel("No model: train one in the Analysis tab (Train model for the real-time "
                                            "view), then run a protocol.")
        self.model_label.setWordWrap(True)
        self.score = QtWidgets.QLabel("")
        self.score.setObjectName("classify_score")
        self.score.setStyleSheet("font-size: 16px; font-weight: bold;")
        self.latest = QtWidgets.QLabel("")
        self.latest.setObjectName("classify_latest")
        self.latest.setAlignment(QtCore.Qt.AlignCenter)
        self.latest.setMinimumHeight(140)
        self.latest.setStyleSheet("font-size: 64px; font-weight: bold; border: 2px solid #ccc;")
        self.grid = QtWidgets.QGridLayout()
        self.grid.setSpacing(4)
        self.grid.setAlignment(QtCore.Qt.AlignTop | QtCore.Qt.AlignLeft)
        gw = QtWidgets.QWidget()
        gw.setLayout(self.grid)
        scroll = QtWidgets.QScrollArea()
        scroll.setWidgetResizable(True)
        scroll.setWidget(gw)
        clear = QtWidgets.QPushButton("Clear")
        clear.clicked.connect(self.clear)

        lay = QtWidgets.QVBoxLayout(self)
        lay.addWidget(self.model_label)
        top = QtWidgets.QHBoxLayout()
        top.addWidget(self.latest, 1)
        top.addWidget(self.score, 2)
        top.addWidget(clear)
        lay.addLayout(top)
        lay.addWidget(QtWidgets.QLabel("Finished trials (newest last): predicted texture; green = correct, red = "
                                       "wrong, the true texture below"))
        lay.addWidget(scroll, 1)

    def set_model(self, clf, taxel_min, taxel_max, *, source: str | None = None) -> None:
        self.model = clf
        self._norm = (np.asarray(taxel_min, float), np.asarray(taxel_max, float))
        self.model_label.setText(f"Model: PCA + LDA on <b>{clf.variant}</b> features, {clf.n_pcs} PCs, textures "
                                 f"{', '.join(map(str, clf.classes_))}" + (f" (from {source})" if source else ""))

    def clear(self) -> None:
        self.results.clear()
        while self.grid.count():
            w = self.grid.takeAt(0).widget()
            if w is not None:
                w.deleteLater()
        self.latest.setText("")
        self.score.setText("")

    def on_trial(self, planned, data) -> None:
        """A finished trial from the protocol runner (GUI thread); classified in a worker thread."""
        if self.model is not None:
            self._pending.append((planned, data))

    def refresh(self) -> None:
        job = self._job
        if job is not None and job.done:
            self._job = None
            planned = job.planned
            if job.error:
                self.model_label.setText(f"<span style='color:#c00'>classification failed: {job.error}</span>")
            else:
                self._add(int(planned.trial_id), str(planned.texture), job.result)
        if self._job is None and self._pending:
            planned, data = self._pending.popleft()
            clf, (lo, hi) = self.model, self._norm
            rate = getattr(getattr(data, "layout", None), "sample_rate_hz", None)
            job = Job(lambda j: classify_trial(clf, lo, hi, data.taxels, planned.speed_mm_s, rate), name="classify")
            job.planned = planned
            self._job = job
            job.start()

    def _add(self, trial_id: int, truth: str, predicted: str) -> None:
        self.results.append((trial_id, truth, predicted))
        ok = truth == predicted
        colour = "#2a2" if ok else "#d22"
        self.latest.setText(predicted)
        self.latest.setStyleSheet(f"font-size: 64px; font-weight: bold; color: white; background: {colour};")
        tile = QtWidgets.QLabel(f"<b style='font-size:20px'>{predicted}</b><br>true {truth}<br>#{trial_id}")
        tile.setAlignment(QtCore.Qt.AlignCenter)
        tile.setFixedSize(70, 70)
        tile.setStyleSheet(f"background: {colour}; color: white; border-radius: 4px;")
        tile.setProperty("correct", ok)
        n = len(self.results) - 1
        if self.grid.count() >= MAX_TILES:
            w = self.grid.takeAt(0).widget()
            if w is not None:
                w.deleteLater()
            n = MAX_TILES - 1
            # re-flow the remaining tiles
            widgets = [self.grid.itemAt(i).widget() for i in range(self.grid.count())]
            for i, w in enumerate(widgets):
                self.grid.addWidget(w, i // 12, i % 12)
        self.grid.addWidget(tile, n // 12, n % 12)
        correct = sum(t == p for _, t, p in self.results)
        self.score.setText(f"{correct}/{len(self.results)} correct ({100 * correct / len(self.results):.0f} %)")
