"""Live view on the simulated rig: taxel traces scroll, the heat map shows the newest readings, and the SA/RA
rasters are drawn from the streaming encoder's spikes (one curve per population)."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl_gui.events import wait_for

pytestmark = pytest.mark.realtime


def test_live_traces_heatmap_and_rasters(window, qapp):
    live = window.live
    window.tabs.setCurrentWidget(live)
    window.control.speed.setValue(100.0)
    window.control.force.setValue(500.0)
    window.control.mount_plate("L")  # a wave texture under the sensor: SA and RA both fire
    window.control.command("run")
    enc = window.encoder
    assert wait_for(qapp, lambda: enc.ready and enc.sa.total > 100 and enc.ra.total > 10, 60), (
        live.info.text(), window.control.message.text(), window.poller.latest)
    p0 = live.paints
    assert wait_for(qapp, lambda: live.paints >= p0 + 10, 10)
    # traces: the last window of every taxel, x = seconds before now
    x, y = live.curves[0].getData()
    assert len(x) > 100 and x[-1] == 0.0 and x[0] >= -live.window_s - 1e-9
    # heat map: the newest readings at its last update (10 Hz), top and bottom layer as 3x3
    cur = live.heatmap_frame.astype(float)
    np.testing.assert_array_equal(live.images[0].image, cur[:9].reshape(3, 3))
    np.testing.assert_array_equal(live.images[1].image, cur[9:].reshape(3, 3))
    # rasters: one image each on the traces' time axis, every spike of the window drawn, taxels 0-17
    for key in ("sa", "ra"):
        st, sc = live.drawn[key]
        assert len(st) > 0 and st.min() >= -live.window_s - 1e-9 and st.max() <= 0.05
        assert sc.min() >= 0 and sc.max() <= 17
        assert live.raster_images[key].image.any()
        assert live.raster_plots[key].viewRange()[0] == live.trace_plots[0].viewRange()[0]
    # frame-to-screen latencies are being measured for the benchmark
    assert live._lat_n > 0
    window.emergency_stop()


def test_quit_after_stops_a_turning_drum_and_exits(tmp_path, gui_home):
    """``--run --quit-after S`` (what benchmarks/bench_gui.py runs): the drum is turning when the time is up, and the
    app still exits (its close asks "the drum is turning" of a user; the option is that answer), status 0."""
    import os
    import subprocess
    import sys

    env = dict(os.environ, QT_QPA_PLATFORM="offscreen", XDG_CONFIG_HOME=str(tmp_path / "config"),
               RIGCTL_CONFIG=str(tmp_path / "rig.json"))
    stats = tmp_path / "stats.jsonl"
    cmd = [sys.executable, "-m", "rigctl_gui.app", "--sim", "--tab", "live", "--run", "--stats-out", str(stats),
           "--quit-after", "12"]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    import json

    lines = [json.loads(x) for x in stats.read_text().splitlines()]
    assert any(ln["connected"] and ln["frames"] > 0 for ln in lines)  # it was streaming when asked to quit


def test_cli_screenshot_of_the_running_app(tmp_path, gui_home):
    """``rigctl gui --screenshot PATH --quit-after S`` renders the main window on the simulated rig and exits."""
    import os
    import subprocess
    import sys

    out = tmp_path / "shot.png"
    env = dict(os.environ, QT_QPA_PLATFORM="offscreen", XDG_CONFIG_HOME=str(tmp_path / "config"),
               RIGCTL_CONFIG=str(tmp_path / "rig.json"))  # fresh QSettings: default window size
    cmd = [sys.executable, "-c", "from rigctl.cli import main; main()", "gui", "--tab", "control",
           "--screenshot", str(out), "--quit-after", "6"]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr[-2000:]
    from PySide6 import QtGui

    img = QtGui.QImage(str(out))
    # the offscreen screen is 800x800: the window (1400x900 where there is room) fits it
    assert 700 <= img.width() <= 800 and 700 <= img.height() <= 800, img.size()
