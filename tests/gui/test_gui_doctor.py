"""Rig > Doctor...: the doctor dialog runs the library's checks on the connected rig (the in-process simulated rig:
the dialog, its worker thread and the config it writes are judged here, the checks on the rigs on ptys and under
simavr in the doctor's own tests) in a worker thread and shows each result as a row; the report lands in the rig
config."""

from __future__ import annotations

import json
import os
from pathlib import Path

from rigctl_gui.events import wait_for


def _menu_action(window, menu_title, text):
    from PySide6 import QtWidgets

    for menu in window.menuBar().findChildren(QtWidgets.QMenu):
        if menu.title().replace("&", "") == menu_title:
            for a in menu.actions():
                if a.text().replace("&", "") == text:
                    return a
    raise AssertionError(f"no menu item {menu_title} > {text}")


def test_the_doctor_dialog_shows_the_checks_of_the_connected_rig(qapp, inprocess_window):
    window = inprocess_window
    _menu_action(window, "Rig", "Doctor...").trigger()
    dlg = window._doctor
    assert dlg is not None and dlg.isVisible()
    dlg.rest_s = 2.0
    dlg.moves.setChecked(False)  # the passive checks: the shared window's rig stays released
    dlg.run_btn.click()
    assert dlg.running and not dlg.run_btn.isEnabled()
    wait_for(qapp, lambda: dlg.run_btn.isEnabled(), 120)  # re-enabled once the dialog has shown the end
    assert dlg.report is not None, dlg.status.text()
    assert dlg.row_of("link")["result"] == "PASS"
    assert dlg.row_of("noise-floor")["result"] == "PASS"
    assert dlg.row_of("serial-numbers")["result"] == "SKIP" and "USB serial" in dlg.row_of("serial-numbers")[
        "measured / why"]
    assert dlg.row_of("force-step")["result"] == ""  # not run: it moves the rig
    assert "passed" in dlg.status.text() and dlg.run_btn.isEnabled()
    stored = json.loads(Path(os.environ["RIGCTL_CONFIG"]).read_text())["doctor"]["inprocess"]
    assert stored["checked_utc"] == dlg.report.checked_utc
    from rigctl.acquisition.doctor import CHECKS

    assert [c["name"] for c in stored["checks"]] == [c.name for c in CHECKS if not c.moves]
    dlg.close()
