"""Real-time classification view (paper Fig. 4A): with a model file (``rigctl analyze --save-model``, or trained in
the analysis tab: a scikit-learn pipeline from raw trials to the texture label, :mod:`rigctl.analysis.model`), every
trial the protocol runner finishes is classified by the model's ``predict`` (it normalises, encodes and classifies
as it was trained); each trial becomes a tile with the predicted texture, green when it matches the ground truth and
red when not."""

from __future__ import annotations

import collections
import dataclasses
import math

from PySide6 import QtCore, QtWidgets

from rigctl_gui.colours import ERROR, on_window
from rigctl_gui.workers import Job

MAX_TILES = 60


def trial_record(data, planned):
    """A finished trial as the model's input: the recorded :class:`rigctl.core.trial.TrialData` with the planned
    speed and force setpoints in its attributes, and without its texture (the answer the model is asked for)."""
    attrs = {k: v for k, v in data.attrs.items() if k != "texture"}
    attrs.update(speed_mm_s=float(planned.speed_mm_s), force_g=float(getattr(planned, "force_g", math.nan)))
    return dataclasses.replace(data, attrs=attrs)


def classify_trial(model, data, planned) -> str:
    """Predicted texture of one finished trial: ``model`` (a loaded model file, raw trials -> label:
    :func:`rigctl.storage.model_file.load_model`) predicts on :func:`trial_record` ``(data, planned)``.

    Raises ValueError when the trial's sensor differs from the one the model was trained on."""
    return str(model.predict([trial_record(data, planned)])[0])


class ClassifyView(QtWidgets.QWidget):
    """The real-time classification tab; ``main`` is the :class:`rigctl_gui.app.MainWindow`."""

    def __init__(self, main, parent=None):
        super().__init__(parent)
        self.main = main
        self.model = None
        self.model_path: str | None = None
        self._pending: collections.deque = collections.deque()
        self._job: Job | None = None
        self.results: list[tuple[int, str, str]] = []  # (trial_id, truth, predicted)

        self.model_label = QtWidgets.QLabel("No model: train one in the Analysis tab (Train model for the real-time "
                                            "view) or load a model file (rigctl analyze --save-model), then run a "
                                            "protocol.")
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
        load = QtWidgets.QPushButton("Load model...")
        load.clicked.connect(self._choose_model)

        lay = QtWidgets.QVBoxLayout(self)
        lay.addWidget(self.model_label)
        top = QtWidgets.QHBoxLayout()
        top.addWidget(self.latest, 1)
        top.addWidget(self.score, 2)
        top.addWidget(clear)
        top.addWidget(load)
        lay.addLayout(top)
        lay.addWidget(QtWidgets.QLabel("Finished trials (newest last): predicted texture; green = correct, red = "
                                       "wrong, the true texture below"))
        lay.addWidget(scroll, 1)

    def load_model(self, path: str) -> None:
        """Use the model file ``path`` for the trials to come. Raises :class:`rigctl.storage.model_file.ModelFileError`
        (not a model file, other library versions) or OSError."""
        from rigctl.storage.model_file import load_model

        model = load_model(path)
        clf = model[-1]
        self.model, self.model_path = model, str(path)
        self.model_label.setText(f"Model: {' -> '.join(model.named_steps)}; PCA + LDA on <b>{clf.variant}</b> "
                                 f"features, {clf.n_pcs_} PCs, textures {', '.join(map(str, clf.classes_))} "
                                 f"(from {path})")

    def _choose_model(self):
        from rigctl_gui.dialogs import choose_path  # non-modal: STOP stays usable

        return choose_path(self, "open", "Model file", "", "Model files (*.skops)", self._model_chosen)

    def _model_chosen(self, path: str) -> None:
        from rigctl_gui.messages import escaped

        try:
            self.load_model(path)
        except (OSError, ValueError) as exc:
            self.model_label.setText(f"<span style='color:{on_window(ERROR, self)}'>cannot load {escaped(path)}: {escaped(exc)}</span>")

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
                self.model_label.setText(f"<span style='color:{on_window(ERROR, self)}'>classification failed: {job.error}</span>")
            else:
                self._add(int(planned.trial_id), str(planned.texture), job.result)
        if self._job is None and self._pending:
            planned, data = self._pending.popleft()
            model = self.model
            job = Job(lambda j: classify_trial(model, data, planned), name="classify")
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
        tile.setAlignment(QtCore.Qt.AlignmentFlag.AlignCenter)
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
