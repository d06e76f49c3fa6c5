"""The status bar's link health and dropped-frame grading, the banner strip, the event log's following and the plot
gaps, on made-up link counters (no rig: these are about what the window shows)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from PySide6 import QtWidgets

from rigctl.acquisition.link_health import LinkState
from rigctl_gui.status_bar import BAD, OK, WARN, Banners, LinkStatus
from rigctl_gui.widgets import gap_breaks


def _taxels(frames=0, dropped=0, connected=True):
    return SimpleNamespace(stats=SimpleNamespace(frames=frames, dropped=dropped, connected=connected,
                                                 frames_per_s=1000.0, crc_errors=0, reconnects=0))


def _poller(reads=0, ok=True, heartbeat=0):
    st = SimpleNamespace(heartbeat=heartbeat)
    return SimpleNamespace(reads=reads, ok=ok, failures=0, error=None, latest=st)


def test_the_status_bar_follows_both_boards_health(qapp):
    links = LinkStatus()
    events = []
    links.health_changed.connect(lambda board, ev: events.append((board, ev.state)))
    links.update_from(_poller(1, heartbeat=100), _taxels(100), now_s=0.0)
    assert ("drum", LinkState.CONNECTED) in events and ("taxel", LinkState.CONNECTED) in events
    assert links.taxel.text().startswith("Taxels: connected") and links.taxel.styleSheet() == OK
    # the taxel stream goes quiet with its port open: stalled after 1 s, red, 0 frames/s
    links.update_from(_poller(2, heartbeat=110), _taxels(200), now_s=0.1)
    links.update_from(_poller(13, heartbeat=220), _taxels(200), now_s=1.2)
    assert events[-1] == ("taxel", LinkState.STALLED)
    assert "STALLED, 0 frames/s" in links.taxel.text() and links.taxel.styleSheet() == BAD
    assert links.state == {"drum": True, "taxel": False}
    # the drum controller restarts (its heartbeat from near 0): controller reset, red
    links.update_from(_poller(14, heartbeat=5), _taxels(300), now_s=1.3)
    assert ("drum", LinkState.CONTROLLER_RESET) in events and "RESET" in links.drum.text()
    assert events[-1] == ("taxel", LinkState.RECONNECTED)
    # the drum's port fails: lost
    links.update_from(_poller(14, ok=False), _taxels(400), now_s=1.4)
    assert events[-1] == ("drum", LinkState.LOST) and "NO RESPONSE" in links.drum.text()
    links.update_from(None, None, now_s=1.5)
    assert links.state == {"drum": None, "taxel": None}


def test_dropped_frames_turn_amber_then_red_against_the_protocols_threshold(qapp):
    links = LinkStatus()
    links.update_from(None, _taxels(10, dropped=0), now_s=0)
    assert links.dropped.text().startswith("0 dropped") and links.dropped.styleSheet() == OK
    links.update_from(None, _taxels(20, dropped=5385), now_s=0.1)  # an outage, no trial being recorded
    assert "5,385 dropped (since connected)" in links.dropped.text() and links.dropped.styleSheet() == WARN
    links.judge_trial(5385, 5)  # a trial starts; the protocol keeps a trial with at most 5 lost frames
    links.update_from(None, _taxels(30, dropped=5388), now_s=0.2)
    assert links.dropped.text().startswith("3 dropped (this trial)") and links.dropped.styleSheet() == WARN
    links.update_from(None, _taxels(40, dropped=5391), now_s=0.3)
    assert links.dropped.text().startswith("6 dropped") and links.dropped.styleSheet() == BAD
    assert "at most 5" in links.dropped.toolTip()


def test_banners_come_and_go_without_moving_anything(qapp):
    w = QtWidgets.QWidget()
    lay = QtWidgets.QVBoxLayout(w)
    banners = Banners()
    button = QtWidgets.QPushButton("Press")
    lay.addWidget(banners)
    lay.addWidget(button)
    lay.addStretch(1)
    w.resize(1024, 300)
    w.show()
    qapp.processEvents()
    before = (banners.geometry(), button.geometry())
    long_text = "Drum controller FAULT (latched). " + "a very long explanation " * 30 + "END"
    banners["fault"].show_message(long_text, error=True)
    banners["taxel"].show_message("Taxel board (Uno) reconnected.", error=False, hide_after_s=5)
    qapp.processEvents()
    assert banners["fault"].isVisible() and banners["taxel"].isVisible()
    assert (banners.geometry(), button.geometry()) == before
    # shown whole (wrapped; scrollable inside the strip when even the smallest font does not fit), never cut with
    # an ellipsis (issue 38 part 8); the tooltip and the log have it too
    assert banners["fault"].text == long_text and banners["fault"].toolTip() == long_text
    assert banners["fault"].label.text() == long_text
    assert banners["fault"].text_area.verticalScrollBar().maximum() > 0  # the end is reachable
    banners["fault"].hide()
    banners["taxel"].hide()
    qapp.processEvents()
    assert (banners.geometry(), button.geometry()) == before
    w.close()


def test_the_event_log_follows_the_newest_line_unless_scrolled_up(qapp):
    import logging

    from rigctl_gui.messages import EventLog

    log = EventLog()
    log.resize(600, 120)
    log.show()
    bar = log.view.verticalScrollBar()
    for i in range(50):
        log.add(logging.INFO, "test", f"line {i}")
    qapp.processEvents()
    assert bar.value() == bar.maximum() > 0
    log.add(logging.INFO, "test", "a long line " * 60)  # adds a horizontal scroll bar: the view gets shorter
    qapp.processEvents()
    assert bar.value() == bar.maximum()
    bar.setValue(3)  # the operator scrolls up to read
    for i in range(10):
        log.add(logging.WARNING, "test", f"more {i}")
    qapp.processEvents()
    assert bar.value() == 3 and bar.maximum() > 3
    bar.setValue(bar.maximum())  # back at the end: it follows again
    log.add(logging.INFO, "test", "newest")
    qapp.processEvents()
    assert bar.value() == bar.maximum()
    log.close()


def test_gap_breaks_put_a_nan_row_in_each_outage():
    t = np.array([0.0, 0.1, 0.2, 2.2, 2.3, 9.0])
    rows = np.column_stack([t, t * 10])
    out = gap_breaks(rows, max_dt=1.0)
    assert out.shape == (8, 2)
    nan_rows = np.flatnonzero(np.isnan(out[:, 1]))
    assert list(nan_rows) == [3, 6] and np.allclose(out[nan_rows, 0], [1.2, 5.65])
    assert np.array_equal(out[~np.isnan(out[:, 1])], rows)
    assert gap_breaks(rows[:3], max_dt=1.0) is not None and len(gap_breaks(rows[:3], max_dt=1.0)) == 3


def test_info_log_lines_take_the_palettes_text_colour(qapp):
    """Issue 38 part 8: info lines were a fixed black (black on near-black with a dark palette); the other levels'
    colours are made readable on the log's background (test_gui_readable.py measures their contrast)."""
    import logging

    from rigctl_gui.messages import EventLog

    log = EventLog()
    line = log._line((0.0, logging.INFO, "app", "connected"))
    assert "color:#000" not in line and "<span><b>info</b> app: connected</span>" in line
    assert "<span style='color:#" in log._line((0.0, logging.ERROR, "app", "x"))
    log.deleteLater()


