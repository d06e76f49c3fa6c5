"""Dialogs that never block STOP.

An application-modal dialog (``QDialog.exec()``, ``QFileDialog.getOpenFileName``, ``QMessageBox.question``) keeps
every click and key away from the main window while it is open, the big STOP button and Esc included, and the drum
keeps turning. Every dialog of the app is therefore opened here, *non-modal*, with a callback for its answer: the
main window (and its STOP) stays usable with the first click (:mod:`rigctl_gui.guards`). Esc inside a dialog closes
the dialog as Cancel would, and nothing else: it never stops the rig or aborts a run (pressing Esc to close a help
box once aborted a running protocol).
"""

from __future__ import annotations

import inspect
import weakref
from collections.abc import Callable
from typing import TypeVar

from PySide6 import QtCore, QtWidgets


def _weak(fn: Callable) -> Callable[[], Callable | None]:
    """A reference to ``fn`` that does not keep its object alive: a dialog's callback must not own the dialog's
    parent (deleting the dialog would then delete its own parent from inside the child's destructor)."""
    if inspect.ismethod(fn):
        return weakref.WeakMethod(fn)
    return lambda: fn


DialogT = TypeVar("DialogT", bound=QtWidgets.QDialog)


def show_dialog(dialog: DialogT, on_accept: Callable[[], None] | None = None) -> DialogT:
    """Show ``dialog`` non-modal (STOP in the main window stays clickable); Esc closes it as Cancel would;
    ``on_accept()`` runs when it is accepted. The dialog is deleted when closed. Returns it (shown, raised)."""
    dialog.setWindowModality(QtCore.Qt.WindowModality.NonModal)
    dialog.setModal(False)
    dialog.setAttribute(QtCore.Qt.WidgetAttribute.WA_DeleteOnClose, True)
    if on_accept is not None:
        ref = _weak(on_accept)
        dialog.accepted.connect(lambda: (fn := ref()) is not None and fn())
    dialog.show()
    dialog.raise_()
    dialog.activateWindow()
    return dialog


def choose_path(parent: QtWidgets.QWidget, mode: str, caption: str, start: str, filters: str,
                on_chosen: Callable[[str], object], *, confirm_overwrite: bool = True) -> QtWidgets.QFileDialog:
    """A non-modal file dialog (Qt's own widgets, the same on every platform). ``mode``: ``"open"`` (an existing
    file), ``"save"`` (a new or existing file; with ``confirm_overwrite`` Qt asks before an existing one is taken)
    or ``"dir"`` (an existing directory). ``on_chosen(path)`` is called once with the chosen path; nothing is called
    on Cancel. Returns the dialog (shown)."""
    dlg = QtWidgets.QFileDialog(parent, caption, start or "", filters)
    dlg.setOption(QtWidgets.QFileDialog.Option.DontUseNativeDialog, True)
    if mode == "open":
        dlg.setFileMode(QtWidgets.QFileDialog.FileMode.ExistingFile)
        dlg.setAcceptMode(QtWidgets.QFileDialog.AcceptMode.AcceptOpen)
    elif mode == "save":
        dlg.setFileMode(QtWidgets.QFileDialog.FileMode.AnyFile)
        dlg.setAcceptMode(QtWidgets.QFileDialog.AcceptMode.AcceptSave)
        dlg.setOption(QtWidgets.QFileDialog.Option.DontConfirmOverwrite, not confirm_overwrite)
    elif mode == "dir":
        dlg.setFileMode(QtWidgets.QFileDialog.FileMode.Directory)
        dlg.setOption(QtWidgets.QFileDialog.Option.ShowDirsOnly, True)
    else:
        raise ValueError(f"mode must be 'open', 'save' or 'dir', got {mode!r}")
    ref = _weak(on_chosen)
    dlg.fileSelected.connect(lambda path: path and (fn := ref()) is not None and fn(path))
    return show_dialog(dlg)


def ask(parent: QtWidgets.QWidget, title: str, text: str, yes: str, no: str,
        on_yes: Callable[[], None]) -> QtWidgets.QMessageBox:
    """A non-modal question with two buttons; ``on_yes()`` runs when ``yes`` is chosen. Returns the message box."""
    box = QtWidgets.QMessageBox(QtWidgets.QMessageBox.Icon.Question, title, text, QtWidgets.QMessageBox.StandardButton.NoButton, parent)
    box.setTextFormat(QtCore.Qt.TextFormat.PlainText)
    yes_btn = box.addButton(yes, QtWidgets.QMessageBox.ButtonRole.AcceptRole)
    box.addButton(no, QtWidgets.QMessageBox.ButtonRole.RejectRole)
    box.setDefaultButton(yes_btn)
    ref = _weak(on_yes)
    box.buttonClicked.connect(lambda b: b is yes_btn and (fn := ref()) is not None and fn())
    show_dialog(box)
    return box


def open_dialogs() -> list[QtWidgets.QDialog]:
    """The app's dialogs now on screen (tests, and the window's own bookkeeping)."""
    return [w for w in QtWidgets.QApplication.topLevelWidgets() if isinstance(w, QtWidgets.QDialog) and w.isVisible()]
