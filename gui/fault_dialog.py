"""The latched-fault dialog: a latched fault names itself, says what to do, and waits for the operator's
acknowledgement (with a reason) before anything clears it.

The rig's safety policy is the library's (:mod:`rigctl.acquisition.safety`): a latched fault (e-stop, over-force,
reversed load cell, watchdog, unexpected reset, HOME failure, stall, link lost mid-press) stops motion, stops a run
(resumable) and never clears by itself. This dialog is the GUI's way to acknowledge it: it names the fault and what to
do, shows whether the e-stop is still pressed (its contact open: OK stays disabled until it is released), takes a
reason, and OK calls :meth:`rigctl.operations.RigControl.acknowledge` (``reason``, ``by`` the login name) in a worker
thread; the library writes the acknowledgement into the session's event log. A refusal (the condition persists) is
shown in the dialog, which stays open. A controller fault the library holds no latch for is cleared with the
controller's Clear fault (the window's event log keeps the reason). Non-modal: STOP stays one click away.

It is the GUI's one acknowledgement path: a new latch opens it, and so do the Rig control tab's Clear fault button
and Rig > Clear fault / acknowledge (no click clears anything by itself). Every fault latched at once is named (the
library's latch and any other controller fault bit), the rig's state beside it in the library's words
(:func:`rigctl.core.drum.status_line`: after an e-stop "drivers off, actuator where it stopped, pressing 508 g"); a
dialog whose latch is gone says so and offers nothing to acknowledge.
"""

from __future__ import annotations

import logging
import threading
import weakref
from collections.abc import Callable
from typing import Any

from PySide6 import QtCore, QtWidgets

from rigctl_gui.colours import on_window

__all__ = ["FaultDialog", "latch_of", "latches_of"]


def latches_of(control: Any, faults: int = 0) -> list[tuple[str, str, str]]:
    """Everything latched on ``control`` (a :class:`rigctl.operations.RigControl`), each as ``(label, detail, what to
    do)``: the library's latch (:attr:`rigctl.operations.RigControl.latch`: the safety table's state, which the
    rig's monitor latches from every controller fault it reads), one entry a cause (two faults at once are both
    shown); ``[]`` when nothing is latched. The GUI derives no latch of its own (issue 76): the controller's fault
    bits (``faults``, kept for the callers) are not merged in."""
    del faults
    latch = getattr(control, "latch", None)
    if latch is None:
        return []
    from rigctl.acquisition.safety import CAUSES

    out: list[tuple[str, str, str]] = []
    causes = tuple(getattr(latch, "causes", (latch.cause,)))  # (two faults at once: the library names both)
    for i, cause in enumerate(causes):
        label, todo = CAUSES.get(cause, (cause, ""))
        out.append((str(label), str(latch.detail) if i == 0 else "", str(todo)))
    return out


def latch_of(control: Any, faults: int) -> tuple[str, str, str]:
    """What is latched on ``control``, as one ``(title, detail, what to do)``: every latch of :func:`latches_of`
    joined (``"e-stop + force limit exceeded"``); ``("no fault", "", "")`` when nothing is."""
    items = latches_of(control, faults)
    if not items:
        return "no fault", "", ""
    if len(items) == 1:
        return items[0]
    return (" + ".join(i[0] for i in items), " ".join(f"{i[0]}: {i[1]}" for i in items if i[1]),
            " ".join(f"{i[0]}: {i[2]}" for i in items if i[2]))


def _operator() -> str:
    """Who acknowledges: the library's operator name (the login name)."""
    from rigctl.acquisition.safety import operator_name

    return operator_name()


