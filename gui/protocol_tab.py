"""Protocol tab: open a protocol file (:func:`rigctl.acquisition.protocol.load_protocol`), show its plan, choose the
output session file, start / pause / resume / abort a run (:class:`rigctl.operations.ProtocolRun` in a
worker thread with stop and pause events), per-trial progress and ETA, the operator prompt to mount the next
texture plate (the simulated rig mounts it by itself), and resume an interrupted session file.

STOP (the main window's, or the library's dead man's switch: any :meth:`rigctl.operations.RigControl.stop`) is the
run engine's STOP (:meth:`rigctl.operations.ProtocolRun.stop`): the drum stops, the trial in progress is discarded and
the run pauses, **stopped, resumable**: Resume records that trial again and goes on. A latched fault (docs/safety.md)
holds the run until the operator acknowledges it (the main window's fault dialog); then it goes on by itself. Abort is
its own action and asks first."""

from __future__ import annotations

import logging
import os
import threading
import time

from PySide6 import QtCore, QtGui, QtWidgets

from rigctl_gui.colours import readable
from rigctl_gui.dialogs import choose_path
from rigctl_gui.messages import set_plain
from rigctl_gui.widgets import FittedText
from rigctl_gui.workers import Job

PLAN_COLUMNS = ("trial", "texture", "speed (mm/s)", "force (g)", "duration (s)", "profile", "status")


def _fmt_s(s: float) -> str:
    s = max(0, int(round(s)))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"


