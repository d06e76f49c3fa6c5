"""The live prediction at the end of each handheld scan (the paper's real-time block, Fig. 4A, Fig. S5).

:class:`ScanClassifier` is trained from an encoded training block (``rigctl encode`` of a ``handheld_training``
session: its real-time features, labels, normalisation and encoding constants) and, optionally, re-centred on an
encoded calibration block (``handheld_calibration``: the mean vector). Handed the run's trial events
(:meth:`on_trial`), it encodes each finished scan as the microcontroller does (:class:`rigctl.encoding.realtime.
ScanEncoder`: the readings chunk by chunk, the tracker's velocity as it came, incremental speed scaling per 100 ms
window) and predicts its texture with LDA on 25 PCs; each prediction goes to ``on_prediction`` (the terminal line)
and, with an LSL publisher, out as a ``prediction`` marker.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from rigctl.acquisition.runner import TrialEvent
from rigctl.core.normalisation import TaxelRange
from rigctl.core.trial import TrialData
from rigctl.operations._control import RigControl
from rigctl.operations._monitor import RigEvent

__all__ = ["Prediction", "ScanClassifier", "recorded_predictions"]

log = logging.getLogger(__name__)

#: how many readings the live encoder takes at a time (the taxel board's 1 kHz in 20 ms blocks)
CHUNK_SAMPLES = 20


@dataclass(frozen=True)
class Prediction:
    """One scan's prediction: trial id, the plate it was on (the truth), the profile, the predicted texture."""

    trial_id: int
    truth: str
    profile: str
    predicted: str
    #: a replayed scan: the trial id it had in the recording replayed (``replayed_trial``), else None
    source_trial: int | None = None

    @property
    def correct(self) -> bool:
        return self.predicted == self.truth

    def line(self) -> str:
        """The terminal line: ``scan 12 (plate D, fast): D  correct``."""
        return (f"scan {self.trial_id} (plate {self.truth}, {self.profile}): predicted {self.predicted}  "
                f"{'correct' if self.correct else 'WRONG'}")


