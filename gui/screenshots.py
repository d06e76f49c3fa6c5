"""Take the documentation screenshots from the real app: ``python -m rigctl_gui.screenshots docs/screenshots``.

Run it under an X server (``xvfb-run -a -s "-screen 0 1600x1000x24" python -m rigctl_gui.screenshots docs/screenshots``).
It opens the main window on the simulated rig and drives each tab the way an experimenter would (mount a plate and
run the drum, record a short protocol, analyse a small generated dataset, calibrate the load cell, classify trials
with the trained model), saving one PNG per tab: control.png, live.png, protocol.png, analysis.png,
analysis_table1.png, analysis_confusion.png, calibration.png, classify.png; then stopped.png (a run stopped by STOP,
resumable), pressed.png (the Rig control tab after an e-stop while pressing 500 g: the drivers off, the sensor still
pressed), fault.png (the latched-fault dialog over it, the whole screen) and handheld.png (the handheld
tab in a real-time block, stopped by STOP; ``python -m rigctl_gui.screenshots OUT_DIR handheld`` takes it alone, without the drum rig).
``--scale 1.5`` takes them at Qt's scale factor 1.5 (``QT_SCALE_FACTOR``; each ``--size`` is then the screen's pixels,
the window 1/1.5 of it in Qt's), ``--palette dark`` with a dark desktop palette
(:func:`rigctl_gui.colours.dark_palette`). ``python -m rigctl_gui.screenshots OUT_DIR live calibration`` takes only
the rig-side shots (control.png, calibration.png, live.png, stopped.png, fault.png: about a minute instead of
several); ``--size 1280x800``
sets the window's size (default 1400x900); more ``--size`` options take every shot at each size in the same session
(the first size's PNGs in OUT_DIR, the others' in OUT_DIR/WxH/).
"""

from __future__ import annotations

import os
import sys
import tempfile
import time

from PySide6 import QtWidgets

from rigctl_gui.events import wait_for

QUICK = """
name = "screenshot_demo"
description = "four textures, two speeds, short trials"
textures = ["A", "B", "G", "L"]
speeds_mm_s = [60, 120]
forces_g = [500]
trials_per_condition = 2
duration_s = 1.0
"""

DATASET = """
name = "screenshot_dataset"
textures = ["A", "B", "C", "G", "H", "L", "M", "N"]
speeds_mm_s = [40, 80, 120]
forces_g = [250, 500, 1000]
trials_per_condition = 3
duration_s = 1.0
"""


