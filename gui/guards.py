"""Application-wide event filters: STOP before any popup, and no mouse wheel on an unfocused setpoint.

:class:`StopGuard` sees every mouse press and key press of the application before the widget it is meant for. While
a popup is open (a menu, a combo box's list, a tooltip-like frame) Qt hands the first click anywhere to the popup,
which only closes itself: a click on STOP would be lost and the drum would keep turning. The guard calls STOP
itself when the press lies inside STOP's rectangle on screen, and lets the popup close as usual. Esc is STOP only
when nothing else takes it: an open popup (a menu, a drop-down's list) closes on Esc and nothing stops, a widget that
uses Esc (an editor in a table cell) keeps it, and in a dialog Esc only closes the dialog (STOP stays one click away,
no dialog is modal: :mod:`rigctl_gui.dialogs`). An Esc that no widget took reaches the main window itself (Qt passes
an ignored key press on to the parent, up to the window): that one is STOP. STOP never aborts a run (it stops it,
resumable), so an Esc taken for STOP by mistake costs a Resume, never the run.

:class:`WheelGuard` keeps the mouse wheel away from spin boxes and combo boxes that do not have the keyboard focus
(the wheel scrolls the panel under them instead): scrolling a panel never changes a setpoint by accident. Such
widgets take the focus only by a click or Tab (``Qt.StrongFocus``), never by the wheel.

:func:`install_guards` installs both as ONE application filter (:class:`GuardFilter`): every event of the application
(paints, timers, queued calls: dozens per frame of the live view) crosses into Python once, and all but mouse presses,
key presses and wheel turns go back after one look at the event's class (issue 26: two filters each reading the
event's type enum cost ~0.5 ms of a 33 ms frame).
"""

from __future__ import annotations

import time
from collections.abc import Callable

from PySide6 import QtCore, QtGui, QtWidgets

#: two STOP triggers closer than this (s) are one press seen twice (by the guard and by the button)
_SAME_PRESS_S = 0.3

def _app() -> QtCore.QCoreApplication:
    """The running QApplication (the guards are installed on it). Raises RuntimeError before one exists."""
    app = QtWidgets.QApplication.instance()
    if app is None:
        raise RuntimeError("no QApplication: create it before installing the guards")
    return app

class StopGuard(QtCore.QObject):
    """Routes a press on ``button`` (and Esc) to ``stop()`` before an open popup of ``window`` consumes it.

    Install with ``QApplication.instance().installEventFilter(guard)``; :meth:`uninstall` removes it. ``stop``
    is called at most once per press (:meth:`trigger` debounces the guard and the button's own click)."""

    def __init__(self, window: QtWidgets.QWidget, button: QtWidgets.QAbstractButton, stop: Callable[[], None]):
        super().__init__(window)
        self.window = window
        self.button = button
        self.stop = stop
        self._last = -1.0
        self.routed = 0  # presses routed to STOP past a popup (tests, log)

    def install(self) -> "StopGuard":
        """Install this guard alone as an application filter (:func:`install_guards` installs both as one)."""
        self.filter: QtCore.QObject = GuardFilter(stop=self)
        _app().installEventFilter(self.filter)
        return self

    def uninstall(self) -> None:
        _remove(getattr(self, "filter", None))

    def trigger(self) -> None:
        """Call ``stop()`` unless it was called for this same press already."""
        now = time.monotonic()
        if now - self._last < _SAME_PRESS_S:
            return
        self._last = now
        self.stop()

    def _on_stop(self, global_pos: QtCore.QPoint) -> bool:
        b = self.button
        if not (b.isVisible() and b.isEnabled()):
            return False
        return QtCore.QRect(b.mapToGlobal(QtCore.QPoint(0, 0)), b.size()).contains(global_pos)

    def handle(self, obj, ev) -> bool:
        """A mouse or key event to ``obj``: True when it was STOP (consumed)."""
        t = ev.type()
        if t == QtCore.QEvent.Type.MouseButtonPress and isinstance(obj, QtWidgets.QWidget):
            popup = QtWidgets.QApplication.activePopupWidget()
            if popup is not None and ev.button() == QtCore.Qt.MouseButton.LeftButton \
                    and self._on_stop(ev.globalPosition().toPoint()):
                self.routed += 1
                self.trigger()
                popup.close()
                return True
        elif t == QtCore.QEvent.Type.KeyPress and ev.key() == QtCore.Qt.Key.Key_Escape and obj is self.window:
            # Esc reached the main window itself: no popup, dialog or widget on the way took it (a popup gets every
            # key while it is open, so Esc closing a drop-down never comes here)
            if QtWidgets.QApplication.activePopupWidget() is None and not ev.isAutoRepeat():
                self.trigger()
                return True
        return False