class ProtocolTab(QtWidgets.QWidget):
    """The protocol tab; ``main`` is the :class:`rigctl_gui.app.MainWindow` (for the rig and the classification view)."""

    def __init__(self, main, parent=None):
        super().__init__(parent)
        self.main = main
        self.protocol = None
        self.plan = []
        self.job: Job | None = None
        self.run = None  # the rigctl.operations.ProtocolRun of the current (or last) run
        self.stop_event = threading.Event()
        self.pause_event = threading.Event()
        self._prompt_event = threading.Event()
        self._prompt_text = None
        self._done_ids: list = []
        self._done_before = 0
        self._failures: list[str] = []
        self._current = None
        self._paused = False
        self._eta = None
        self._trial_started = time.monotonic()
        #: the taxel stream's dropped-frame count when the current trial started (the status bar grades the trial)
        self.trial_dropped_base: int | None = None
        self.last_output = None
        self.last_summary = None
        #: why the run was stopped (STOP, the dead man's switch: set from any thread): it waits for Resume or Abort
        self.stopped_reason: str | None = None
        self._halted = False  # the engine discarded a trial on STOP (its "halted" event)
        self.latched: str | None = None  # the latched fault the run waits on (its "latched" event), in words
        self._unhook_stop = None  # removes this tab's STOP listener from the rig (RigControl.on_stop)

        self.open_btn = QtWidgets.QPushButton("Open protocol...")
        self.open_btn.clicked.connect(self._browse_protocol)
        self.path_label = QtWidgets.QLabel("no protocol loaded")
        self.summary = QtWidgets.QLabel("")
        self.summary.setWordWrap(True)
        # two lines whatever it says: the table and the buttons below never move
        self.summary.setFixedHeight(2 * self.summary.fontMetrics().lineSpacing() + 4)
        self.summary.setAlignment(QtCore.Qt.AlignLeft | QtCore.Qt.AlignTop)
        self.table = QtWidgets.QTableWidget(0, len(PLAN_COLUMNS))
        self.table.setHorizontalHeaderLabels(PLAN_COLUMNS)
        self.table.verticalHeader().setVisible(False)
        self.table.setEditTriggers(QtWidgets.QAbstractItemView.EditTrigger.NoEditTriggers)
        self.table.horizontalHeader().setSectionResizeMode(QtWidgets.QHeaderView.Stretch)

        self.start_btn = QtWidgets.QPushButton("Start")
        self.pause_btn = QtWidgets.QPushButton("Pause")
        self.resume_btn = QtWidgets.QPushButton("Resume")
        self.abort_btn = QtWidgets.QPushButton("Abort")
        for b, f in (
            (self.start_btn, self.start),
            (self.pause_btn, self.pause),
            (self.resume_btn, self.resume),
            (self.abort_btn, self.ask_abort),
        ):
            b.clicked.connect(f)
        self.trial_bar = QtWidgets.QProgressBar()
        self.trial_bar.setFormat("trial %p%")
        self.run_bar = QtWidgets.QProgressBar()
        self.run_bar.setFormat("session %v/%m trials")
        self.status = QtWidgets.QLabel("idle")
        self.status.setObjectName("protocol_status")
        self.status.setTextFormat(QtCore.Qt.TextFormat.PlainText)  # errors shown whole, '<' included
        self.status.setWordWrap(True)

        self._build_run_strip()

        self._build_builtin_choice()
        self.path_label.setSizePolicy(QtWidgets.QSizePolicy.Policy.Ignored, QtWidgets.QSizePolicy.Policy.Preferred)
        top = QtWidgets.QHBoxLayout()
        top.addWidget(self.open_btn)
        top.addWidget(self.builtin)
        top.addWidget(self.path_label, 1)
        out = self._build_output_row()
        ctl = QtWidgets.QHBoxLayout()
        for b in (self.start_btn, self.pause_btn, self.resume_btn, self.abort_btn):
            ctl.addWidget(b)
        ctl.addWidget(self.trial_bar, 1)
        ctl.addWidget(self.run_bar, 1)

        lay = QtWidgets.QVBoxLayout(self)
        lay.addLayout(top)
        lay.addWidget(self.summary)
        lay.addWidget(self.table, 1)
        lay.addLayout(out)
        lay.addLayout(ctl)
        lay.addWidget(self.status)
        self._update_buttons()

        last = self.main.settings.value("protocol/path") if hasattr(main, "settings") else None
        if last and os.path.exists(str(last)):
            try:
                self.load(str(last))
            except Exception:  # noqa: BLE001 - a stale setting is not an error
                pass

    def _build_output_row(self) -> QtWidgets.QHBoxLayout:
        """The output file, its chooser, Resume and Publish on LSL."""
        self.out_edit = QtWidgets.QLineEdit()
        self.out_edit.setPlaceholderText("output session file (.h5)")
        out_btn = QtWidgets.QPushButton("Choose...")
        out_btn.clicked.connect(self._browse_output)
        self.resume_box = QtWidgets.QCheckBox("Resume this (interrupted) session file")
        self.resume_box.setToolTip("Skip the trials already recorded in the output file and record the rest")
        self.lsl_box = QtWidgets.QCheckBox("Publish on LSL")
        self.lsl_box.setToolTip("Publish the run on Lab Streaming Layer for LabRecorder (taxels, SA/RA spikes, drum "
                                "state, markers; docs/guides/labrecorder.md). Set from the rig config's lsl.enabled "
                                "when the rig connects. Needs pylsl: pip install 'rigctl[lsl]'")
        out = QtWidgets.QHBoxLayout()
        out.addWidget(QtWidgets.QLabel("Output"))
        out.addWidget(self.out_edit, 1)
        out.addWidget(out_btn)
        out.addWidget(self.resume_box)
        out.addWidget(self.lsl_box)
        return out

    def _build_run_strip(self) -> None:
        """The run strip: the run's state and the operator prompt, shown by the main window above the tabs so they
        are seen from every tab."""
        self.run_strip = QtWidgets.QFrame()
        self.run_strip.setObjectName("run_strip")
        self.run_strip.setStyleSheet("QFrame#run_strip { background: #eef; border: 1px solid #88a; } QLabel { color: #000; }")
        # the whole state (STOPPED's reason and what to do), wrapped or smaller where the strip is narrow, never cut
        self.run_label = FittedText(bold=True, align=QtCore.Qt.AlignmentFlag.AlignLeft
                                    | QtCore.Qt.AlignmentFlag.AlignVCenter)
        self.run_label.setObjectName("run_state")
        self.prompt_frame = QtWidgets.QFrame()
        self.prompt_frame.setStyleSheet("QFrame { background: #ffd; border: 1px solid #aa0; } QLabel { color: #000; }")
        self.prompt_label = QtWidgets.QLabel()
        self.prompt_label.setStyleSheet("font-weight: bold;")
        self.prompt_ok = QtWidgets.QPushButton("Plate mounted - continue")
        self.prompt_ok.clicked.connect(self._prompt_done)
        pl = QtWidgets.QHBoxLayout(self.prompt_frame)
        pl.setContentsMargins(4, 0, 4, 0)
        pl.addWidget(self.prompt_label, 1)
        pl.addWidget(self.prompt_ok)
        self.prompt_frame.hide()
        # one row (the main window's top strip has a fixed height): the run's state, then the operator prompt
        rs = QtWidgets.QHBoxLayout(self.run_strip)
        rs.setContentsMargins(6, 0, 6, 0)
        rs.addWidget(self.run_label, 1)
        rs.addWidget(self.prompt_frame)
        self.run_strip.hide()

    def _build_builtin_choice(self) -> None:
        """The protocols that ship with rigctl (rigctl.acquisition.builtin), one choice away."""
        from rigctl.acquisition.builtin import builtin_protocols, summary

        self.builtin = QtWidgets.QComboBox()
        self.builtin.setObjectName("builtin_protocols")
        self.builtin.addItem("Built-in protocol...", None)
        for name, path in builtin_protocols().items():
            self.builtin.addItem(name, str(path))
            self.builtin.setItemData(self.builtin.count() - 1, summary(path) or name, QtCore.Qt.ItemDataRole.ToolTipRole)
        self.builtin.setToolTip("Load one of the protocols that ship with rigctl (rigctl acquire NAME runs the same)")
        self.builtin.activated.connect(self._builtin_chosen)

    # ------------------------------------------------------------------------------------------------------
    def _browse_protocol(self) -> QtWidgets.QFileDialog:
        """The (non-modal) file dialog to open a protocol (the built-in protocols' folder in its side bar, and
        where it starts the first time); :meth:`load` takes the chosen file."""
        from rigctl.acquisition.builtin import builtin_folder

        folder = str(builtin_folder())
        start = str(self.main.settings.value("dirs/protocol", folder))
        dlg = choose_path(self, "open", "Open protocol", start, "Protocols (*.toml *.py)", self.load)
        dlg.setSidebarUrls([*dlg.sidebarUrls(), QtCore.QUrl.fromLocalFile(folder)])
        return dlg

    def _builtin_chosen(self, index: int) -> None:
        path = self.builtin.itemData(index)
        self.builtin.setCurrentIndex(0)  # a menu of choices, not a state
        if path:
            self.load(str(path))

    def _browse_output(self) -> QtWidgets.QFileDialog:
        """The (non-modal) file dialog to choose the output session file (an existing one is resumed, never
        overwritten: Start refuses it unless 'Resume' is ticked)."""
        start = str(self.main.settings.value("dirs/output", ""))
        return choose_path(self, "save", "Session file", start, "HDF5 session (*.h5)", self._output_chosen,
                           confirm_overwrite=False)

    def _output_chosen(self, path: str) -> None:
        self.out_edit.setText(path)
        self.main.settings.setValue("dirs/output", os.path.dirname(path))
        self.resume_box.setChecked(os.path.exists(path))

    def load(self, path: str) -> None:
        """Load and show a protocol file; a bad file is reported with the line at fault (``ProtocolError``)."""
        from rigctl.acquisition.protocol import load_protocol

        if self.running:
            set_plain(self.status, "a protocol is running: abort it before loading another", error=True)
            return
        try:
            protocol = load_protocol(path)
            plan = list(protocol.plan())
        except Exception as exc:  # noqa: BLE001 - ProtocolError names the line; shown, nothing lost
            # the previous protocol is unloaded: Start must never run it into the new file name
            self.protocol, self.plan = None, []
            self.table.setRowCount(0)
            self.summary.setText("")
            self.path_label.setText(f"{path}: not loaded")
            set_plain(self.status, f"could not load {path}: {exc}", error=True)
            self._notify(logging.ERROR, f"could not load the protocol {path}: {exc}")
            self._update_buttons()
            return
        self.protocol, self.plan = protocol, plan
        set_plain(self.status, "idle")
        self.main.settings.setValue("protocol/path", path)
        self.main.settings.setValue("dirs/protocol", os.path.dirname(path))
        self.path_label.setText(path)
        self.table.setRowCount(len(self.plan))
        for r, p in enumerate(self.plan):
            vals = (
                p.trial_id,
                p.texture,
                f"{p.speed_mm_s:g}",
                f"{p.force_g:g}",
                f"{p.duration_s:g}",
                str(getattr(p, "profile", "") or "constant"),
                "planned",
            )
            for c, v in enumerate(vals):
                self.table.setItem(r, c, QtWidgets.QTableWidgetItem(str(v)))
        textures = sorted({p.texture for p in self.plan})
        speeds = sorted({p.speed_mm_s for p in self.plan})
        forces = sorted({p.force_g for p in self.plan})
        est = self.estimated_duration_s()
        self.summary.setText(
            f"<b>{getattr(self.protocol, 'name', os.path.basename(path))}</b>: {len(self.plan)} trials; "
            f"textures {', '.join(map(str, textures))}; speeds {', '.join(f'{s:g}' for s in speeds)} mm/s; "
            f"forces {', '.join(f'{f:g}' for f in forces)} g; estimated duration {_fmt_s(est)} of recording "
            "(+ force settling and plate changes per trial; the ETA below uses measured trial times)"
        )
        if not self.out_edit.text():
            base = os.path.splitext(os.path.basename(path))[0]
            self.out_edit.setText(os.path.join(str(self.main.settings.value("dirs/output", os.getcwd())), base + ".h5"))
        self.run_bar.setRange(0, len(self.plan))
        self.run_bar.setValue(0)
        self._update_buttons()

    def estimated_duration_s(self) -> float:
        """Recording time of the plan (sum of trial durations), s; settling and plate changes come on top."""
        return float(sum(float(p.duration_s) for p in self.plan))

    # ------------------------------------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        """A run owns the rig: recording, paused, stopped (waiting for Resume or Abort) or latched."""
        return self.job is not None and not self.job.done

    def _notify(self, level: int, text: str) -> None:
        notify = getattr(self.main, "notify", None)
        if notify is not None:
            notify(text, level=level, source="protocol")

    def start(self) -> None:
        h = self.main.handle
        if self.protocol is None or h is None or self.running:
            set_plain(self.status, "load a protocol and connect the rig first" if not self.running
                      else "already running", error=True)
            return
        cal = getattr(self.main, "calibration", None)
        if cal is not None and cal.job is not None and not cal.job.done:
            set_plain(self.status, "a calibration is running: start the protocol when it has finished", error=True)
            return
        out = self.out_edit.text().strip()
        if not out:
            set_plain(self.status, "choose an output file", error=True)
            return
        resume = self.resume_box.isChecked() and os.path.exists(out)
        from rigctl.storage.outputs import OutputError, check_output

        try:  # the library's one output policy (exists, held by another writer, folder, ...)
            check_output(out, option="output", overwrite=resume, kind="session",
                         overwrite_hint="tick 'Resume' to continue it, or choose another file")
        except OutputError as exc:
            set_plain(self.status, str(exc), error=True)
            return
        from rigctl.core.lsl import LslUnavailable
        from rigctl.operations import ProtocolRun

        try:
            run = ProtocolRun(h.control, self.protocol, out, resume=resume,
                              prompt=self._prompt,  # hardware only: the simulated rig mounts plates by itself
                              lsl=self.lsl_box.isChecked())
        except LslUnavailable as exc:
            set_plain(self.status, f"{exc} (or untick 'Publish on LSL')", error=True)
            return
        self.run = run
        self.stop_event, self.pause_event = run.stop_event, run.pause_event  # the run's controls, shown here
        self.stopped_reason, self._halted, self.latched = None, False, None
        control = getattr(h, "control", None)
        if control is not None:  # the rig's STOP (the button, Esc, the dead man's switch) says why it stopped the run
            self._unhook_stop = control.on_stop(self.request_stop)
        self._done_ids, self._failures = [], []
        self._current, self._paused, self._eta = None, False, None
        self._trial_started = time.monotonic()
        self._done_before = self._completed_in(out) if resume else 0

        def work(job: Job):
            run.on_trial = lambda ev: job.events.put(("trial", ev))
            return run.run()

        self.job = Job(work, name="protocol")
        self.job.start()
        lock = getattr(self.main, "apply_run_lock", None)
        if lock is not None:
            lock()  # the run owns the rig from now on: the manual controls go at once, not at the next tick
        self.last_output = out
        set_plain(self.status, f"recording to {out}" + (" (resuming)" if resume else ""))
        self._notify(logging.INFO, f"protocol {self.protocol_name()} started, recording to {out}"
                     + (" (resuming)" if resume else ""))
        self.resume_box.setChecked(False)
        for r in range(self.table.rowCount()):
            self._set_status(r, "planned")
        if resume:
            for tid in self._completed_ids(out):
                self._set_status(self._row_of(tid), "recorded earlier")
        self._update_buttons()

    @staticmethod
    def _completed_ids(path: str) -> list:
        from rigctl.storage.session import open_session

        try:
            with open_session(path) as s:
                return list(s.completed_ids())
        except Exception:  # noqa: BLE001 - the runner reports a bad file itself
            return []

    def _completed_in(self, path: str) -> int:
        return len(self._completed_ids(path))

    def protocol_name(self) -> str:
        return str(getattr(self.protocol, "name", "") or "protocol")

    def pause(self) -> None:
        if self.running:
            self.run.pause()
            set_plain(self.status, "pausing after the current trial...")
            self._notify(logging.INFO, f"protocol {self.protocol_name()}: pause requested (after the current "
                         "trial, the sensor released)")
            self._update_buttons()

    def resume(self) -> None:
        if self.running:
            self.stopped_reason, self._halted = None, False
            self.run.resume()
            set_plain(self.status, "resumed")
            self._notify(logging.INFO, f"protocol {self.protocol_name()} resumed")
            self._update_buttons()

    def ask_abort(self):
        """Abort (the button and Run > Abort): asks first (non-modal). STOP never aborts: it stops the run,
        resumable."""
        if not self.running:
            return None
        from rigctl_gui.dialogs import ask

        done = len(self._done_ids) + self._done_before
        self._abort_question = ask(
            self, "Abort the protocol run?",
            f"Abort the protocol {self.protocol_name()} ({done}/{len(self.plan)} trials done)? The trial in "
            "progress is discarded, the rig stops safely and the finished trials stay in the session file (tick "
            "'Resume' to continue it later).", "Abort the run", "Keep running", self.request_abort)
        return self._abort_question

    def request_stop(self, reason: str) -> None:
        """STOP hit the run (any thread: the rig's :meth:`~rigctl.operations.RigControl.stop` listener, which then
        stops the run itself: :meth:`rigctl.operations.ProtocolRun.stop`): say why while it waits for Resume or
        Abort."""
        if self.running and not self.stop_event.is_set():
            self.stopped_reason = reason

    def request_abort(self) -> None:
        if self.running and not self.stop_event.is_set():
            self.run.abort()
            self._prompt_event.set()
            set_plain(self.status, "aborting: the rig stops safely, finished trials stay in the file")
            self._notify(logging.WARNING, "protocol run aborted: the rig stops safely, finished trials stay in "
                         "the file")

    def abort_and_wait(self, timeout_s: float = 10.0) -> None:
        self.request_abort()
        if self.job is not None:
            self.job.join(timeout_s)

    # operator prompt (worker thread side): show it, wait for the button (or an abort)
    def _prompt(self, text, *args, **kwargs):
        self._prompt_event.clear()
        self.job.events.put(("prompt", str(text)))
        while not self._prompt_event.wait(0.1):
            if self.stop_event.is_set():
                break
        return not self.stop_event.is_set()

    def _prompt_done(self) -> None:
        self.prompt_frame.hide()
        self._prompt_event.set()

    # ------------------------------------------------------------------------------------------------------
    def _set_status(self, row: int, text: str, tip: str = "") -> None:
        if 0 <= row < self.table.rowCount():
            item = QtWidgets.QTableWidgetItem(text)
            if tip:
                item.setToolTip(tip)
            if text.startswith("FAILED"):
                item.setForeground(QtGui.QColor(readable("#c00", self.table.palette().color(QtGui.QPalette.ColorRole.Base))))
            self.table.setItem(row, len(PLAN_COLUMNS) - 1, item)

    def row_status(self, row: int) -> str:
        item = self.table.item(row, len(PLAN_COLUMNS) - 1)
        return item.text() if item is not None else ""

    def _row_of(self, trial) -> int:
        tid = int(getattr(trial, "trial_id", trial))
        for r, p in enumerate(self.plan):
            if p.trial_id == tid:
                return r
        return -1

    def _on_event(self, ev) -> None:
        """A :class:`rigctl.acquisition.runner.TrialEvent` from the runner thread."""
        self._eta = ev.eta_s
        row = self._row_of(ev.planned) if ev.planned is not None else -1
        if ev.kind in ("start", "texture") and self._current is not ev.planned:
            # a new trial (its first event may be its plate): its clock and its dropped frames start now
            self._trial_started = time.monotonic()
            handle = getattr(self.main, "handle", None)
            self.trial_dropped_base = int(handle.taxels.stats.dropped) if handle is not None else None
        if ev.kind == "start":
            self._current = ev.planned
            self._set_status(row, "settling, then recording")
        elif ev.kind == "texture":
            self._current = ev.planned
            self._set_status(row, f"mounting plate {ev.planned.texture}")
        elif ev.kind == "complete":
            self._done_ids.append(ev.planned.trial_id)
            self._set_status(row, "recorded")
            self._current = None
            if ev.data is not None:
                self.main.classify.on_trial(ev.planned, ev.data)
        elif ev.kind == "failed":
            self._set_status(row, f"FAILED: {ev.error}", ev.error)
            self._failures.append(ev.error)
            self._current = None
            self._notify(logging.ERROR, f"trial {ev.planned.trial_id} failed: {ev.error}")
        elif ev.kind == "retry":
            self._set_status(row, f"recording again (attempt {ev.attempt + 1}): {ev.error}", ev.error)
            self._notify(logging.WARNING, f"trial {ev.planned.trial_id} is recorded again: {ev.error}")
        elif ev.kind == "link_down":
            self._notify(logging.ERROR, f"the run waits for a lost link: {ev.error}")
        elif ev.kind in ("paused", "resumed"):
            self._paused = ev.kind == "paused"
            if ev.kind == "resumed":
                self.stopped_reason, self._halted = None, False
        elif ev.kind == "halted":  # STOP: the engine discarded the trial and pauses
            self._halted = True
            self._set_status(row, "stopped (not recorded: recorded again on Resume)", ev.error or "")
            self._current = None
            self._notify(logging.WARNING, f"protocol {self.protocol_name()} STOPPED"
                         + (f" ({self.stopped_reason})" if self.stopped_reason else "")
                         + f": trial {ev.planned.trial_id} discarded; Resume records it again, Abort ends the run")
        elif ev.kind == "latched":
            self.latched = ev.error or "a latched fault"
            self._set_status(row, f"LATCHED: {self.latched}", self.latched)
            self._notify(logging.ERROR, f"protocol {self.protocol_name()} waits on a latched fault: {self.latched}; "
                         "acknowledge it (the fault dialog) to go on")
        elif ev.kind == "acknowledged":
            self.latched = None
            self._set_status(row, "acknowledged: recorded again")
            self._notify(logging.INFO, f"protocol {self.protocol_name()}: the fault was acknowledged (nothing moved: "
                         f"{self._rig_words()}); Resume starts the run again (HOME and TARE first)")

    def _rig_words(self) -> str:
        """What the rig does now in the controller's words, never the run's (:func:`rigctl.core.drum.status_line` of
        the monitor's last read, with the latch held): "actuator released" only when the controller reads the
        actuator home and the load cell below :data:`rigctl.core.drum.RELEASED_G` (issue 76: a paused run said
        "rig released" while an e-stop left the sensor pressed at 304 g)."""
        from rigctl.core.drum import status_line

        h = getattr(self.main, "handle", None)
        control = getattr(h, "control", None)
        poller = getattr(self.main, "poller", None)
        st = getattr(poller, "latest", None)
        if st is None or not getattr(poller, "ok", True):
            return "the rig's state unknown (no status from its controller)"
        latch = getattr(control, "latch", None)
        return status_line(st, None if latch is None else latch.label)

    def take_rig_defaults(self, control) -> None:
        """A rig connected (a :class:`rigctl.operations.RigControl`): 'Publish on LSL' as its rig config says
        (``lsl.enabled``, default off)."""
        from rigctl.operations import lsl_requested

        self.lsl_box.setChecked(lsl_requested(None, control.host_config))

    def refresh(self) -> None:
        job = self.job
        if job is None:
            return
        while not job.events.empty():
            kind, payload = job.events.get()
            if kind == "trial":
                self._on_event(payload)
            elif kind == "prompt":
                self.prompt_label.setText(payload)
                self.prompt_frame.show()
                self._notify(logging.WARNING, f"operator: {payload}")
        n_done, n = len(self._done_ids), len(self.plan)
        self.run_bar.setValue(n_done + self._done_before)
        if not job.done:
            cur = self._current
            if cur is not None:
                # the trial's time includes settling before the recording: the bar never claims 100 % before the
                # trial is recorded
                el = time.monotonic() - self._trial_started
                self.trial_bar.setValue(int(min(95, 100 * el / max(float(cur.duration_s), 1e-3))))
                self.trial_bar.setFormat(f"trial {cur.trial_id}: {el:.1f} s (settling, then {cur.duration_s:g} s)")
            rig = self._rig_words()
            if self.latched:
                state = f"LATCHED: {self.latched} - {rig} - acknowledge it in the fault dialog, then Resume"
            elif self.pause_event.is_set() and (self._halted or self.stopped_reason):
                why = f" ({self.stopped_reason})" if self.stopped_reason else ""
                state = (f"STOPPED{why}: {rig}. Resume records the discarded trial again, Abort ends the run")
            elif self.pause_event.is_set():
                state = f"PAUSED: {rig}" if self._paused else f"pausing after the current trial ({rig})..."
            elif cur is not None:
                state = f"trial {cur.trial_id}: texture {cur.texture}, {cur.speed_mm_s:g} mm/s, {cur.force_g:g} g"
            else:
                state = "preparing"
            eta = "" if self._eta is None or self._eta != self._eta else f", ETA {_fmt_s(self._eta)}"
            text = f"{state} - {n_done + self._done_before}/{n} done{eta}"
            set_plain(self.status, text)
            self.run_label.setText(f"Protocol {self.protocol_name()}: {text}")
            self.run_strip.show()
        else:
            self.job = None
            if self._unhook_stop is not None:
                self._unhook_stop()
                self._unhook_stop = None
            self.prompt_frame.hide()
            self.run_strip.hide()
            self.trial_bar.setFormat("trial %p%")
            summary = job.result
            for r in range(self.table.rowCount()):  # a trial cut short by the abort is not "recording" any more
                if self.row_status(r).startswith(("settling", "recording", "mounting")):
                    self._set_status(r, "aborted (not recorded)")
            level = logging.INFO
            self.stopped_reason, self._halted, self.latched = None, False, None
            if job.error:
                text, level = f"run failed: {job.error}", logging.ERROR
            elif summary is not None and summary.stopped:
                text, level = (f"aborted: {summary.complete}/{summary.planned} trials in {self.last_output} "
                               "(tick 'Resume' and Start to continue it)"
                               + (f"; {summary.link_lost}" if summary.link_lost else "")), logging.WARNING
            elif summary is not None:
                self.trial_bar.setValue(100)
                text = (f"finished: {summary.complete}/{summary.planned} trials in {self.last_output} "
                        f"({summary.samples} samples, {summary.dropped_frames} dropped frames, "
                        f"{summary.crc_errors} CRC errors, {summary.failed} failed)")
                level = logging.WARNING if summary.failed else logging.INFO
            else:
                text = "run ended"
            set_plain(self.status, text, error=level >= logging.ERROR)
            self._notify(level, f"protocol {self.protocol_name()} {text}")
            self.last_summary = summary
        self._update_buttons()

    def _update_buttons(self) -> None:
        running = self.running
        self.start_btn.setEnabled(not running and self.protocol is not None)
        self.pause_btn.setEnabled(running and not self.pause_event.is_set() and not self.stop_event.is_set())
        self.resume_btn.setEnabled(running and self.pause_event.is_set() and not self.latched)
        self.abort_btn.setEnabled(running)
        self.open_btn.setEnabled(not running)
        self.builtin.setEnabled(not running)
