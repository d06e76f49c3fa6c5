"""rigctl.operations: the operator service layer, what the CLI and the GUI both call (and nothing below imports).

One package of small modules, each one job an operator does:

- :class:`RigSource` (``_source``): where a rig comes from (a kind of :data:`rigctl.rigs.KINDS`, its ports or
  recording); :func:`open_control` opens it as a :class:`RigControl` (``_control``): setpoints checked against the
  controller's limits, run at a speed and force (press -> settle -> run), stop, tare, home, clear a fault, mount a
  plate, status; :class:`Home` says what opening does with a latched fault; its ``drum`` is a read-only
  :class:`DrumView` (``_drum_view``): no face holds the drum client. Its :attr:`RigControl.monitor`
  (:class:`RigMonitor`, ``_monitor``) polls the status, feeds the controller's watchdog, publishes
  :class:`RigEvent` s to the faces and runs the dead man's switch (a face's :class:`Heartbeat`).
- :func:`calibrate_loadcell`, :func:`record_taxel_normalisation`, :func:`store_taxel_normalisation`
  (``_calibrate``): calibrating an open rig (checked, stored, taken up by the rig at once).
- :class:`ProtocolRun` (``_run``): run, pause, resume, abort a protocol (in this thread or a worker).
- The host's safety rules, once (``_rules``): :data:`SAFETY_TRANSITIONS` (the rig's and the run's states, the events
  every face sends, the allowed transitions with their actions; anything else :class:`SafetyRefused`),
  :func:`safety_decide`, :class:`SafetyTable` (one state behind one lock), :func:`safety_table_markdown` (``rigctl
  safety table``, docs/safety.md), and :data:`RUN_STATES`, the one run-state vocabulary of every face.
- :func:`setpoint_refusals` / :class:`SetpointRefusal` (``_setpoints``): the setpoint policy in the operator's words.
- :func:`doctor` (``_doctor``): the bring-up checks (:mod:`rigctl.acquisition.doctor`) on a source or an open rig,
  the dated report stored in the rig config.
- :class:`AnalysisPlan` / :func:`run_analyses` (``_analysis``): the paper's analyses as ``rigctl analyze`` and the
  GUI's analysis tab run them (which tasks, the parameter objects of :mod:`rigctl.analysis.params`, baseline,
  skip or raise); :func:`load_or_encode`, :func:`train_model`, :func:`force_leak_report`; :func:`trial_spikes`
  (``_trial_spikes``): one trial of a session encoded on the fly, as a trial browser shows it.
- :class:`RunQueue` (``_queue``): protocol runs one after another on one rig, kept in a file across restarts
  (``rigctl serve``'s HTTP API is a face on it); :func:`read_queue_file` (a queue file read before the rig opens),
  :func:`lock_queue_file` (one queue per queue file).
- :class:`LslPublisher` (``_lsl``): a run published on Lab Streaming Layer (taxels, SA/RA spikes, drum state,
  markers); :func:`lsl_requested` (the flag, else the rig config's ``lsl.enabled``).
- :func:`import_recordings` / :class:`ImportReport` (``_import``): other labs' recordings (or a known dataset's
  preset) into a session file, with the per-file segmentation table and the outlier warnings.
- :class:`ScanClassifier` / :class:`Prediction` (``_handheld``): the handheld rig's live prediction at the end of
  each scan (a training block's classifier, re-centred on a calibration block).
- :class:`LiveEncoder` (``_live``): the taxel stream encoded into SA/RA spikes as it arrives, into
  :class:`SpikeRing` s a live view reads.

The values they speak in (:class:`rigctl.core.drum.DrumStatus`, :class:`rigctl.core.drum.DrumLimits`, states,
faults, errors) are :mod:`rigctl.core.drum`'s, shared by every layer.
"""

# the errors of opening and holding a rig, for the faces (which never import the acquisition layer's rig module)
from rigctl.acquisition.rig import FaultAtOpen, RigError, RigOpenError
from rigctl.operations._analysis import (
    ANALYSIS_TASKS,
    AnalysisPlan,
    BaselineError,
    TrainedModel,
    encoded_path_for,
    force_leak_report,
    load_or_encode,
    run_analyses,
    train_model,
)
from rigctl.operations._calibrate import (
    StoredNormalisation,
    calibrate_loadcell,
    record_taxel_normalisation,
    store_taxel_normalisation,
)
from rigctl.operations._control import Home, RigControl, RunStarted, open_control
from rigctl.operations._doctor import doctor
from rigctl.operations._drum_view import DrumView
from rigctl.operations._handheld import Prediction, ScanClassifier, recorded_predictions
from rigctl.operations._import import IMPORT_PRESETS, ImportReport, import_recordings
from rigctl.operations._live import LIVE_WINDOW_MAX_S, LiveEncoder, SpikeRing, live_ring, spike_capacity
from rigctl.operations._lsl import LslPublisher, lsl_requested
from rigctl.operations._monitor import DEADMAN_TIMEOUT_S, Heartbeat, RigEvent, RigMonitor, StatusHistory
from rigctl.operations._queue import RUN_QUEUE_STATES, QueuedRun, QueueError, RunQueue, lock_queue_file, read_queue_file
from rigctl.operations._rules import (
    RUN_STATES,
    TRANSITIONS as SAFETY_TRANSITIONS,
    Event as SafetyEvent,
    Refused as SafetyRefused,
    SafetyState,
    SafetyTable,
    decide as safety_decide,
    table_markdown as safety_table_markdown,
)
from rigctl.operations._run import ProtocolRun
from rigctl.operations._setpoints import SetpointRefusal, setpoint_refusals
from rigctl.operations._source import KINDS, RigSource
from rigctl.operations._trial_spikes import TrialSpikes, session_taxel_range, trial_spikes

__all__ = [
    "LslPublisher", "lsl_requested", "RunQueue", "QueuedRun", "QueueError", "RUN_QUEUE_STATES", "lock_queue_file",
    "read_queue_file",
    "RigSource", "KINDS", "open_control", "RigControl", "DrumView", "Home", "RunStarted", "RigError", "RigOpenError", "FaultAtOpen",
    "RigMonitor", "RigEvent", "Heartbeat", "StatusHistory", "DEADMAN_TIMEOUT_S",
    "SetpointRefusal", "setpoint_refusals", "doctor",
    "LiveEncoder", "SpikeRing", "spike_capacity", "LIVE_WINDOW_MAX_S", "live_ring",
    "AnalysisPlan", "ANALYSIS_TASKS", "BaselineError", "run_analyses", "load_or_encode", "encoded_path_for",
    "train_model", "TrainedModel", "force_leak_report", "ProtocolRun", "RUN_STATES",
    "SAFETY_TRANSITIONS", "SafetyEvent", "SafetyRefused", "SafetyState", "SafetyTable", "safety_decide",
    "safety_table_markdown",
    "TrialSpikes", "trial_spikes", "session_taxel_range",
    "import_recordings", "ImportReport", "IMPORT_PRESETS", "ScanClassifier", "Prediction", "recorded_predictions",
    "calibrate_loadcell", "record_taxel_normalisation", "store_taxel_normalisation", "StoredNormalisation",
]
