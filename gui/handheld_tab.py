"""Handheld tab: the paper's real-time system (Fig. 4A) on the handheld rig: connect the window to it (the simulated
operator, a tracker's LSL stream ``lsl:NAME`` or a motion board ``serial:PORT``, with the finger's taxel board at a
port or the sensor model's taxels), run the calibration block and the real-time block with the operator's prompts
(which plate, which profile, go) and show each scan's end-of-scan prediction as a big letter, green when right and
red when wrong.

The tab owns nothing of the rig: the handheld rig is the main window's one connection (:meth:`rigctl_gui.app.
MainWindow.connect_source`), the operations layer's :class:`rigctl.operations.RigControl`, and a block is that rig's
run (:class:`rigctl.operations.ProtocolRun`, the one run engine of every protocol). So the main STOP (the button, Esc,
the dead man's switch: :meth:`rigctl.operations.RigControl.stop`) pauses a block as it pauses a drum protocol: the
scan in progress is discarded, the operator is told to lift the finger (the rig's ``stop`` cue), and Resume goes on
at the next cue (the discarded scan cued again). Abort is its own button and asks first. The tab sends commands and
listens to the rig's event stream (:meth:`~rigctl.operations.RigControl.subscribe`: ``prompt`` events, what the rig
tells its operator; ``prediction`` events, what the :class:`rigctl.operations.ScanClassifier` predicted at each
scan's end; ``run`` events). Training the classifier and encoding the calibration block run in worker threads
(:class:`rigctl_gui.workers.Job`); the events are queued by the threads that make them and drained here every 50 ms,
so nothing slow runs on the GUI thread.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import queue
import time

from PySide6 import QtCore, QtWidgets

from rigctl_gui.classify_view import PredictionBoard
from rigctl_gui.messages import set_plain
from rigctl_gui.workers import Job

#: the blocks the tab runs: name -> the built-in protocol
BLOCKS = {"calibration": "handheld_calibration", "realtime": "handheld_realtime"}
CUE_STYLE = {"plate": "background: #ffd; border: 2px solid #aa0;", "go": "background: #2a2; color: white;",
             "stop": "background: #b00;",
             "": "background: palette(window); border: 2px solid #ccc;"}
#: what the operator reads while a block is stopped
STOPPED_TEXT = ("STOPPED{why}: lift the finger off the plate. Resume continues at the next cue (the discarded scan "
                "again); Abort block ends the block")


class HandheldTab(QtWidgets.QWidget):
    """The handheld tab (module docstring); ``main`` is the :class:`rigctl_gui.app.MainWindow` (settings,
    notifications)."""

    def __init__(self, main, parent=None):
        super().__init__(parent)
        from rigctl.acquisition.builtin import find_protocol

        self.main = main
        self.events: queue.SimpleQueue = queue.SimpleQueue()  # RigEvents, put by the threads that make them
        self._listening = None  # the RigControl this tab listens to (the main window's handheld rig)
        self._unsubscribe = None
        self._unhook_stop = None
        #: why STOP stopped the block (set by the rig's STOP listener, any thread); None while it runs
        self.stopped_reason: str | None = None
        self.job: Job | None = None  # training the classifier or encoding a block
        self.job_kind = ""  # which: classifier, encode, log
        self.run = None  # the rigctl.operations.ProtocolRun of the block being recorded
        self.block: str | None = None
        self.classifier = None
        self.calibration_enc: str | None = None
        self.last_output: str | None = None
        self.protocols = {kind: str(find_protocol(name)) for kind, name in BLOCKS.items()}
        self._build()
        self.timer = QtCore.QTimer(self)
        self.timer.timeout.connect(self.refresh)
        self.timer.start(50)

    # ------------------------------------------------------------------------------------------------- layout
    def _build_form(self) -> QtWidgets.QFormLayout:
        """The form: motion source, taxel board, Connect, classifier, scans per condition, output, block buttons."""
        self.motion = QtWidgets.QLineEdit(str(self.main.settings.value("handheld/motion", "sim")))
        self.motion.setToolTip("sim: the simulated operator; lsl:NAME: a tracker's LSL stream; serial:PORT: a motion "
                               "board (docs/guides/handheld.md)")
        self.taxel_port = QtWidgets.QLineEdit(str(self.main.settings.value("handheld/taxel_port", "")))
        self.taxel_port.setPlaceholderText("the finger's taxel board (empty: the sensor model's taxels)")
        self.taxel_port.setToolTip("With lsl:NAME or serial:PORT motion: the serial port of the finger's taxel board "
                                   "(its frames are the trials' taxels); empty: the sensor model along the tracked "
                                   "path")
        self.open_btn = QtWidgets.QPushButton("Connect")
        self.open_btn.setToolTip("Connect the window to the handheld rig (it replaces the rig connected now): its "
                                 "STOP, status and event log are the window's")
        self.open_btn.clicked.connect(self.open_rig)
        self.training = QtWidgets.QLineEdit(str(self.main.settings.value("handheld/training", "")))
        self.training.setPlaceholderText("encoded training block (rigctl encode of a handheld_training session)")
        browse = QtWidgets.QPushButton("Choose...")
        browse.clicked.connect(self._browse_training)
        self.per_condition = QtWidgets.QSpinBox()
        self.per_condition.setRange(0, 100)
        self.per_condition.setSpecialValueText("as the protocol")
        self.per_condition.setToolTip("scans per texture and profile (the protocol's: 10 per texture to calibrate, "
                                      "20 in real time)")
        self.out_dir = QtWidgets.QLineEdit(str(self.main.settings.value("dirs/output", os.getcwd())))
        self.cal_btn = QtWidgets.QPushButton("1. Calibration block")
        self.cal_btn.clicked.connect(lambda: self.start_block("calibration"))
        self.rt_btn = QtWidgets.QPushButton("2. Real-time block")
        self.rt_btn.clicked.connect(lambda: self.start_block("realtime"))
        self.resume_btn = QtWidgets.QPushButton("Resume")
        self.resume_btn.setToolTip("Go on after STOP, at the next cue (the discarded scan is cued again)")
        self.resume_btn.clicked.connect(self.resume)
        self.abort_btn = QtWidgets.QPushButton("Abort block")
        self.abort_btn.setToolTip("End the block (asks first); the finished scans stay in its file")
        self.abort_btn.clicked.connect(self.ask_abort)

        form = QtWidgets.QFormLayout()
        row = QtWidgets.QHBoxLayout()
        row.addWidget(self.motion, 1)
        row.addWidget(self.open_btn)
        form.addRow("Motion", row)
        form.addRow("Taxel board", self.taxel_port)
        row = QtWidgets.QHBoxLayout()
        row.addWidget(self.training, 1)
        row.addWidget(browse)
        form.addRow("Classifier", row)
        form.addRow("Scans per condition", self.per_condition)
        form.addRow("Output folder", self.out_dir)
        buttons = QtWidgets.QHBoxLayout()
        for b in (self.cal_btn, self.rt_btn, self.resume_btn, self.abort_btn):
            buttons.addWidget(b)
        form.addRow(buttons)
        return form

    def _build(self) -> None:
        form = self._build_form()

        self.cue = QtWidgets.QFrame()
        self.cue.setObjectName("handheld_cue")
        self.cue_plate = QtWidgets.QLabel("")
        self.cue_plate.setObjectName("handheld_cue_plate")
        self.cue_plate.setAlignment(QtCore.Qt.AlignmentFlag.AlignCenter)
        self.cue_plate.setStyleSheet("font-size: 56px; font-weight: bold;")
        self.cue_text = QtWidgets.QLabel("Connect the handheld rig, then run the calibration block")
        self.cue_text.setObjectName("handheld_cue_text")
        self.cue_text.setWordWrap(True)
        self.cue_text.setAlignment(QtCore.Qt.AlignmentFlag.AlignCenter)
        self.cue_text.setStyleSheet("font-size: 20px; font-weight: bold;")
        cl = QtWidgets.QVBoxLayout(self.cue)
        cl.addWidget(QtWidgets.QLabel("The operator's prompt (plate, profile, go)"))
        cl.addStretch(1)
        cl.addWidget(self.cue_plate)
        cl.addWidget(self.cue_text)
        cl.addStretch(1)
        self._show_cue("", "", "Connect the handheld rig, then run the calibration block")
        self.status = QtWidgets.QLabel("not open")
        self.status.setObjectName("handheld_status")
        self.status.setWordWrap(True)

        self.board = PredictionBoard(letter_px=96, per_row=7)
        left = QtWidgets.QVBoxLayout()
        left.addLayout(form)
        left.addWidget(self.cue, 1)
        left.addWidget(self.status)
        right = QtWidgets.QVBoxLayout()
        right.addWidget(QtWidgets.QLabel("Prediction at the end of each scan (green: right, red: wrong)"))
        top = QtWidgets.QHBoxLayout()
        top.addWidget(self.board.latest, 2)
        side = QtWidgets.QVBoxLayout()
        side.addWidget(self.board.score)
        side.addWidget(self.board.detail)
        side.addStretch(1)
        top.addLayout(side, 1)
        right.addLayout(top)
        right.addWidget(self.board.tiles, 1)
        # the main window's tabs scroll this tab's content when the window is shorter than it (the prediction tile
        # alone asks 211 px: rigctl_gui.widgets.PageTabs)
        lay = QtWidgets.QHBoxLayout(self)
        lay.addLayout(left, 1)
        lay.addLayout(right, 1)
        self._update_buttons()

    def _browse_training(self) -> None:
        from rigctl_gui.dialogs import choose_path  # non-modal: STOP stays usable

        choose_path(self, "open", "Encoded training block", "", "Encoded sessions (*.enc.h5 *.h5)",
                    self.training.setText)

    def _show_cue(self, cue: str, plate: str, text: str) -> None:
        text_colour = "QLabel { color: white; }" if cue == "stop" else ""  # 7:1 on the stop cue's red
        self.cue.setStyleSheet(f"QFrame#handheld_cue {{ {CUE_STYLE.get(cue, CUE_STYLE[''])} }} {text_colour}")
        self.cue.setProperty("cue", cue)
        self.cue_plate.setText(plate)
        self.cue_text.setText(text)

    def _notify(self, text: str, level: int = logging.INFO) -> None:
        notify = getattr(self.main, "notify", None)
        if notify is not None:
            notify(text, level=level, source="handheld")

    # ------------------------------------------------------------------------------------------------- commands
    @property
    def control(self):
        """The main window's rig when it is a handheld rig (a :class:`rigctl.operations.RigControl` without a drum),
        else None."""
        handle = getattr(self.main, "handle", None)
        control = getattr(handle, "control", None)
        return control if control is not None and not control.has_drum else None

    @property
    def block_running(self) -> bool:
        """A block owns the rig: recording, stopped (waiting for Resume or Abort) or latched."""
        return self.run is not None and self.run.state != "done"

    @property
    def running(self) -> bool:
        return self.block_running or (self.job is not None and not self.job.done)

    def open_rig(self) -> None:
        """Connect the main window to the handheld rig with the motion source (and taxel board) typed: the window's
        one connection (its worker: an LSL stream or a port may take seconds)."""
        from rigctl.operations import RigSource

        if self.running:
            return
        busy = getattr(self.main, "_run_lock", None) or ("the drum is turning: stop it first" if getattr(
            self.main, "drum_turning", lambda: False)() else None)
        if busy:  # the window's rig is busy: connecting another would abort its run
            set_plain(self.status, f"not connected: {busy}", error=True)
            return
        motion = self.motion.text().strip() or "sim"
        port = self.taxel_port.text().strip() or None
        try:
            source = RigSource("handheld", motion=motion, taxel_port=port)
        except ValueError as exc:
            set_plain(self.status, str(exc), error=True)
            return
        self.main.settings.setValue("handheld/motion", motion)
        self.main.settings.setValue("handheld/taxel_port", port or "")
        self.main.connect_source(source)
        set_plain(self.status, f"connecting the {source.label()}...")

    def start_block(self, kind: str) -> None:
        """Record the ``kind`` block ("calibration" or "realtime") into a new file in the output folder; the
        real-time block first trains the classifier (a worker) on the training block, re-centred on the calibration
        block recorded here."""
        if self.control is None or self.running:
            set_plain(self.status, "connect the handheld rig first" if self.control is None else "a block is running",
                      error=True)
            return
        if kind == "realtime":
            training = self.training.text().strip()
            if not os.path.exists(training):
                set_plain(self.status, "choose the encoded training block (the classifier) first", error=True)
                return
            self.main.settings.setValue("handheld/training", training)
            from rigctl.operations import ScanClassifier

            cal, control = self.calibration_enc, self.control
            self._start_job("classifier", lambda job: ScanClassifier(training, calibration=cal, control=control))
            set_plain(self.status, "training the classifier" + (" (re-centred on the calibration block)" if cal
                                                                else " (no calibration block: the training mean)"))
            return
        self._record(kind)

    def _record(self, kind: str) -> None:
        from rigctl.acquisition.protocol import Protocol, load_protocol
        from rigctl.operations import ProtocolRun

        control = self.control
        if control is None:
            set_plain(self.status, "the handheld rig is not connected any more", error=True)
            return
        proto = load_protocol(self.protocols[kind])
        if self.per_condition.value() > 0 and isinstance(proto, Protocol):
            proto = dataclasses.replace(proto, trials_per_condition=self.per_condition.value())
        folder = self.out_dir.text().strip() or os.getcwd()
        os.makedirs(folder, exist_ok=True)
        out = os.path.join(folder, f"{BLOCKS[kind]}-{time.strftime('%Y%m%d-%H%M%S')}.h5")
        clf = self.classifier if kind == "realtime" else None
        self.stopped_reason = None
        self.run = ProtocolRun(control, proto, out, on_trial=None if clf is None else clf.on_trial).start()
        self.block, self.last_output = kind, out
        if kind == "realtime":
            self.board.clear()
        set_plain(self.status, f"{kind} block: recording {len(proto.plan())} scans into {out}")
        self._notify(f"handheld {kind} block started, recording to {out}")
        lock = getattr(self.main, "apply_run_lock", None)
        if lock is not None:
            lock()  # the block owns the rig: Connect and the manual controls go at once
        self._update_buttons()

    def request_stop(self, reason: str) -> None:
        """STOP hit the rig (its :meth:`~rigctl.operations.RigControl.stop` listener, any thread; the rig then stops
        the block itself: :meth:`rigctl.operations.ProtocolRun.stop`): say why while it waits for Resume or Abort."""
        if self.block_running:
            self.stopped_reason = reason

    def resume(self) -> None:
        """Go on after STOP, at the next cue."""
        if self.block_running:
            self.stopped_reason = None
            self.run.resume()
            set_plain(self.status, f"{self.block} block resumed: the next cue follows")
            self._notify(f"handheld {self.block} block resumed")
            self._update_buttons()

    def ask_abort(self):
        """Abort the block: asks first (non-modal; STOP stays usable). STOP never aborts: it pauses the block."""
        if not self.block_running:
            return None
        from rigctl_gui.dialogs import ask

        done = sum(1 for r in self.board.results) if self.block == "realtime" else None
        self._abort_question = ask(
            self, "Abort the handheld block?",
            f"Abort the {self.block} block? The scan in progress is discarded; the finished scans stay in "
            f"{self.last_output}" + (f" ({done} predicted)" if done is not None else "") + ".",
            "Abort the block", "Keep the block", self.request_abort)
        return self._abort_question

    def request_abort(self) -> None:
        if self.block_running:
            self.run.abort()
            set_plain(self.status, f"aborting the {self.block} block: the finished scans stay in its file")
            self._notify(f"handheld {self.block} block aborted", logging.WARNING)

    def abort_and_wait(self, timeout_s: float = 10.0) -> None:
        """Abort a block and wait for its end (the window closes, or connects another rig)."""
        run = self.run
        if run is not None:
            run.abort()
            try:
                run.wait(timeout_s)
            except Exception:  # noqa: BLE001 - the run's own error; the rig is closed anyway
                pass

    def _listen(self) -> None:
        """Listen to the main window's handheld rig (again after a new connection), and to nothing else."""
        control = self.control
        if control is self._listening:
            return
        for undo in (self._unsubscribe, self._unhook_stop):
            if undo is not None:
                undo()
        self._unsubscribe = self._unhook_stop = None
        self._listening = control
        if control is None:
            self.classifier = None
            set_plain(self.status, "not connected: connect the handheld rig")
            self._show_cue("", "", "Connect the handheld rig, then run the calibration block")
            return
        self._unsubscribe = control.subscribe(self.events.put)
        self._unhook_stop = control.on_stop(self.request_stop)
        set_plain(self.status, f"connected: {control.source.label()}; run the calibration block")
        self._show_cue("", "", "Ready: run the calibration block")

    def _start_job(self, name: str, fn) -> None:
        self.job = Job(fn, name=f"handheld-{name}")
        self.job_kind = name
        self.job.start()
        self._update_buttons()

    # ------------------------------------------------------------------------------------------------- events
    def refresh(self) -> None:
        """Drain the rig's events and finish what the workers and the run did (GUI thread, every 50 ms)."""
        self._listen()
        while not self.events.empty():
            self._on_event(self.events.get())
        job = self.job
        if job is not None and job.done:
            self.job = None
            self._job_done(job, self.job_kind)
        run = self.run
        if run is not None and run.state == "done":
            self.run = None
            self._run_done(run)
        elif run is not None and run.pause_event.is_set() and run.state in ("paused", "pausing"):
            why = f" ({self.stopped_reason})" if self.stopped_reason else ""
            if self.cue.property("cue") != "stop":
                self._show_cue("stop", "", STOPPED_TEXT.format(why=why))
            set_plain(self.status, f"{self.block} block stopped{why}: Resume or Abort block")
        self._update_buttons()

    def _on_event(self, ev) -> None:
        f = ev.fields or {}
        if ev.kind == "prompt":
            if f.get("cue") == "stop":
                self._show_cue("stop", "", STOPPED_TEXT.format(why=f" ({f['reason']})" if f.get("reason") else ""))
            elif f.get("cue") == "go":
                speeds = (f"{f['start_mm_s']:g} mm/s" if f.get("start_mm_s") == f.get("end_mm_s") else
                          f"{f.get('start_mm_s', 0):g} -> {f.get('end_mm_s', 0):g} mm/s")
                self._show_cue("go", str(f.get("texture", "")), f"scan {f.get('trial_id')}: profile "
                               f"{f.get('profile')} ({speeds}): GO")
            else:
                self._show_cue("plate", str(f.get("texture", "")), f"move the finger to the start of plate "
                               f"{f.get('texture')}")
        elif ev.kind == "prediction":
            self.board.add(int(f["trial_id"]), str(f["truth"]), str(f["predicted"]))
            self._notify(ev.message, logging.INFO)
        elif ev.kind == "run" and ev.trial is not None and ev.trial.kind == "failed":
            self._notify(f"scan {ev.trial.planned.trial_id} failed: {ev.trial.error}", logging.WARNING)
        elif ev.kind == "run" and ev.trial is not None and ev.trial.kind == "halted":
            self._notify(f"handheld {self.block} block STOPPED: scan {ev.trial.planned.trial_id} discarded; Resume "
                         "cues it again, Abort block ends the block", logging.WARNING)

    def _job_done(self, job: Job, kind: str) -> None:
        if job.error:
            set_plain(self.status, f"{kind}: {job.error}", error=True)
            self._notify(f"handheld {kind} failed: {job.error}", logging.ERROR)
            return
        if kind == "classifier":
            self.classifier = job.result
            self._record("realtime")
        elif kind == "encode":
            self.calibration_enc = job.result
            set_plain(self.status, f"calibration block encoded ({job.result}): run the real-time block")

    def _run_done(self, run) -> None:
        kind, out = self.block, self.last_output
        self.block = None
        s = run.summary
        self.stopped_reason = None
        if run.error is not None or s is None:
            set_plain(self.status, f"{kind} block failed: {run.error}", error=True)
            return
        if s.stopped:
            self._show_cue("", "", f"{kind} block aborted: {s.complete}/{s.planned} scans kept in {out}")
            set_plain(self.status, f"{kind} block aborted: {s.complete}/{s.planned} scans in {out}")
            return
        self._show_cue("", "", f"{kind} block done: {s.complete}/{s.planned} scans")
        if kind == "calibration" and s.complete:
            from rigctl.encoding.pipeline import encode_session

            enc = str(out).removesuffix(".h5") + ".enc.h5"
            self._start_job("encode", lambda job: str(encode_session(
                out, enc, variants=["realtime_original", "realtime_speed_scaled"])))
            set_plain(self.status, f"calibration block: {s.complete}/{s.planned} scans; encoding it")
        elif kind == "realtime" and self.classifier is not None:
            clf = self.classifier
            self._start_job("log", lambda job: clf.log_to(out))
            set_plain(self.status, f"real-time block: {s.complete}/{s.planned} scans, {len(clf.predictions)} "
                      f"predicted, {100 * clf.accuracy():.0f} % right; predictions logged in {out}")

    def _update_buttons(self) -> None:
        busy = self.running
        stopped = self.block_running and self.run.pause_event.is_set() and self.run.state != "latched"
        self.open_btn.setEnabled(not busy)
        self.cal_btn.setEnabled(self.control is not None and not busy)
        self.rt_btn.setEnabled(self.control is not None and not busy)
        self.resume_btn.setEnabled(stopped)
        self.abort_btn.setEnabled(self.block_running and not self.run.stop_event.is_set())