def main(out_dir: str, only: list[str] | None = None, size: tuple[int, int] = (1400, 900),
         more_sizes: list[tuple[int, int]] | None = None, *, scale: float = 1.0, palette: str = "") -> int:
    """Save the screenshots into ``out_dir``; ``only`` = a subset of the shot names (without ``.png``; the
    rig-side ones control, calibration, live need no dataset) or None for all; ``size`` = the window's
    (width, height) in screen pixels; ``more_sizes``: each shot is also taken at these sizes, into ``out_dir/WxH/``
    (width, height) in pixels. ``scale``: Qt's scale factor (``QT_SCALE_FACTOR``, set before the app starts: the
    window is ``size / scale`` of Qt's pixels, the PNG ``size`` screen pixels); ``palette``: ``"dark"`` gives the
    app :func:`rigctl_gui.colours.dark_palette` (a dark desktop theme), else the style's own."""
    os.makedirs(out_dir, exist_ok=True)
    tmp = tempfile.mkdtemp(prefix="rigctl-shots-")
    os.environ.setdefault("RIGCTL_CONFIG", os.path.join(tmp, "rig.json"))
    if scale != 1.0:
        os.environ["QT_SCALE_FACTOR"] = f"{scale:g}"
    from PySide6 import QtCore

    QtCore.QSettings.setPath(QtCore.QSettings.Format.IniFormat, QtCore.QSettings.Scope.UserScope, os.path.join(tmp, "settings"))
    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication(sys.argv[:1])
    if palette == "dark":
        from rigctl_gui.colours import dark_palette

        QtWidgets.QApplication.setStyle("Fusion")
        QtWidgets.QApplication.setPalette(dark_palette())
    from rigctl_gui.app import MainWindow, configure_pyqtgraph
    from rigctl_gui.workers import RigSource

    configure_pyqtgraph()
    # the shots show the views, not the dead man's switch: a machine busy with other work can starve this GUI
    # thread for over the app's 0.5 s and stop the drum mid-shot (the tests' windows do the same)
    MainWindow.deadman_s = 5.0
    w = MainWindow(RigSource("sim"))
    size, more_sizes = _logical(size, scale), [_logical(s, scale) for s in more_sizes or []]
    w.resize(*size)
    w.show()

    def wait(pred, timeout_s):
        return wait_for(app, pred, timeout_s)

    def shot(name):
        if only and name[:-4] not in only:
            return
        more = more_sizes or []
        for i, (wd, ht) in enumerate([size, *more]):
            w.resize(wd, ht)
            for _ in range(8 if i or more else 5):  # a resized window redraws first
                app.processEvents()
                time.sleep(0.05)
            folder = out_dir if i == 0 else os.path.join(out_dir, "{}x{}".format(*_screen((wd, ht), scale)))
            os.makedirs(folder, exist_ok=True)
            path = os.path.join(folder, name)
            w.grab().save(path)
            print("saved", path, f"({w.width()}x{w.height()})")
        w.resize(*size)

    if only and set(only) <= {"handheld"}:  # the handheld rig needs no drum rig: its shot alone
        handheld_shots(w, app, shot, tmp)
        w._close_confirmed = True
        w.close()
        return 0
    assert wait(lambda: w.handle is not None, 60), w.banner.text
    # calibration first (the drum must be released for TARE)
    w.tabs.setCurrentWidget(w.calibration)
    w.calibration.mass.setValue(500)
    w.calibration.calibrate_loadcell()
    wait(lambda: w.calibration.job is None, 60)
    # rig control: wave plate L at 80 mm/s, 500 g
    w.tabs.setCurrentWidget(w.control)
    w.control.speed.setValue(80)
    w.control.force.setValue(500)
    w.control.mount_plate("G")
    w.control.command("run")
    wait(lambda: False, 12)
    shot("control.png")
    # calibration: a 5 s taxel normalisation capture while the drum runs
    w.tabs.setCurrentWidget(w.calibration)
    w.calibration.norm_seconds.setValue(5)
    w.calibration.record_normalisation()
    wait(lambda: w.calibration.job is None, 30)
    shot("calibration.png")
    # live view
    w.tabs.setCurrentWidget(w.live)
    wait(lambda: False, 6)
    shot("live.png")
    w.emergency_stop()
    if only and not set(only) - {"control", "calibration", "live", *SAFETY_SHOTS}:
        safety_shots(w, app, out_dir, tmp, only)
        w._close_confirmed = True
        w.close()
        return 0
    # analysis on a small generated dataset (also trains the model for the real-time view)
    from rigctl.acquisition.protocol import parse_protocol
    from rigctl.simulation.dataset import generate_dataset

    ds = os.path.join(tmp, "dataset.h5")
    generate_dataset(parse_protocol(DATASET), ds, workers=1, progress=None)
    a = w.analysis
    w.tabs.setCurrentWidget(a)
    a.open(ds)
    area = w.tabs.area(w.tabs.indexOf(a))
    if area is not None:  # a tab too narrow (1.5x on 1024x700) shows its views, scrolled to them as a user would
        bar = area.horizontalScrollBar()
        bar.rangeChanged.connect(lambda _lo, hi: bar.setValue(hi))
    a.repeats.setValue(3)
    a.n_pcs.setValue(30)
    a.run_analyses()
    wait(lambda: a.job is None, 600)
    a.trials.selectRow(40)
    wait(lambda: a._trial_job is None, 60)
    a.views.setCurrentIndex(1)
    shot("analysis.png")
    a.views.setCurrentIndex(2)
    shot("analysis_table1.png")
    a.views.setCurrentIndex(3)
    shot("analysis_confusion.png")
    a.views.setCurrentIndex(0)
    shot("analysis_trial.png")
    a.model_variant.setCurrentText("speed_scaled")
    a.train_model()
    wait(lambda: a.job is None, 300)
    # protocol: record a short protocol; the real-time view classifies each finished trial
    p = w.protocol
    proto = os.path.join(tmp, "screenshot_demo.toml")
    with open(proto, "w") as f:
        f.write(QUICK)
    w.tabs.setCurrentWidget(p)
    p.load(proto)
    p.out_edit.setText(os.path.join(tmp, "demo.h5"))
    p.start()
    wait(lambda: len(p._done_ids) >= 5, 300)
    shot("protocol.png")
    wait(lambda: p.job is None, 300)
    w.tabs.setCurrentWidget(w.classify)
    wait(lambda: not w.classify._pending and w.classify._job is None, 120)
    shot("classify.png")
    safety_shots(w, app, out_dir, tmp, only)
    handheld_shots(w, app, shot, tmp)
    w._close_confirmed = True
    w.close()
    return 0


