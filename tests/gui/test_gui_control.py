"""Rig control panel on the simulated rig: setpoints reach the drum controller, out-of-range input is refused, the
big STOP stops the drum, and a taxel-board disconnect is shown and recovered."""

from __future__ import annotations

import pytest
from PySide6 import QtCore

from rigctl.devices.wire import DrumState, HoldingRegister

from rigctl_gui.events import wait_for


def test_setpoints_reach_the_simulated_drum_and_stop_stops_it(window, qapp, qtbot):
    panel = window.control
    window.tabs.setCurrentWidget(panel)
    panel.speed.setValue(72.5)
    panel.force.setValue(420)
    qtbot.mouseClick(panel.apply_btn, QtCore.Qt.LeftButton)
    drum = window.handle.drum
    assert wait_for(qapp, lambda: drum.read_holding(HoldingRegister.SPEED_SETPOINT_0P1MMS) == 725
                 and drum.read_holding(HoldingRegister.FORCE_SETPOINT_G) == 420, 5)

    qtbot.mouseClick(panel.buttons["run"], QtCore.Qt.LeftButton)
    poller = window.poller
    assert wait_for(qapp, lambda: poller.latest is not None and poller.latest.state == DrumState.RUNNING
                 and abs(poller.latest.speed_mm_s - 72.5) < 1.0, 20), poller.latest
    # the panel shows the state in words and the plots hold the history
    assert wait_for(qapp, lambda: panel.state_label.text().startswith("Running"), 2)
    assert wait_for(qapp, lambda: panel.speed_curve.getData()[1] is not None
                 and abs(panel.speed_curve.getData()[1][-1] - 72.5) < 1.5, 2)
    assert abs(poller.latest.force_g - 420) < 30

    qtbot.mouseClick(window.stop_btn, QtCore.Qt.LeftButton)
    assert wait_for(qapp, lambda: poller.latest.state == DrumState.IDLE and abs(poller.latest.speed_mm_s) < 0.5, 20)
    assert poller.latest.force_setpoint_active_g == 0


def test_out_of_range_setpoint_is_refused(window, qapp, qtbot):
    panel = window.control
    drum = window.handle.drum
    limit = drum.read_holding(HoldingRegister.SPEED_LIMIT_0P1MMS) / 10.0
    assert panel.speed.maximum() == pytest.approx(limit)
    panel.speed.setValue(50.0)
    qtbot.mouseClick(panel.apply_btn, QtCore.Qt.LeftButton)
    assert wait_for(qapp, lambda: drum.read_holding(HoldingRegister.SPEED_SETPOINT_0P1MMS) == 500, 5)
    # typing a speed above the controller's limit: the spin box does not take it
    panel.speed.selectAll()
    qtbot.keyClicks(panel.speed.lineEdit(), f"{limit * 3:.0f}")
    qtbot.keyClick(panel.speed.lineEdit(), QtCore.Qt.Key_Return)
    assert panel.speed.value() <= limit
    qtbot.mouseClick(panel.apply_btn, QtCore.Qt.LeftButton)
    wait_for(qapp, lambda: False, 0.5)
    assert drum.read_holding(HoldingRegister.SPEED_SETPOINT_0P1MMS) <= limit * 10
    # and the library refuses it before anything is sent, reported in the panel
    window.commands.submit("set speed", drum.set_speed, limit * 3)
    assert wait_for(qapp, lambda: "failed" in panel.message.text(), 5), panel.message.text()


def test_taxel_board_disconnect_is_shown_and_recovered(window, qapp):
    sim = window.handle.sim
    stats = window.handle.taxels.stats
    assert stats.connected
    reconnects = stats.reconnects
    sim.unplug_taxel()
    try:
        assert wait_for(qapp, lambda: "DISCONNECTED" in window.links.taxel.text(), 10), window.links.taxel.text()
        assert window.banner.isVisible()
        assert "disconnected" in window.banner.label.text()
    finally:
        sim.replug_taxel()
    assert wait_for(qapp, lambda: window.links.taxel.text().startswith("Taxels: connected"), 15), window.links.taxel.text()
    assert "reconnected" in window.banner.label.text()
    assert window.handle.taxels.stats.reconnects > reconnects
    # frames flow again into the live view's ring
    n = window.handle.taxels.ring.total
    assert wait_for(qapp, lambda: window.handle.taxels.ring.total > n + 200, 5)
