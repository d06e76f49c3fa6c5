"""Real-time classification view (paper Fig. 4A): with a model file (``rigctl analyze --save-model``, or trained in
the analysis tab: a scikit-learn pipeline from raw trials to the texture label, :mod:`rigctl.analysis.model`), every
trial the protocol runner finishes is classified by the model's ``predict`` (it normalises, encodes and classifies
as it was trained); each trial becomes a tile with the predicted texture, green when it matches the ground truth and
red when not."""

from __future__ import annotations

import collections
import dataclasses
import math
from collections.abc import Callable
from typing import Any

from PySide6 import QtCore, QtWidgets

from rigctl_gui.colours import ERROR, on_window
from rigctl_gui.messages import escaped
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


class PredictionBoard(QtWidgets.QWidget):
    """The predictions of finished trials or scans: the latest as a big letter on green (right) or red (wrong), the
    score, and a tile per prediction in :attr:`tiles` (newest last, the truth below, at most :data:`MAX_TILES`)."""

    def __init__(self, parent=None, *, letter_px: int = 64, per_row: int = 12):
        super().__init__(parent)
        self.results: list[tuple[int, str, str]] = []  # (trial_id, truth, predicted)
        self._letter_px, self.per_row = letter_px, per_row
        self.score = QtWidgets.QLabel("")
        self.score.setObjectName("classify_score")
        self.score.setStyleSheet("font-size: 16px; font-weight: bold;")
        self.latest = QtWidgets.QLabel("")
        self.latest.setObjectName("classify_latest")
        self.latest.setAlignment(QtCore.Qt.AlignmentFlag.AlignCenter)
        self.latest.setMinimumHeight(int(letter_px * 2.2))
        self.latest.setStyleSheet(f"font-size: {letter_px}px; font-weight: bold; border: 2px solid #ccc;")
        self.detail = QtWidgets.QLabel("")  # the latest in words (a layout may show it)
        self.detail.setObjectName("classify_detail")
        self.detail.setWordWrap(True)
        self.grid = QtWidgets.QGridLayout()
        self.grid.setSpacing(4)
        self.grid.setAlignment(QtCore.Qt.AlignmentFlag.AlignTop | QtCore.Qt.AlignmentFlag.AlignLeft)
        gw = QtWidgets.QWidget()
        gw.setLayout(self.grid)
        self.tiles = QtWidgets.QScrollArea()
        self.tiles.setWidgetResizable(True)
        self.tiles.setWidget(gw)

    def clear(self) -> None:
        self.results.clear()
        while self.grid.count():
            item = self.grid.takeAt(0)
            w = item.widget() if item is not None else None
            if w is not None:
                w.deleteLater()
        self.latest.setText("")
        self.latest.setStyleSheet(f"font-size: {self._letter_px}px; font-weight: bold; border: 2px solid #ccc;")
        self.score.setText("")
        self.detail.setText("")

    def add(self, trial_id: int, truth: str, predicted: str) -> None:
        """Show one prediction: the big letter (green: right, red: wrong), its tile, the score."""
        self.results.append((trial_id, truth, predicted))
        ok = truth == predicted
        colour = "#2a2" if ok else "#d22"
        self.latest.setText(predicted)
        self.latest.setProperty("correct", ok)
        self.detail.setText(f"#{trial_id}: predicted {predicted}, the plate was {truth}: "
                            f"{'right' if ok else 'WRONG'}")
        self.latest.setToolTip(self.detail.text())
        self.latest.setStyleSheet(f"font-size: {self._letter_px}px; font-weight: bold; color: white; "
                                  f"background: {colour};")
        tile = QtWidgets.QLabel(f"<b style='font-size:20px'>{predicted}</b><br>true {truth}<br>#{trial_id}")
        tile.setAlignment(QtCore.Qt.AlignmentFlag.AlignCenter)
        tile.setFixedSize(70, 70)
        tile.setStyleSheet(f"background: {colour}; color: white; border-radius: 4px;")
        tile.setProperty("correct", ok)
        n = len(self.results) - 1
        if self.grid.count() >= MAX_TILES:
            item = self.grid.takeAt(0)
            old = item.widget() if item is not None else None
            if old is not None:
                old.deleteLater()
            n = MAX_TILES - 1
            # re-flow the remaining tiles
            items = [self.grid.itemAt(i) for i in range(self.grid.count())]
            widgets = [it.widget() for it in items if it is not None]
            for i, kept in enumerate(w for w in widgets if w is not None):
                self.grid.addWidget(kept, i // self.per_row, i % self.per_row)
        self.grid.addWidget(tile, n // self.per_row, n % self.per_row)
        correct = sum(t == p for _, t, p in self.results)
        self.score.setText(f"{correct}/{len(self.results)} correct ({100 * correct / len(self.results):.0f} %)")


class ClassifyView(QtWidgets.QWidget):
    """The real-time classification tab; ``main`` is the :class:`rigctl_gui.app.MainWindow`."""

    def __init__(self, main, parent=None):
        super().__init__(parent)
        self.main = main
        self.model = None
        self.model_path: str | None = None
        self._pending: collections.deque = collections.deque()
        self._job: Job | None = None
        self._loading: tuple[Job, Callable[[Any], None] | None] | None = None  # a model file being loaded
        self.board = PredictionBoard()
        self.results = self.board.results  # (trial_id, truth, predicted)
        self.score, self.latest, self.grid = self.board.score, self.board.latest, self.board.grid

        self.model_label = QtWidgets.QLabel("No model: train one in the Analysis tab (Train model for the real-time "
                                            "view) or load a model file (rigctl analyze --save-model), then run a "
                                            "protocol.")
        self.model_label.setWordWrap(True)
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
        lay.addWidget(self.board.tiles, 1)

    def load_model(self, path: str, on_loaded: Callable[[Any], None] | None = None) -> None:
        """Use the model file ``path`` for the trials to come, loaded in a worker thread (the first load imports
        skops and scikit-learn: ~1.5 s, which on the GUI thread would trip the dead man's switch while the drum
        turns); :meth:`refresh` applies it on the GUI thread and calls ``on_loaded(model)``. A file that cannot be
        loaded (:class:`rigctl.storage.model_file.ModelFileError`: not a model file, other library versions; OSError)
        is named in the tab and the model in use stays."""
        from rigctl.storage.model_file import load_model

        self.model_label.setText(f"Loading the model {escaped(path)} ...")
        job = Job(lambda j: load_model(path), name="load-model")
        job.path = str(path)
        self._loading = (job, on_loaded)
        job.start()

    def _apply_loaded(self) -> None:
        """The model load :meth:`load_model` started, once it is done (GUI thread)."""
        if self._loading is None or not self._loading[0].done:
            return
        job, on_loaded = self._loading
        self._loading = None
        if job.error:
            self.model_label.setText(f"<span style='color:{on_window(ERROR, self)}'>cannot load {escaped(job.path)}: "
                                     f"{escaped(job.error)}</span>")
            return
        model = job.result
        clf = model[-1]
        self.model, self.model_path = model, job.path
        self.model_label.setText(f"Model: {' -> '.join(model.named_steps)}; PCA + LDA on <b>{clf.variant}</b> "
                                 f"features, {clf.n_pcs_} PCs, textures {', '.join(map(str, clf.classes_))} "
                                 f"(from {job.path})")
        if on_loaded is not None:
            on_loaded(model)

    def _choose_model(self):
        from rigctl_gui.dialogs import choose_path  # non-modal: STOP stays usable

        return choose_path(self, "open", "Model file", "", "Model files (*.skops)", self.load_model)

    def clear(self) -> None:
        self.board.clear()

    def on_trial(self, planned, data) -> None:
        """A finished trial from the protocol runner (GUI thread); classified in a worker thread."""
        if self.model is not None:
            self._pending.append((planned, data))

    def refresh(self) -> None:
        self._apply_loaded()
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
        self.board.add(trial_id, truth, predicted)
