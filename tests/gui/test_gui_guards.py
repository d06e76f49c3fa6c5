"""The application-wide guards (rigctl_gui.guards) in a main window without a rig, offscreen: Esc is STOP in the
main window when nothing else takes it; Esc closing one of its menus or drop-downs, or in a dialog or a dialog's
drop-down, stops nothing; the wheel leaves an unfocused spin box alone. (tests/gui/test_gui_x11.py does the same
with real X clicks on the simulated rig.)"""

from __future__ import annotations

import pytest
from PySide6 import QtCore, QtGui, QtTest, QtWidgets

from rigctl_gui.events import wait_for


@pytest.fixture
def bare_window(qapp, gui_home):
    from rigctl_gui.app import MainWindow, configure_pyqtgraph

    configure_pyqtgraph()
    w = MainWindow(autoconnect=False)
    w.show()
    qapp.processEvents()
    stops = []
    w.stop_guard.stop = lambda: stops.append(1)  # count STOPs (no rig to stop)
    w.stops = stops
    yield w
    w.close()
    w.deleteLater()
    qapp.processEvents()


def _esc(widget):
    QtTest.QTest.keyClick(widget, QtCore.Qt.Key_Escape)


def test_esc_is_stop_in_the_main_window_but_only_closes_its_menus_and_drop_downs(bare_window, qapp):
    w = bare_window
    _esc(w.tabs.tabBar())
    assert len(w.stops) == 1
    menu = next(m for m in w.menuBar().findChildren(QtWidgets.QMenu) if m.title() == "&File")
    menu.popup(w.mapToGlobal(QtCore.QPoint(20, 20)))
    assert wait_for(qapp, lambda: QtWidgets.QApplication.activePopupWidget() is menu, 2)
    wait_for(qapp, lambda: False, 0.4)  # (past the debounce of one press)
    _esc(menu)
    assert wait_for(qapp, lambda: not menu.isVisible(), 2) and len(w.stops) == 1  # the menu closed, nothing else
    combo = w.protocol.builtin
    combo.showPopup()
    popup = QtWidgets.QApplication.activePopupWidget()
    assert popup is not None
    _esc(popup)
    assert wait_for(qapp, lambda: QtWidgets.QApplication.activePopupWidget() is None, 2) and len(w.stops) == 1
    _esc(w.tabs.tabBar())  # the popup gone, Esc is STOP again
    assert len(w.stops) == 2


def test_esc_in_a_dialog_or_its_drop_down_only_closes_it(bare_window, qapp):
    w = bare_window
    dlg = w.choose_source()
    assert dlg is not None and dlg.isVisible()
    combo = dlg.drum_port
    combo.addItems(["/dev/ttyACM0", "/dev/ttyACM1"])
    combo.showPopup()
    popup = QtWidgets.QApplication.activePopupWidget()
    assert popup is not None
    _esc(popup)
    wait_for(qapp, lambda: False, 0.2)
    assert w.stops == [] and dlg.isVisible()  # the drop-down closed, the dialog stays, nothing stopped
    _esc(dlg)
    assert wait_for(qapp, lambda: w._connect_dialog is None, 2)
    assert w.stops == []


def _wheel(widget, steps=3):
    pos = QtCore.QPointF(widget.width() / 2, widget.height() / 2)
    for _ in range(steps):
        ev = QtGui.QWheelEvent(pos, QtCore.QPointF(widget.mapToGlobal(pos.toPoint())), QtCore.QPoint(0, 0),
                               QtCore.QPoint(0, 120), QtCore.Qt.NoButton, QtCore.Qt.NoModifier,
                               QtCore.Qt.NoScrollPhase, False)
        QtWidgets.QApplication.sendEvent(widget, ev)


def test_the_wheel_changes_only_a_focused_setpoint(bare_window, qapp):
    w = bare_window
    box = w.control.speed
    assert box.focusPolicy() == QtCore.Qt.StrongFocus and w.control.plate.focusPolicy() == QtCore.Qt.StrongFocus
    box.setValue(80.0)
    w.tabs.tabBar().setFocus()
    qapp.processEvents()
    _wheel(box)
    assert box.value() == 80.0
    box.setFocus()
    qapp.processEvents()
    if not box.hasFocus():  # an offscreen window is not always the active one: make it so
        w.activateWindow()
        box.setFocus()
        qapp.processEvents()
    assert box.hasFocus()
    _wheel(box)
    assert box.value() > 80.0  # the wheel events do arrive: only the unfocused box ignored them


def test_the_analysis_tab_built_on_first_show_is_guarded_and_logged_like_the_rest(bare_window, qapp, monkeypatch):
    """The Analysis tab is built the first time it is shown (not with the window): then its spin and combo boxes
    get the wheel guard's focus policy and the wheel leaves its unfocused spin box alone, and its buttons' presses
    reach the event log, as the window's own widgets do from the start. The app starts the analysis jobs' fork
    server then (start_job_server_with_analysis, as ``rigctl gui`` wires it), once, not before."""
    import rigctl_gui.app as app

    w = bare_window
    started: list[int] = []
    monkeypatch.setattr(app, "start_job_server", lambda: started.append(1))
    app.start_job_server_with_analysis(w)
    w.tabs.setCurrentIndex(0)
    qapp.processEvents()
    assert w._analysis is None and not started  # not built with the window, no server for a tab never shown
    w.tabs.setCurrentIndex(w._analysis_index)  # the operator clicks its tab: built a plot per event-loop pass
    tab = w._analysis
    assert tab is not None and wait_for(qapp, lambda: not tab.building, 10)
    assert started == [1]
    w.tabs.setCurrentIndex(0)
    w.tabs.setCurrentIndex(w._analysis_index)
    assert started == [1] and w.analysis is tab
    app.start_job_server_with_analysis(w)  # a window whose tab is built already (``--tab analysis``): at once
    assert started == [1, 1]
    w.tabs.setCurrentIndex(w._analysis_index)
    assert tab is not None and w.tabs.currentWidget() is tab and w.analysis is tab
    boxes = tab.findChildren(QtWidgets.QAbstractSpinBox) + tab.findChildren(QtWidgets.QComboBox)
    assert len(boxes) > 5 and all(b.focusPolicy() == QtCore.Qt.StrongFocus for b in boxes)
    wait_for(qapp, lambda: False, 0.05)
    w.tabs.tabBar().setFocus()
    qapp.processEvents()
    before = tab.repeats.value()
    _wheel(tab.repeats)
    assert tab.repeats.value() == before
    tab.encode_btn.setEnabled(True)
    tab.encode_btn.click()  # (no file open: the tab says so)
    assert "pressed 'Encode'" in w.events.text()