class ScanClassifier:
    """Classifies each finished handheld scan (module docstring).

    Parameters
    ----------
    training : the encoded training block (``.enc.h5``).
    calibration : the encoded calibration block, or None (centre: the training block's mean).
    variant : the features classified: ``realtime_speed_scaled`` (the paper's system) or ``realtime_original``.
    n_pcs : principal components (the paper: 25).
    alignment : :data:`rigctl.analysis.realtime_model.ALIGNMENTS`: ``"statistics"`` (default: each train's mean,
        spread and change over its windows, a feature that does not depend on where on the plate the scan was cut;
        issue 78 item 2, docs/results.md 3b), ``"none"`` (the paper's: the windows themselves) or ``"session"``.
    on_prediction : receives each :class:`Prediction`.
    lsl : an :class:`rigctl.operations.LslPublisher` (its marker outlet), or None.
    control : the rig's owner (:class:`rigctl.operations.RigControl`): each prediction also goes on its event
        stream as a ``prediction`` :class:`rigctl.operations.RigEvent` (what the GUI listens to), or None.

    Raises
    ------
    ValueError
        The training file lacks the variant, or the calibration file another sensor's features.
    """

    def __init__(self, training: str | os.PathLike[str], *, calibration: str | os.PathLike[str] | None = None,
                 variant: str = "realtime_speed_scaled", n_pcs: int = 25, alignment: str = "statistics",
                 on_prediction: Callable[[Prediction], Any] | None = None, lsl: Any = None,
                 control: RigControl | None = None) -> None:
        # the encoder (numba) and the classifier (scikit-learn) load when a classifier is made, not with the layer
        from rigctl.analysis.realtime_model import RealtimeClassifier
        from rigctl.encoding.params import EncodeParams
        from rigctl.encoding.realtime import ScanEncoder
        from rigctl.storage.encoded import open_encoded

        with open_encoded(training) as f:
            if variant not in f.variants:
                raise ValueError(f"{training} holds no {variant} features (encode the training block with them)")
            x, labels = f.features(variant), f.trials["texture"]
            norm = f.normalisation
            self.params = EncodeParams.from_dict(f.parameters)
        self.variant = variant
        self.model = RealtimeClassifier(x, labels, n_pcs=n_pcs, alignment=alignment)
        #: why the calibration block's features are not on the live scans' scale ("" when they are)
        self.calibration_note = ""
        if calibration is not None:
            with open_encoded(calibration) as c:
                if variant not in c.variants:
                    raise ValueError(f"{calibration} holds no {variant} features")
                self.model.calibrate(c.features(variant), np.asarray(c.trials["texture"]).astype(str))
                cn = c.normalisation
            same = all(np.shape(cn[k]) == np.shape(norm[k]) and np.array_equal(cn[k], norm[k])
                       for k in ("taxel_min", "taxel_max"))
            if not same:  # the live scans are encoded with the training block's range: the paper's one range
                self.calibration_note = (f"{calibration} was normalised with its own range, the live scans with "
                                         f"{training}'s: encode it with rigctl encode --range-from {training}")
                log.warning("%s", self.calibration_note)
            if self.model.alignment_note:  # the session's scans sit outside the training's alignment
                log.warning("%s", self.model.alignment_note)
        self.encoder = ScanEncoder(TaxelRange(norm["taxel_min"], norm["taxel_max"]), self.params)
        self.on_prediction, self.lsl, self.control = on_prediction, lsl, control
        self.predictions: list[Prediction] = []

    def features(self, data: TrialData) -> np.ndarray:
        """The scan's features, encoded live: readings in blocks of :data:`CHUNK_SAMPLES`, each velocity sample
        given once the readings have passed its time; a scan encoded on the board (``data.onboard``): its counts
        frame's (:func:`rigctl.encoding.features.counted_realtime_features` with the speeds the board applied).
        Raises ValueError (no velocity; an on-board scan for another variant than ``realtime_speed_scaled``)."""
        if data.onboard is not None:  # encoded on the finger's board: its counts frame and the speeds it applied
            from rigctl.encoding.features import counted_realtime_features

            if self.variant != "realtime_speed_scaled":
                raise ValueError(f"a scan encoded on the board gives realtime_speed_scaled features, not {self.variant}")
            return counted_realtime_features(data.onboard.counts, data.onboard.speeds_mm_s)
        se = self.encoder
        se.reset()
        t, v = data.speed_time_s, data.speed_mm_s
        sent = 0
        for a in range(0, data.n_samples, CHUNK_SAMPLES):
            se.feed(data.taxels[a:a + CHUNK_SAMPLES])
            n = int(np.searchsorted(t, (a + CHUNK_SAMPLES) / data.rate_hz, side="right"))
            if n > sent:
                se.feed_speed(t[sent:n], v[sent:n])
                sent = n
        if sent < t.size:
            se.feed_speed(t[sent:], v[sent:])
        feats = se.features()
        if self.variant not in feats:
            raise ValueError("the scan has no velocity samples: no speed-scaled features")
        return feats[self.variant]

    def classify(self, trial_id: int, truth: str, profile: str, data: TrialData) -> Prediction:
        """Predict one scan's texture; reports it (``on_prediction``, the LSL marker) and returns it."""
        source = data.attrs.get("replayed_trial")
        pred = Prediction(int(trial_id), str(truth), str(profile), str(self.model.predict(self.features(data))[0]),
                          None if source is None else int(source))
        self.predictions.append(pred)
        if self.on_prediction is not None:
            self.on_prediction(pred)
        if self.control is not None:
            self.control.publish(RigEvent("prediction", pred.line(), time.monotonic(), fields={
                "trial_id": pred.trial_id, "truth": pred.truth, "profile": pred.profile, "predicted": pred.predicted,
                "correct": pred.correct, "variant": self.variant}))
        if self.lsl is not None:
            self.lsl.run_marker("prediction", trial_id=pred.trial_id, truth=pred.truth, profile=pred.profile,
                                predicted=pred.predicted, correct=pred.correct, variant=self.variant)
        return pred

    def on_trial(self, event: TrialEvent) -> None:
        """A run's trial event: each complete scan is classified."""
        if event.kind == "complete" and event.data is not None and event.planned is not None:
            self.classify(event.planned.trial_id, event.planned.texture, event.planned.profile, event.data)

    def accuracy(self) -> float:
        """Fraction of the scans classified so far that were right (NaN before the first)."""
        return float(np.mean([p.correct for p in self.predictions])) if self.predictions else float("nan")

    def log_to(self, session: str | os.PathLike[str]) -> int:
        """Write the predictions made so far into the session file's event log (``prediction`` events: trial id,
        truth, profile, predicted, correct, variant, PCs; after the run, which holds the file while it records; one
        commit).
        Returns how many. Raises SessionError, OSError."""
        from rigctl.storage.session import SessionWriter

        w = SessionWriter.open(session)
        try:  # one commit for all of them (each commit's journal is applied by a helper process)
            w.log_events([("prediction", {"trial_id": p.trial_id, "truth": p.truth, "profile": p.profile,
                                          "predicted": p.predicted, "correct": p.correct, "variant": self.variant,
                                          "n_pcs": self.model.n_pcs, "alignment": self.model.alignment,
                                          "session_shift_mm": self.model.shift_mm,
                                          "outside_alignment": bool(self.model.alignment_note)})
                          for p in self.predictions])
        finally:
            w.close()
        return len(self.predictions)

    def compare_recorded(self, recording: str | os.PathLike[str]) -> tuple[int, list[str]]:
        """The replay check: this run's predictions of replayed scans against those the recording logged for the
        same scans (:meth:`log_to`). Returns (how many were compared, one line per difference). Raises
        SessionError, OSError."""
        recorded = recorded_predictions(recording)
        n, diffs = 0, []
        for p in self.predictions:
            if p.source_trial is None or p.source_trial not in recorded:
                continue
            n += 1
            if recorded[p.source_trial] != p.predicted:
                diffs.append(f"scan {p.trial_id} (recorded trial {p.source_trial}): predicted {p.predicted}, the "
                             f"recorded run predicted {recorded[p.source_trial]}")
        return n, diffs


def recorded_predictions(session: str | os.PathLike[str]) -> dict[int, str]:
    """trial id -> predicted texture of a session's ``prediction`` events (the last one of each trial). Raises
    SessionError, OSError."""
    from rigctl.storage.session import open_session

    with open_session(session) as s:
        return {int(e["trial_id"]): str(e["predicted"]) for e in s.events if e.get("kind") == "prediction"}
