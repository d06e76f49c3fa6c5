"""Live view on the simulated rig: taxel traces scroll, the heat map shows the newest readings, and the SA/RA
rasters are drawn from the streaming encoder's spikes (one curve per population). What the view draws is logic: the
in-process rig feeds it (the pty rig's stream reaches the live view in test_gui_x11's stall, test_gui_replay_layout
and the ``rigctl gui --sim`` run below)."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl_gui.events import wait_for

# wall: a real window's live view, and `rigctl gui --sim` run to its screenshot
pytestmark = pytest.mark.realtime


def test_live_traces_heatmap_and_rasters(inprocess_window, qapp):
    window = inprocess_window
    # the Live view is built when first shown, and its encoder runs only while it is shown; shown, its traces start
    # at the connect, as a view built with the window's did
    assert window._live is None and not window.encoder.active
    ring = window.handle.taxels.ring
    assert wait_for(qapp, lambda: ring.total > 0, 10)
    before = ring.total
    window.tabs.setCurrentIndex(window._live_index)
    live = window.live
    assert window.tabs.currentWidget() is live and window.encoder.active
    assert wait_for(qapp, lambda: live.buffer.n_samples > 0, 10)
    assert live.buffer.n_samples >= before  # its first refresh took every frame since the connect
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


def test_quit_after_stops_a_turning_drum_and_exits_with_a_screenshot(tmp_path, gui_home, monkeypatch):
    """``rigctl gui --sim --tab live --run --screenshot PATH --quit-after S`` (the documented screenshot command;
    with ``--stats-out``, what benchmarks/bench_gui.py runs): the drum is turning when the time is up, and the app
    still exits (its close asks "the drum is turning" of a user; the option is that answer), status 0, having
    rendered the main window to PATH; it never started the analysis jobs' fork server (no Analysis tab shown). The
    CLI's command line is taken in process (click's runner: what it hands the app), then the app runs it in a
    process of its own (one app and simulated rig for the CLI's screenshot and the benchmark's exit, which each
    started their own before)."""
    import json
    import os
    import subprocess
    import sys

    from click.testing import CliRunner

    import rigctl_gui.app
    from rigctl.cli import main as cli

    stats, out = tmp_path / "stats.jsonl", tmp_path / "shot.png"
    handed: list[list[str]] = []
    monkeypatch.setattr(rigctl_gui.app, "main", lambda argv: handed.append(argv) or 0)
    res = CliRunner().invoke(cli, ["gui", "--sim", "--tab", "live", "--run", "--screenshot", str(out),
                                   "--quit-after", "12"], env={"QT_QPA_PLATFORM": "offscreen"})
    assert res.exit_code == 0 and len(handed) == 1, res.output
    args = rigctl_gui.app.parse_args(handed[0])
    assert (args.sim, args.run, args.tab, args.screenshot, args.quit_after) == (True, True, "live", str(out), 12.0)
    env = dict(os.environ, QT_QPA_PLATFORM="offscreen", XDG_CONFIG_HOME=str(tmp_path / "config"),
               RIGCTL_CONFIG=str(tmp_path / "rig.json"))  # fresh QSettings: default window size
    cmd = [sys.executable, "-m", "rigctl_gui.app", *handed[0], "--stats-out", str(stats)]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    lines = [json.loads(x) for x in stats.read_text().splitlines()]
    assert any(ln["connected"] and ln["frames"] > 0 for ln in lines)  # it was streaming when asked to quit
    # the analysis jobs' fork server is not started while the Analysis tab is never shown (the app starts it with
    # that tab: test_gui_guards.py)
    assert lines and all(ln["job_server"] is None for ln in lines), [ln["job_server"] for ln in lines]
    from PySide6 import QtGui

    img = QtGui.QImage(str(out))
    # the offscreen screen is 800x800: the window (1400x900 where there is room) fits it
    assert 700 <= img.width() <= 800 and 700 <= img.height() <= 800, img.size()