def test_banners_wrap_the_whole_text_and_keep_the_strips_height(qapp):
    """Issue 38 part 8: at 1024 px the drum banner lost "While the link is down STOP cannot ..." to an ellipsis."""
    from rigctl_gui.events import wait_for
    from rigctl_gui.status_bar import Banners

    strip = Banners()
    strip.resize(1024, 10)
    strip.show()
    height = strip.height()
    tail = "While the link is down STOP cannot reach the drum controller: stop the rig by hand (the red switch)."
    drum = ("Drum controller (Mega) not responding for 2.0 s (/dev/ttyACM0): reconnecting every 1 s. " + tail)
    strip["drum"].show_message(drum, error=True)
    for t in ("taxel", "fault", "app"):
        strip[t].show_message(f"{t}: a second message of some length to share the strip with", error=True)
    wait_for(qapp, lambda: False, 0.1)
    strip["drum"]._fit_text()
    label = strip["drum"].label
    assert label.text() == drum and "\u2026" not in label.text()  # whole, never elided
    assert label.font().pixelSize() >= strip["drum"].MIN_PX
    assert strip.height() == height  # nothing below the strip moves
    strip.close()


def test_the_drums_state_in_one_line_for_every_tab():
    """Issue 38 part 8: the top strip (on every tab) says whether the drum turns, presses or is in fault."""
    from rigctl.core.drum import DrumState, DrumStatus, Fault, StatusFlag
    from rigctl_gui.control_panel import drum_summary

    def status(state, faults=0, force_g=498.4, flags=StatusFlag.DRIVERS_ENABLED):
        return SimpleNamespace(ok=True, latest=DrumStatus(
            force_g=force_g, speed_mm_s=80.2, speed_target_mm_s=80.0, angle_deg=0.0, revolutions=0, actuator_mm=2.0,
            state=DrumState(int(state)), faults=Fault(faults), firmware=(1, 0), heartbeat=0, loadcell_raw=0,
            force_setpoint_active_g=0.0, flags=flags))

    assert drum_summary(None) == ("Drum: not connected", "#555")
    assert drum_summary(SimpleNamespace(ok=False, latest=None))[0] == "Drum: NOT RESPONDING"
    assert drum_summary(status(DrumState.RUNNING)) == ("Drum: Running 80 mm/s, 498 g", "#080")
    assert drum_summary(status(DrumState.SEEKING_FORCE))[0] == "Drum: Seeking force 80 mm/s, 498 g"
    assert drum_summary(status(DrumState.FAULT, 4, force_g=1.0)) == ("Drum: FAULT", "#c00")
    assert drum_summary(status(DrumState.IDLE, 4, force_g=1.0))[0] == "Drum: Idle (fault latched)"
    # issue 51: after an e-stop the drivers are off where they stand and the sensor stays pressed
    assert drum_summary(status(DrumState.FAULT, 16, flags=StatusFlag.ESTOP_OPEN), "e-stop") == (
        "Drum: FAULT, pressing 498 g", "#c00")