def handheld_shots(w, app, shot, tmp: str) -> None:
    """handheld.png: the handheld tab in the middle of a real-time block on the simulated operator, stopped by the
    main STOP (the operator told to lift the finger; the predictions so far), with a classifier trained on a training
    block (2 scans per texture and profile, recorded and encoded here) and calibrated on the calibration block the
    tab records (1 per texture and profile)."""
    from rigctl.acquisition.builtin import find_protocol
    from rigctl.acquisition.protocol import load_protocol
    from rigctl.encoding.pipeline import encode_session
    from rigctl.operations import ProtocolRun, RigSource, open_control

    def wait(pred, timeout_s):
        return wait_for(app, pred, timeout_s)

    training = os.path.join(tmp, "handheld_training.h5")
    proto = load_protocol(find_protocol("handheld_training"))
    with open_control(RigSource("handheld"), seed=11) as control:
        ProtocolRun(control, type(proto)(**{**proto.__dict__, "trials_per_condition": 2}), training).run()
    enc = str(encode_session(training, training.removesuffix(".h5") + ".enc.h5",
                             variants=["realtime_original", "realtime_speed_scaled"]))
    tab = w.handheld
    w.tabs.setCurrentWidget(tab)
    tab.training.setText(enc)
    tab.per_condition.setValue(1)
    tab.out_dir.setText(tmp)
    tab.open_rig()
    wait(lambda: tab.control is not None, 60)
    tab.start_block("calibration")
    wait(lambda: tab.calibration_enc is not None, 300)
    tab.start_block("realtime")
    wait(lambda: len(tab.board.results) >= 12, 300)
    w.emergency_stop()  # the main STOP: the block pauses, the operator is told to lift the finger
    wait(lambda: tab.run is None or (tab.run.state == "paused" and tab.cue.property("cue") == "stop"), 60)
    wait(lambda: False, 0.5)
    shot("handheld.png")
    if tab.run is not None:
        tab.resume()
    wait(lambda: tab.run is None and tab.job is None, 300)


#: the shots of :func:`safety_shots`
SAFETY_SHOTS = ("stopped", "fault", "pressed")