class FaultDialog(QtWidgets.QDialog):
    """Names the latched fault of ``control`` and acknowledges it (module docstring). ``log(level, source, text)``
    (a bound method, held weakly: the dialog never keeps its window alive) writes into the window's event log;
    ``faults`` the controller's latched fault bits as last seen."""

    acknowledged = QtCore.Signal(str)  # the acknowledgement's words, once the library took it (GUI thread)
    refused = QtCore.Signal(str)  # why it was refused (GUI thread)

    def __init__(self, control: Any, faults: int, parent: QtWidgets.QWidget | None = None, *,
                 log: Callable[[int, str, str], None] | None = None) -> None:
        super().__init__(parent)
        self.setObjectName("fault_dialog")
        self.setWindowTitle("Latched fault: the rig is stopped")
        self.setModal(False)
        self.control, self.faults = control, int(faults)
        self._log_ref = weakref.WeakMethod(log) if log is not None else None
        self.busy = False
        self.cleared = False  # the latch is gone: nothing to acknowledge (said in the dialog)
        self.title = QtWidgets.QLabel()
        self.title.setTextFormat(QtCore.Qt.TextFormat.PlainText)
        self.title.setStyleSheet(f"font-size: 16px; font-weight: bold; color: {on_window('#c00', self)};")
        self.detail = QtWidgets.QLabel()
        self.detail.setTextFormat(QtCore.Qt.TextFormat.PlainText)
        self.detail.setWordWrap(True)
        self.todo = QtWidgets.QLabel()
        self.todo.setTextFormat(QtCore.Qt.TextFormat.PlainText)
        self.todo.setWordWrap(True)
        self.rig_now = QtWidgets.QLabel()
        self.rig_now.setObjectName("rig_now")
        self.rig_now.setTextFormat(QtCore.Qt.TextFormat.PlainText)
        self.rig_now.setWordWrap(True)
        self.estop = QtWidgets.QLabel()
        self.estop.setObjectName("estop_state")
        self.estop.setTextFormat(QtCore.Qt.TextFormat.PlainText)
        self.reason = QtWidgets.QLineEdit()
        self.reason.setPlaceholderText("why it happened and what you did (written into the session's event log)")
        self.message = QtWidgets.QLabel()
        self.message.setTextFormat(QtCore.Qt.TextFormat.PlainText)
        self.message.setWordWrap(True)
        self.message.setStyleSheet(f"color: {on_window('#c00', self)};")
        self.ok_btn = QtWidgets.QPushButton("Acknowledge and clear")
        self.ok_btn.setDefault(True)
        self.later_btn = QtWidgets.QPushButton("Later")
        self.ok_btn.clicked.connect(self.acknowledge)
        self.later_btn.clicked.connect(self.reject)
        form = QtWidgets.QFormLayout()
        form.addRow("Rig now:", self.rig_now)
        form.addRow("E-stop:", self.estop)
        form.addRow("Reason:", self.reason)
        buttons = QtWidgets.QHBoxLayout()
        buttons.addStretch(1)
        buttons.addWidget(self.later_btn)
        buttons.addWidget(self.ok_btn)
        lay = QtWidgets.QVBoxLayout(self)
        lay.addWidget(self.title)
        lay.addWidget(self.detail)
        lay.addWidget(self.todo)
        lay.addLayout(form)
        lay.addWidget(self.message)
        lay.addLayout(buttons)
        self.setMinimumWidth(520)
        self.reason.textChanged.connect(lambda _=None: self.update_from(None))
        self.acknowledged.connect(self._done)
        self.refused.connect(self._refused)
        self.update_from(None)

    def update_from(self, status: Any) -> None:
        """Refresh from the newest controller status (None: keep the last): every latched fault's words, the rig's
        state in the library's words (:func:`rigctl.core.drum.status_line`: drivers off, pressing N g...) and the
        e-stop. A latch that is gone (acknowledged elsewhere, or the rig closed) is said so: nothing to acknowledge."""
        from rigctl.core.drum import status_line

        if status is not None:
            self.faults = int(status.faults)
            self._estop_open = bool(getattr(status, "estop_open", False))
            latch = getattr(self.control, "latch", None)
            try:
                self.rig_now.setText(status_line(status, latch.label if latch is not None else None))
            except (AttributeError, TypeError, ValueError):  # a status without the fields (a stand-in)
                self.rig_now.setText("")
        items = latches_of(self.control, self.faults)
        self.cleared = not items and not self.busy
        if self.cleared:
            self.title.setText("Cleared: nothing is latched now")
            self.detail.setText("The latch this dialog was opened for is gone (acknowledged, or the controller "
                                "cleared it): there is nothing to acknowledge. Motion still needs a separate start.")
            self.todo.setText("")
            self.later_btn.setText("Close")
        else:
            title, detail, todo = latch_of(self.control, self.faults)
            self.title.setText(f"Latched: {title}" if len(items) == 1 else f"Latched ({len(items)} at once): {title}")
            self.detail.setText(detail)
            self.todo.setText(f"What to do: {todo}" if todo else "")
            self.later_btn.setText("Later")
        pressed = getattr(self, "_estop_open", False)
        self.estop.setText("PRESSED (contact open): release it before acknowledging" if pressed else "released")
        self.estop.setStyleSheet(f"color: {on_window('#c00', self)}; font-weight: bold;" if pressed
                                 else f"color: {on_window('#070', self)};")
        ready = not pressed and bool(self.reason.text().strip()) and not self.busy and not self.cleared
        self.ok_btn.setEnabled(ready)
        self.ok_btn.setToolTip("" if ready else "nothing is latched" if self.cleared else
                               "release the e-stop and give a reason first" if pressed else "give a reason first")

    def acknowledge(self) -> None:
        """OK: the library's acknowledgement with the reason, in a worker thread (it moves nothing: the start is
        separate, docs/safety.md)."""
        reason = self.reason.text().strip()
        if not reason or self.busy:
            return
        self.busy = True
        self.update_from(None)
        self.message.setStyleSheet("")  # the palette's text colour
        self.message.setText("acknowledging: the library clears the latch and the controller's fault...")
        threading.Thread(target=self._work, args=(reason,), name="acknowledge", daemon=True).start()

    def _work(self, reason: str) -> None:
        try:
            if getattr(self.control, "latch", None) is not None:  # the library's latch: its acknowledgement
                self.control.acknowledge(reason, by=_operator())
            else:  # nothing latched in the library: the controller's Clear fault, the reason logged here
                self.control.clear_fault(by=_operator())
        except Exception as exc:  # noqa: BLE001 - shown in the dialog, which stays open
            self.refused.emit(str(exc))
        else:
            self.acknowledged.emit(reason)

    def _log(self, level: int, text: str) -> None:
        log = self._log_ref() if self._log_ref is not None else None
        if log is not None:
            log(level, "fault", text)

    def _done(self, reason: str) -> None:
        self.busy = False
        self._log(logging.WARNING, f"fault acknowledged by {_operator()}: {reason}")
        self.accept()

    def _refused(self, why: str) -> None:
        self.busy = False
        self.message.setStyleSheet(f"color: {on_window('#c00', self)};")
        self.message.setText(f"not cleared: {why}")
        self._log(logging.ERROR, f"acknowledgement refused: {why}")
        self.update_from(None)