class WheelGuard(QtCore.QObject):
    """The mouse wheel reaches a spin box or a combo box only while it has the keyboard focus; otherwise the wheel
    goes to the widget's parent (a scroll area scrolls). :meth:`protect` sets ``Qt.StrongFocus`` on the widgets."""

    KINDS = (QtWidgets.QAbstractSpinBox, QtWidgets.QComboBox)

    def install(self) -> "WheelGuard":
        """Install this guard alone as an application filter (:func:`install_guards` installs both as one)."""
        self.filter: QtCore.QObject = GuardFilter(wheel=self)
        _app().installEventFilter(self.filter)
        return self

    def uninstall(self) -> None:
        _remove(getattr(self, "filter", None))

    @classmethod
    def protect(cls, root: QtWidgets.QWidget) -> int:
        """Give every spin box and combo box under ``root`` ``Qt.StrongFocus`` (click or Tab, not the wheel).
        Returns how many."""
        n = 0
        for w in root.findChildren(QtWidgets.QWidget):
            if isinstance(w, cls.KINDS):
                w.setFocusPolicy(QtCore.Qt.FocusPolicy.StrongFocus)
                n += 1
        return n

    def handle(self, obj, ev) -> bool:
        """A wheel event to ``obj``: True when it was kept from an unfocused box (passed on to its parent)."""
        if ev.type() != QtCore.QEvent.Type.Wheel or not isinstance(obj, QtWidgets.QWidget):
            return False
        target: QtWidgets.QWidget | None = obj
        # a spin box's line edit or a combo's own child gets the event first: judge the box it belongs to
        while target is not None and not isinstance(target, self.KINDS):
            target = target.parentWidget() if not target.isWindow() else None
        if target is None or target.hasFocus() or ((proxy := target.focusProxy()) is not None and proxy.hasFocus()):
            return False
        if isinstance(target, QtWidgets.QComboBox) and target.view().isVisible():
            return False  # its open list scrolls
        ev.ignore()  # not for this box: Qt passes an ignored wheel event on to the parent (the scroll area)
        return True


class GuardFilter(QtCore.QObject):
    """One application event filter for a :class:`StopGuard` and a :class:`WheelGuard` (either may be None): mouse
    and key events go to the STOP guard, wheel events to the wheel guard, and every other event straight back to Qt,
    judged by the event's Python class alone (reading ``ev.type()`` builds an enum member: too slow for every paint
    and timer event of the application)."""

    def __init__(self, stop: StopGuard | None = None, wheel: WheelGuard | None = None):
        super().__init__(stop.window if stop is not None else None)
        self._by_class: dict[type, Callable[[QtCore.QObject, QtCore.QEvent], bool]] = {}
        if stop is not None:
            self._by_class[QtGui.QMouseEvent] = self._by_class[QtGui.QKeyEvent] = stop.handle
        if wheel is not None:
            self._by_class[QtGui.QWheelEvent] = wheel.handle

    def eventFilter(self, obj, ev) -> bool:  # noqa: N802 - Qt override
        handle = self._by_class.get(type(ev))
        return handle is not None and handle(obj, ev)


def _remove(event_filter: QtCore.QObject | None) -> None:
    app = QtWidgets.QApplication.instance()
    if app is not None and event_filter is not None:
        app.removeEventFilter(event_filter)


def install_guards(window: QtWidgets.QWidget, stop_button: QtWidgets.QAbstractButton,
                   stop: Callable[[], None]) -> tuple[StopGuard, WheelGuard]:
    """Install both guards for ``window`` (its STOP ``stop_button`` calling ``stop``) as one application filter and
    protect its spin and combo boxes; returns them (uninstall either, or both, when the window closes: both go)."""
    WheelGuard.protect(window)
    stop_guard, wheel_guard = StopGuard(window, stop_button, stop), WheelGuard(window)
    stop_guard.filter = wheel_guard.filter = GuardFilter(stop_guard, wheel_guard)
    _app().installEventFilter(stop_guard.filter)
    return stop_guard, wheel_guard


__all__ = ["GuardFilter", "StopGuard", "WheelGuard", "install_guards"]
