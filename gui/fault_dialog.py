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
"""

from __future__ import annotations

import logging
import threading
import weakref
from collections.abc import Callable
from typing import Any

from PySide6 import QtCore, QtWidgets

from rigctl_gui.colours import on_window

__all__ = ["FaultDialog", "latch_of"]


def latch_of(control: Any, faults: int) -> tuple[str, str, str]:
    """What is latched on ``control`` (a :class:`rigctl.operations.RigControl`), as ``(title, detail, what to do)``:
    the library's latch (:attr:`rigctl.operations.RigControl.latch`) when it holds one, else the controller's fault
    bits ``faults``."""
    from rigctl.core.drum import FAULT_WORDS, Fault

    latch = getattr(control, "latch", None)
    if latch is not None:
        from rigctl.acquisition.safety import CAUSES

        label, todo = CAUSES.get(latch.cause, (latch.cause, ""))
        return str(label), str(latch.detail), str(todo)
    words = [FAULT_WORDS[b] for b in Fault if int(faults) & int(b) and b in FAULT_WORDS]
    if not words:
        return "no fault", "", ""
    return (", ".join(w.label for w in words), " ".join(w.meaning[:1].upper() + w.meaning[1:] + "." for w in words),
            " ".join(w.advice for w in words))


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
        self.title = QtWidgets.QLabel()
        self.title.setTextFormat(QtCore.Qt.TextFormat.PlainText)
        self.title.setStyleSheet(f"font-size: 16px; font-weight: bold; color: {on_window('#c00', self)};")
        self.detail = QtWidgets.QLabel()
        self.detail.setTextFormat(QtCore.Qt.TextFormat.PlainText)
        self.detail.setWordWrap(True)
        self.todo = QtWidgets.QLabel()
        self.todo.setTextFormat(QtCore.Qt.TextFormat.PlainText)
        self.todo.setWordWrap(True)
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
        """Refresh from the newest controller status (None: keep the last): the fault's words and the e-stop."""
        if status is not None:
            self.faults = int(status.faults)
            self._estop_open = bool(getattr(status, "estop_open", False))
        title, detail, todo = latch_of(self.control, self.faults)
        self.title.setText(f"Latched: {title}")
        self.detail.setText(detail)
        self.todo.setText(f"What to do: {todo}" if todo else "")
        pressed = getattr(self, "_estop_open", False)
        self.estop.setText("PRESSED (contact open): release it before acknowledging" if pressed else "released")
        self.estop.setStyleSheet(f"color: {on_window('#c00', self)}; font-weight: bold;" if pressed
                                 else f"color: {on_window('#070', self)};")
        ready = not pressed and bool(self.reason.text().strip()) and not self.busy
        self.ok_btn.setEnabled(ready)
        self.ok_btn.setToolTip("" if ready else "release the e-stop and give a reason first" if pressed
                               else "give a reason first")

    def acknowledge(self) -> None:
        """OK: the library's acknowledgement with the reason, in a worker thread (it homes the actuator)."""
        reason = self.reason.text().strip()
        if not reason or self.busy:
            return
        self.busy = True
        self.update_from(None)
        self.message.setStyleSheet("")  # the palette's text colour
        self.message.setText("acknowledging: the rig is made ready (STOP, CLEAR_FAULT, HOME)...")
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
        self._log(logging.WARNING, f"fault acknowledged by the operator: {reason}")
        self.accept()

    def _refused(self, why: str) -> None:
        self.busy = False
        self.message.setStyleSheet(f"color: {on_window('#c00', self)};")
        self.message.setText(f"not cleared: {why}")
        self._log(logging.ERROR, f"acknowledgement refused: {why}")
        self.update_from(None)