def safety_shots(w, app, out_dir: str, tmp: str, only: list[str] | None = None) -> None:
    """stopped.png: a protocol run stopped by STOP (resumable: the run strip and the protocol tab say so);
    fault.png: the whole screen with the latched-fault dialog over the window after the e-stop was pressed and
    released (the dialog is a window of its own, so the screen is grabbed), a reason typed in."""
    from PySide6 import QtGui

    def wait(pred, timeout_s):
        return wait_for(app, pred, timeout_s)

    def save(name, pixmap):
        if only and name not in only:
            return
        path = os.path.join(out_dir, f"{name}.png")
        pixmap.save(path)
        print("saved", path, f"({pixmap.width()}x{pixmap.height()})")

    p = w.protocol
    for banner in ("app", "fault"):  # what earlier shots left (a loaded machine's dead man's switch, a fault)
        w.banners[banner].hide()
    proto = os.path.join(tmp, "screenshot_stop.toml")
    with open(proto, "w") as f:
        f.write(QUICK)
    w.tabs.setCurrentWidget(p)
    p.load(proto)
    p.out_edit.setText(os.path.join(tmp, "stopped.h5"))
    p.resume_box.setChecked(False)
    p.start()
    wait(lambda: len(p._done_ids) >= 3 and p._current is not None, 300)
    w.emergency_stop()
    wait(lambda: p._paused and p.stopped_reason is not None, 60)
    wait(lambda: False, 1.0)
    save("stopped", w.grab())
    p.request_abort()
    wait(lambda: p.job is None, 60)
    from rigctl.core.faults import parse_fault

    bench = w.handle.control.bench  # the simulated bench's hand: the e-stop pressed for 2 s of the rig's clock
    assert bench is not None, "the screenshots need a simulated rig"
    w.fit_to_screen()  # the screen is grabbed: the whole window on it, its title bar too (as a desktop places it)
    # the sensor pressed (500 g) when the e-stop is pressed: the drivers go off where they stand, the sensor stays
    # pressed, and the window says so (pressed.png: the Rig control tab; fault.png: the dialog over it)
    w.tabs.setCurrentWidget(w.control)
    w.control.force.setValue(500.0)
    w.control.command("press")
    wait(lambda: w.poller.latest is not None and int(w.poller.latest.state) == 3, 60)  # FORCE_SETTLED
    bench.inject_faults([parse_fault("estop@0+2")])
    wait(lambda: w.fault_dialog is not None, 10)
    dlg = w.fault_dialog
    if dlg is not None:
        dlg.later_btn.click()  # Later: the window itself first
    wait(lambda: "pressing" in w.control.state_label.text(), 10)
    wait(lambda: False, 1.0)
    save("pressed", w.grab())
    dlg = w.open_fault_dialog()
    wait(lambda: dlg is not None and dlg.estop.text() == "released", 10)
    if dlg is not None:
        dlg.reason.setText("pressed to check a loose plate; plate G fastened again")
        dlg.move(w.geometry().center() - dlg.rect().center())
    wait(lambda: False, 1.0)
    save("fault", QtGui.QGuiApplication.primaryScreen().grabWindow(0))
    if dlg is not None:  # acknowledged, as the operator would: the shots after it show no latched fault
        dlg.acknowledge()
        wait(lambda: w.fault_dialog is None and not w.banners["fault"].isVisible(), 20)
    w.control.command("home")  # acknowledging is not starting: the sensor is released by a start (HOME)
    wait(lambda: w.poller.latest is not None and w.poller.latest.force_g < 20, 60)


def _logical(size: tuple[int, int], scale: float) -> tuple[int, int]:
    """A window of ``size`` screen pixels in Qt's pixels at ``scale``."""
    return round(size[0] / scale), round(size[1] / scale)


def _screen(size: tuple[int, int], scale: float) -> tuple[int, int]:
    """A window of ``size`` Qt pixels in screen pixels at ``scale`` (the folder's name: what was asked)."""
    return round(size[0] * scale), round(size[1] * scale)


def _cli(argv: list[str]) -> int:
    """``OUT_DIR [NAME ...] [--size WxH ...] [--scale F] [--palette dark]``."""
    opts = {"--scale": "1", "--palette": ""}
    for name in opts:
        if name in argv:
            i = argv.index(name)
            opts[name] = argv[i + 1]
            argv = argv[:i] + argv[i + 2:]
    sizes = []
    while "--size" in argv:
        i = argv.index("--size")
        width, height = (int(v) for v in argv[i + 1].lower().split("x"))
        sizes.append((width, height))
        argv = argv[:i] + argv[i + 2:]
    sizes = sizes or [(1400, 900)]
    return main(argv[0] if argv else "docs/screenshots", argv[1:] or None, size=sizes[0], more_sizes=sizes[1:],
                scale=float(opts["--scale"]), palette=opts["--palette"])


if __name__ == "__main__":
    sys.exit(_cli(sys.argv[1:]))
