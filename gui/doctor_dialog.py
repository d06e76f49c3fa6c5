"""The doctor dialog (Rig > Doctor...): the bring-up checks of ``rigctl doctor`` on the connected rig, one row each
with PASS / FAIL / SKIP, what was measured and the fix. A thin face over :func:`rigctl.operations.doctor` (the CLI
calls the same function); the report is stored, dated, in the rig config."""

from __future__ import annotations

import queue
import threading

from PySide6 import QtCore, QtGui, QtWidgets

from rigctl.acquisition.doctor import CHECKS
from rigctl_gui.colours import readable
from rigctl_gui.workers import Job

#: row colours by status
COLOURS = {"pass": "#1b7f3b", "fail": "#b3261e", "skip": "#6b6b6b"}
#: columns of the results table
COLUMNS = ("check", "result", "measured / why", "fix")


class DoctorDialog(QtWidgets.QDialog):
    """Runs the doctor's checks on ``control`` (a :class:`rigctl.operations.RigControl`) in a worker thread and
    fills the table as results arrive. Closing the dialog while it runs cancels the run (the rig is stopped safely).

    Attributes
    ----------
    table : QTableWidget, one row per check (in the order they run)
    report : the :class:`rigctl.acquisition.doctor.DoctorReport` once done (None before)
    """

    def __init__(self, control, parent=None, *, host_config_path=None, rest_s: float = 10.0):
        super().__init__(parent)
        self.setWindowTitle("Rig doctor")
        self.control = control
        self.host_config_path = host_config_path
        self.rest_s = rest_s
        self.report = None
        self._job: Job | None = None
        self._results: queue.SimpleQueue = queue.SimpleQueue()
        self._cancel = threading.Event()

        self.moves = QtWidgets.QCheckBox("Include the checks that move the rig (press the sensor, turn the drum)")
        self.moves.setChecked(True)
        self.run_btn = QtWidgets.QPushButton("Run checks")
        self.run_btn.clicked.connect(self.start)
        self.status = QtWidgets.QLabel("Checks the connected rig; the result is stored in the rig config.")
        self.status.setWordWrap(True)
        self.table = QtWidgets.QTableWidget(len(CHECKS), len(COLUMNS))
        self.table.setHorizontalHeaderLabels(COLUMNS)
        self.table.verticalHeader().setVisible(False)
        self.table.setEditTriggers(QtWidgets.QAbstractItemView.EditTrigger.NoEditTriggers)
        self.table.setWordWrap(True)
        header = self.table.horizontalHeader()
        header.setSectionResizeMode(0, QtWidgets.QHeaderView.ResizeMode.ResizeToContents)
        header.setSectionResizeMode(1, QtWidgets.QHeaderView.ResizeMode.ResizeToContents)
        header.setSectionResizeMode(2, QtWidgets.QHeaderView.ResizeMode.Stretch)
        header.setSectionResizeMode(3, QtWidgets.QHeaderView.ResizeMode.Stretch)
        for row, check in enumerate(CHECKS):
            item = QtWidgets.QTableWidgetItem(check.name)
            item.setToolTip(check.title + (" (moves the rig)" if check.moves else ""))
            self.table.setItem(row, 0, item)
        buttons = QtWidgets.QDialogButtonBox(QtWidgets.QDialogButtonBox.StandardButton.Close)
        buttons.rejected.connect(self.close)

        top = QtWidgets.QHBoxLayout()
        top.addWidget(self.moves, 1)
        top.addWidget(self.run_btn)
        layout = QtWidgets.QVBoxLayout(self)
        layout.addLayout(top)
        layout.addWidget(self.status)
        layout.addWidget(self.table, 1)
        layout.addWidget(buttons)
        self.resize(1000, 560)

        self._timer = QtCore.QTimer(self)
        self._timer.setInterval(100)
        self._timer.timeout.connect(self._poll)

    # ------------------------------------------------------------------------------------------------ running
    def start(self) -> None:
        """Run the checks (all, or the passive ones) on the connected rig, in a worker thread."""
        if self._job is not None and not self._job.done:
            return
        from rigctl.operations import doctor

        names = [c.name for c in CHECKS if self.moves.isChecked() or not c.moves]
        for row in range(self.table.rowCount()):
            for col in range(1, len(COLUMNS)):
                self.table.setItem(row, col, QtWidgets.QTableWidgetItem(""))
        self._cancel.clear()
        self.report = None
        control, results, cancel = self.control, self._results, self._cancel

        def work(job):
            return doctor(control=control, checks=names, host_config_path=self.host_config_path,
                          rest_s=self.rest_s, on_result=results.put, cancel=cancel)

        self._job = Job(work, name="doctor")
        self._job.start()
        self.run_btn.setEnabled(False)
        self.moves.setEnabled(False)
        self.status.setText("Running the checks..." + (" The rig will press the sensor and turn the drum."
                                                        if self.moves.isChecked() else ""))
        self._timer.start()

    @property
    def running(self) -> bool:
        return self._job is not None and not self._job.done

    def _poll(self) -> None:
        while True:
            try:
                self._show(self._results.get_nowait())
            except queue.Empty:
                break
        job = self._job
        if job is None or not job.done:
            return
        self._timer.stop()
        self.run_btn.setEnabled(True)
        self.moves.setEnabled(True)
        if job.error is not None:
            self.status.setText(f"The doctor stopped: {job.error}")
            return
        report = self.report = job.result
        n = report.counts()
        self.status.setText(f"{n['pass']} passed, {n['fail']} failed, {n['skip']} skipped; stored in the rig config "
                            f"({report.checked_utc}).")

    def _show(self, result) -> None:
        row = next((i for i, c in enumerate(CHECKS) if c.name == result.name), None)
        if row is None:
            return
        colour = QtGui.QColor(readable(COLOURS[result.status], self.table.palette().color(QtGui.QPalette.ColorRole.Base)))
        for col, text in ((1, result.status.upper()), (2, result.summary), (3, result.fix)):
            item = QtWidgets.QTableWidgetItem(text)
            item.setToolTip(text)
            if col == 1:
                item.setForeground(colour)
                font = item.font()
                font.setBold(True)
                item.setFont(font)
            self.table.setItem(row, col, item)
        self.table.resizeRowToContents(row)

    def row_of(self, name: str) -> dict[str, str]:
        """The table's row for the check ``name``: ``{"check", "result", "measured / why", "fix"}`` (tests)."""
        row = next(i for i, c in enumerate(CHECKS) if c.name == name)
        return {col: (item.text() if (item := self.table.item(row, i)) is not None else "")
                for i, col in enumerate(COLUMNS)}

    def cancel(self) -> None:
        """End the run early: the running check stops at its next poll (the rig stopped safely), the rest skip."""
        self._cancel.set()

    def reject(self) -> None:
        """Esc and Close: cancel a running check, then hide."""
        if self.running:
            self.cancel()
        super().reject()

    def closeEvent(self, event: QtGui.QCloseEvent) -> None:  # noqa: N802 - Qt's name
        """Closing while the checks run cancels them."""
        if self.running:
            self.cancel()
        super().closeEvent(event)
