"""Drive the real app on a real X server (run by tests/gui/test_gui_x11.py under Xvfb + openbox, never directly).

``python x11_driver.py OUT.json [--fit-only]`` with ``DISPLAY`` set: opens the main window as an experimenter would, clicks and
types with xdotool (real X events through the X server, past the popups' pointer grabs), and writes what it measured
to ``OUT.json`` for the test to judge. Nothing is asserted here: the test does that.

Measures, in order:

- ``fit``: first start (fresh settings) and a start after a larger size was saved: the screen's available area, the
  window's frame, its smallest size and STOP's rectangle on screen, and Qt's scale factor (``--fit-only``: only
  this, e.g. under ``QT_SCALE_FACTOR=1.5``);
- ``stall``: the live tab shown, the drum turning, every visible widget's geometry; the simulated Uno stalled
  :data:`STALL_S`: the time until the taxel banner and the log line, every widget's geometry again, and after it
  resumes the gaps in the live traces;
- ``menu_stop`` / ``combo_stop``: the drum turning, a menu (File) or the plate drop-down opened by a click, then
  one click on STOP: whether the popup was open, the controller's state and speed target afterwards;
- ``wheel``: the wheel over the unfocused speed box, then over the focused one: the values;
- ``esc_dialog``: a protocol running, the keyboard-shortcuts dialog opened, Esc: the dialog closed, the run going.

The window of the second start is the rig's; one rig serves all the checks after it, in this order (the drum still
turning after the stall is the menu's); every wait is on the condition (the window manager's placement, the drum's
state, a popup), fixed pauses only where nothing is to be seen (a wheel that must change nothing, a run that must go
on).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import threading
import time

PROTOCOL = """
name = "x11_run"
textures = ["A"]
speeds_mm_s = [60]
forces_g = [300]
trials_per_condition = 3
duration_s = 2.0
retries = 0
"""

#: how long the simulated Uno stalls, s: longer than the taxel link's 1 s to call it stalled plus the 2 s the banner
#: may take, and than the live view's 2 s window (the gap then takes the whole window)
STALL_S = 3.0


def main(out_path: str, fit_only: bool = False) -> int:
    tmp = tempfile.mkdtemp(prefix="rigctl-x11-")
    os.environ["RIGCTL_CONFIG"] = os.path.join(tmp, "rig.json")
    # the rig paced to the wall clock, as for a person at the window (the suite's default is unpaced): the stall's
    # banner, log line and gap are judged on the wall clock the person sees
    os.environ["RIGCTL_SIM_PACE"] = "wall"
    from PySide6 import QtCore, QtWidgets

    QtCore.QSettings.setPath(QtCore.QSettings.IniFormat, QtCore.QSettings.UserScope, os.path.join(tmp, "settings"))
    app = QtWidgets.QApplication(sys.argv[:1])
    from rigctl.devices.wire import DrumState
    from rigctl_gui.app import MainWindow, configure_pyqtgraph, make_settings
    from rigctl_gui.dialogs import open_dialogs
    from rigctl_gui.events import wait_for
    from rigctl_gui.workers import RigSource

    configure_pyqtgraph()
    out: dict = {}

    def wait(pred, timeout_s):
        return wait_for(app, pred, timeout_s)

    def pause(s):
        wait(lambda: False, s)

    def xdo(*args):
        subprocess.run(["xdotool", *map(str, args)], check=True, timeout=10)
        pause(0.2)

    def centre(w):
        p = w.mapToGlobal(QtCore.QPoint(w.width() // 2, w.height() // 2))
        return p.x(), p.y()

    def click(w):
        xdo("mousemove", *centre(w))
        xdo("click", 1)

    def rect(w):
        p = w.mapToGlobal(QtCore.QPoint(0, 0))
        return [p.x(), p.y(), w.width(), w.height()]

    def placed(w, timeout_s=10.0):
        """Wait until the window manager has framed and placed ``w`` (mapped, exposed, a frame around it) and its
        frame has kept still for 0.3 s (a resize to fit the screen may follow the first placement)."""
        def framed():
            h = w.windowHandle()
            return h is not None and h.isExposed() and w.frameGeometry() != w.geometry()
        end = time.monotonic() + timeout_s
        wait(framed, timeout_s)
        last = w.frameGeometry()
        while time.monotonic() < end:
            pause(0.3)
            now = w.frameGeometry()
            if now == last:
                return
            last = now

    def place(w):
        screen = w.screen()
        g = w.frameGeometry()
        smallest = w.minimumSizeHint().expandedTo(w.minimumSize())
        return {"avail": list(screen.availableGeometry().getRect()), "screen": list(screen.geometry().getRect()),
                "frame": list(g.getRect()), "stop": rect(w.stop_btn), "visible": w.isVisible(),
                "smallest": [smallest.width(), smallest.height()], "scale": w.devicePixelRatio()}

    # the GUI tests' dead man's limit (tests/gui/conftest.py TEST_DEADMAN_S): a loaded machine can starve the GUI
    # thread for half a second, and these checks are not about the dead man's switch
    MainWindow.deadman_s = 5.0
    # --- fit: first start, then after a larger size was saved ---
    w = MainWindow(autoconnect=False)
    w.show()
    placed(w)
    out["fit_first"] = place(w)
    w.close()
    # the saved size: a plain widget's geometry (the same bytes as the main window's; never shown: no window manager
    # clamps it)
    big = QtWidgets.QWidget()
    big.setGeometry(0, 0, 2400, 1600)
    make_settings().setValue("ui/geometry", big.saveGeometry())
    big.deleteLater()
    # (the window of the rig's checks below: it connects meanwhile)
    w = MainWindow(autoconnect=False) if fit_only else MainWindow(RigSource("sim"))
    out["restored_size_before_fit"] = [w.width(), w.height()]
    w.show()
    placed(w)
    out["fit_restored"] = place(w)
    if fit_only:
        w.close()
        app.processEvents()
        return _write(out_path, out)

    # --- the rig: the simulated rig on ptys ---
    ok = wait(lambda: w.handle is not None, 60)
    out["connected"] = ok
    if not ok:
        out["connect_error"] = w.banner.text
        return _write(out_path, out)
    wait(lambda: w.poller.latest is not None, 10)
    from rigctl.operations._control import rig_of

    sim = rig_of(w.handle.control).backend.sim

    def state():
        st = w.poller.latest
        return (int(st.state), float(st.speed_target_mm_s)) if st is not None else (None, None)

    def turning():
        return state()[0] == DrumState.RUNNING and w.poller.latest.speed_mm_s > 20

    spin_failures: list = []

    def spin():
        if turning():  # (still turning from the section before)
            return True
        w.control.speed.setValue(60.0)
        w.control.force.setValue(300.0)
        w.control.command("run")
        ok = wait(turning, 40)
        if not ok:  # what the operator saw: the panel's message line, the rig's state, the log's last lines
            spin_failures.append({"message": w.control.message.text(), "state": state(),
                                  "log": [e[3] for e in w.events.entries[-8:]]})
        return ok

    def stopped():
        return wait(lambda: state()[0] in (DrumState.IDLE, DrumState.HOMING) and state()[1] == 0, 15)

    def click_menu(title):
        mb = w.menuBar()
        act = next(a for a in mb.actions() if a.text().replace("&", "") == title)
        p = mb.mapToGlobal(mb.actionGeometry(act).center())
        xdo("mousemove", p.x(), p.y())
        xdo("click", 1)

    # --- a stalled taxel stream: banner, log line, nothing moves, gaps in the plots (the drum turning) ---
    w.tabs.setCurrentWidget(w.live)
    ok = spin()  # (seconds: the live view fills its window meanwhile)
    paints = w.live.paints
    wait(lambda: w.live.paints >= paints + 5, 5)

    def geometry():
        g = {}
        for c in w.findChildren(QtWidgets.QWidget):
            if not c.isVisible() or c.window() is not w or c.objectName().startswith("banner") \
                    or any(p.objectName().startswith("banner") for p in _parents(c)):
                continue
            if isinstance(c, (QtWidgets.QAbstractButton, QtWidgets.QAbstractSpinBox, QtWidgets.QComboBox,
                              QtWidgets.QTabBar, QtWidgets.QLineEdit, QtWidgets.QAbstractScrollArea)):
                p = c.mapTo(w, QtCore.QPoint(0, 0))
                g[f"{type(c).__name__}:{c.objectName() or getattr(c, 'text', lambda: '')()}:{id(c)}"] = \
                    [p.x(), p.y(), c.width(), c.height()]
        return g

    banner = w.banners["taxel"]
    # a host starved on a loaded machine can see the stream stall on its own (the pty hands the frames over late):
    # the banner then says so, rightly; the stall made here starts once that one is over (what it shows is then
    # the stall made here)
    earlier = banner.text if banner.isVisible() else None
    wait(lambda: not banner.isVisible(), 15)
    before = geometry()
    res = {"spinning": ok, "banner_before": banner.isVisible(), "banner_earlier": earlier, "n_widgets": len(before),
           "stall_s": STALL_S}
    n_log = len(w.events.entries)
    t0, wall0 = time.monotonic(), time.time()
    sim_end = sim.clock.now() + STALL_S
    sim.uno.stall(STALL_S)
    stall_end: list[float] = []  # the wall time at which the rig's clock passed the stall's end

    def watch_stall_end():  # (the stall lasts STALL_S of the rig's time: longer on the wall if the world was held)
        while sim.clock.now() < sim_end and time.monotonic() < t0 + 120.0:
            time.sleep(0.01)
        stall_end.append(time.monotonic())

    watcher = threading.Thread(target=watch_stall_end, daemon=True)
    watcher.start()
    res["banner_shown"] = wait(lambda: banner.isVisible() and "stalled" in banner.text, STALL_S)
    res["banner_s"] = time.monotonic() - t0
    res["log_s"] = None
    for e in w.events.entries[n_log:]:
        if "stalled" in e[3]:
            res["log_s"] = e[0] - wall0
            res["log_line"] = e[3]
            break
    res["banner_text"] = banner.text
    res["status_text"] = w.links.taxel.text()
    after = geometry()
    res["moved"] = {k: (before[k], after.get(k)) for k in before if after.get(k) != before[k]}
    shown: dict = {}

    def drawn_after_gap():
        """Frames came again and the live view shows the gap with traces drawn after it (0.2 s of them): what it
        shows then (the traces of one refresh; a fixed pause instead let a starved GUI thread's next refresh scroll
        the gap out of the 2 s window before it was read)."""
        if w.links.health["taxel"].state.value not in ("reconnected", "connected") or not w.live.shown_gaps:
            return False
        shown["gaps"] = [list(g) for g in w.live.shown_gaps]
        shown["segments"] = [len(it.segments) for it in w.live.trace_items]
        shown["first_t"] = [float(it.t[0]) if len(it.t) else 0.0 for it in w.live.trace_items]  # oldest, s before now
        return w.live.shown_gaps[0][0] <= -0.2

    wait(lambda: bool(stall_end), 125.0)  # (the GUI's events go on meanwhile)
    res["stall_wall_s"] = stall_end[0] - t0 if stall_end else None
    res["resumed"] = wait(drawn_after_gap, 20)
    res.update({"gaps": [], "segments": [], "first_t": []}, **shown)
    out["stall"] = res

    # --- one click on STOP with a popup open (the drum turning still from the stall) ---
    w.tabs.setCurrentWidget(w.control)
    for name, opener in (("menu_stop", lambda: click_menu("File")), ("combo_stop", lambda: click(w.control.plate))):
        res = {"spinning": spin()}
        routed = w.stop_guard.routed
        opener()
        wait(lambda: QtWidgets.QApplication.activePopupWidget() is not None, 3)
        popup = QtWidgets.QApplication.activePopupWidget()
        res["popup"] = type(popup).__name__ if popup is not None else None
        t0 = time.monotonic()
        click(w.stop_btn)  # one click
        res["stopped"] = stopped()
        res["stop_s"] = time.monotonic() - t0
        res["routed_by_guard"] = w.stop_guard.routed - routed
        res["popup_after"] = QtWidgets.QApplication.activePopupWidget() is not None
        res["state_after"] = state()
        out[name] = res
        pause(0.5)

    # --- wheel over the speed box: unfocused, then focused ---
    box = w.control.speed
    box.setValue(80.0)
    w.tabs.tabBar().setFocus()
    pause(0.3)
    xdo("mousemove", *centre(box))
    xdo("click", "--repeat", 3, "--delay", 50, 4)  # three notches of the wheel, up
    res = {"unfocused_value": box.value(), "unfocused_has_focus": box.hasFocus()}
    click(box)
    xdo("click", "--repeat", 3, "--delay", 50, 4)
    res["focused_value"] = box.value()
    res["focused_has_focus"] = box.hasFocus()
    out["wheel"] = res
    box.setValue(80.0)
    w.tabs.tabBar().setFocus()

    # --- Esc in a dialog during a run ---
    proto = os.path.join(tmp, "x11_run.toml")
    with open(proto, "w") as f:
        f.write(PROTOCOL)
    tab = w.protocol
    tab.load(proto)
    tab.out_edit.setText(os.path.join(tmp, "x11_run.h5"))
    tab.resume_box.setChecked(False)
    tab.start()
    res = {"running": wait(lambda: tab._current is not None, 60)}
    w._show_shortcuts()
    dlg = next((d for d in open_dialogs() if d.windowTitle() == "Keyboard shortcuts"), None)
    res["dialog_open"] = dlg is not None
    if dlg is not None:
        click(dlg)  # the operator clicks into it (the window manager gives it the focus), then presses Esc
        xdo("key", "Escape")
        res["dialog_closed"] = wait(lambda: not any(d.windowTitle() == "Keyboard shortcuts" for d in open_dialogs()),
                                    5)
    pause(1.0)
    res["running_after"] = tab.running and not tab.stop_event.is_set()
    res["log_aborted"] = "aborted" in w.events.text()
    out["esc_dialog"] = res
    w.emergency_stop()
    wait(lambda: tab._paused, 30)
    tab.request_abort()  # STOP left the run stopped (resumable): end it
    wait(lambda: tab.job is None, 30)
    stopped()
    out["spin_failures"] = spin_failures
    w._close_confirmed = True
    w.close()
    return _write(out_path, out)


def _parents(w):
    p = w.parentWidget()
    while p is not None:
        yield p
        p = p.parentWidget()


def _write(path: str, out: dict) -> int:
    with open(path, "w") as f:
        json.dump(out, f, indent=1, default=str)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], "--fit-only" in sys.argv[2:]))
