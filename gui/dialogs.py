"""Dialogs that never block STOP.

An application-modal dialog (``QDialog.exec()``, ``QFileDialog.getOpenFileName``, ``QMessageBox.question``) keeps
every click and key away from the main window while it is open, the big STOP button and Esc included, and the drum
keeps turning. Every dialog of the app is therefore opened here, *non-modal*, with a callback for its answer: the
main window (and its STOP) stays usable, and Esc inside the dialog is STOP too (it sends the safe stop, then closes
the dialog as a cancel would).

The STOP handler is the ``emergency_stop`` of the nearest parent widget that has one (the main window).
"""

from __future__ import annotations

import inspect
import weakref
from collections.abc import Callable

from PySide6 import QtCore, QtWidgets


def stop_handler(widget: QtWidgets.QWidget | None) -> Callable[[], None] | None:
    """The ``emergency_stop`` method of ``widget`` or its nearest parent that has one, else None."""
    w = widget
    while w is not None:
        fn = getattr(w, "emergency_stop", None)
        if callable(fn):
            return fn
        w = w.parentWidget()
    return None


class _EscIsStop(QtCore.QObject):
    """Event filter on a dialog: Esc (pressed on the dialog or on any of its widgets that lets it through) sends
    STOP, then closes the dialog as Cancel would."""

    def __init__(self, dialog: QtWidgets.QDialog, stop: Callable[[], None] | None):
        super().__init__(dialog)
        self.dialog = dialog
        self.stop = stop

    def eventFilter(self, obj, ev) -> bool:  # noqa: N802 - Qt override
        if ev.type() == QtCore.QEvent.KeyPress and ev.key() == QtCore.Qt.Key_Escape:
            if self.stop is not None:
                self.stop()
            self.dialog.reject()
            return True
        return False


def _weak(fn: Callable) -> Callable[[], Callable | None]:
    """A reference to ``fn`` that does not keep its object alive: a dialog's callback must not own the dialog's
    parent (deleting the dialog would then delete its own parent from inside the child's destructor)."""
    if inspect.ismethod(fn):
        return weakref.WeakMethod(fn)
    return lambda: fn


def show_dialog(dialog: QtWidgets.QDialog, on_accept: Callable[[], None] | None = None, *,
                stop: Callable[[], None] | None = None) -> QtWidgets.QDialog:
    """Show ``dialog`` non-modal (STOP in the main window stays clickable); Esc in it sends STOP and closes it;
    ``on_accept()`` runs when it is accepted. The dialog is deleted when closed. Returns it (shown, raised)."""
    stop = stop or stop_handler(dialog.parentWidget())
    dialog.setWindowModality(QtCore.Qt.NonModal)
    dialog.setModal(False)
    dialog.setAttribute(QtCore.Qt.WA_DeleteOnClose, True)
    dialog.installEventFilter(_EscIsStop(dialog, stop))
    if on_accept is not None:
        ref = _weak(on_accept)
        dialog.accepted.connect(lambda: (fn := ref()) is not None and fn())
    dialog.show()
    dialog.raise_()
    dialog.activateWindow()
    return dialog


def choose_path(parent: QtWidgets.QWidget, mode: str, caption: str, start: str, filters: str,
                on_chosen: Callable[[str], None], *, confirm_overwrite: bool = True) -> QtWidgets.QFileDialog:
    """A non-modal file dialog (Qt's own widgets, the same on every platform). ``mode``: ``"open"`` (an existing
    file), ``"save"`` (a new or existing file; with ``confirm_overwrite`` Qt asks before an existing one is taken)
    or ``"dir"`` (an existing directory). ``on_chosen(path)`` is called once with the chosen path; nothing is called
    on Cancel. Returns the dialog (shown)."""
    dlg = QtWidgets.QFileDialog(parent, caption, start or "", filters)
    dlg.setOption(QtWidgets.QFileDialog.DontUseNativeDialog, True)
    if mode == "open":
        dlg.setFileMode(QtWidgets.QFileDialog.ExistingFile)
        dlg.setAcceptMode(QtWidgets.QFileDialog.AcceptOpen)
    elif mode == "save":
        dlg.setFileMode(QtWidgets.QFileDialog.AnyFile)
        dlg.setAcceptMode(QtWidgets.QFileDialog.AcceptSave)
        dlg.setOption(QtWidgets.QFileDialog.DontConfirmOverwrite, not confirm_overwrite)
    elif mode == "dir":
        dlg.setFileMode(QtWidgets.QFileDialog.Directory)
        dlg.setOption(QtWidgets.QFileDialog.ShowDirsOnly, True)
    else:
        raise ValueError(f"mode must be 'open', 'save' or 'dir', got {mode!r}")
    ref = _weak(on_chosen)
    dlg.fileSelected.connect(lambda path: path and (fn := ref()) is not None and fn(path))
    return show_dialog(dlg)


def ask(parent: QtWidgets.QWidget, title: str, text: str, yes: str, no: str,
        on_yes: Callable[[], None]) -> QtWidgets.QMessageBox:
    """A non-modal question with two buttons; ``on_yes()`` runs when ``yes`` is chosen. Returns the message box."""
    box = QtWidgets.QMessageBox(QtWidgets.QMessageBox.Question, title, text, QtWidgets.QMessageBox.NoButton, parent)
    box.setTextFormat(QtCore.Qt.PlainText)
    yes_btn = box.addButton(yes, QtWidgets.QMessageBox.AcceptRole)
    box.addButton(no, QtWidgets.QMessageBox.RejectRole)
    box.setDefaultButton(yes_btn)
    ref = _weak(on_yes)
    box.buttonClicked.connect(lambda b: b is yes_btn and (fn := ref()) is not None and fn())
    show_dialog(box)
    return box


def open_dialogs() -> list[QtWidgets.QDialog]:
    """The app's dialogs now on screen (tests, and the window's own bookkeeping)."""
    return [w for w in QtWidgets.QApplication.topLevelWidgets() if isinstance(w, QtWidgets.QDialog) and w.isVisible()]
