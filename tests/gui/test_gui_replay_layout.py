"""The whole app on the simulated rig replaying a non-default sensor: recordings of a 3x3 single-layer sensor at 100 Hz
(generated CSVs, imported with ``rigctl import``) streamed through the simulated taxel board. The live view shows
one 3x3 heat map, 9 traces at 100 Hz and 9-row rasters; the plate list is the session's texture set, and mounting a
plate in the control panel replays that texture's recordings (its own frequency on screen)."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.cli import main
from rigctl_gui.events import wait_for

# wall: the whole app streaming a replay through the taxel board into a real window
pytestmark = pytest.mark.realtime

RATE_HZ = 100
#: texture -> the sine frequency of its recordings (Hz)
TEXTURES = {"Denim": 3.0, "Silk": 0.75}


PROTOCOL = """
name = "finger_replay"
description = "two plates of the replayed finger session"
textures = ["Silk", "Denim"]
speeds_mm_s = [40]
forces_g = [300]
trials_per_condition = 1
duration_s = 1.5
order = "blocked"

[texture_set]
name = "finger"
textures = ["Denim", "Silk"]

[settle]
force_timeout_s = 10
speed_timeout_s = 5
speed_tolerance_mm_s = 3
"""


@pytest.fixture(scope="module")
def finger_session(tmp_path_factory):
    """A session file of 9 channels at 100 Hz, textures Denim and Silk, 8 s per trial (``rigctl import`` from CSV)."""
    d = tmp_path_factory.mktemp("finger")
    rng = np.random.default_rng(3)
    t = np.arange(8 * RATE_HZ) / RATE_HZ
    for tex, f0 in TEXTURES.items():
        for rep in range(2):
            x = (np.linspace(250, 650, 9)[None, :] + 150 * np.sin(2 * np.pi * f0 * t[:, None] + 0.5 * np.arange(9))
                 + rng.normal(0, 4, (len(t), 9)))
            np.savetxt(d / f"{tex}__V40__{rep}.csv", np.rint(x).astype(int), fmt="%d", delimiter=",")
    out = d / "finger.h5"
    files = sorted(str(p) for p in d.glob("*.csv"))
    # the CLI in this process (click's runner): the import is how the file is made, not what is tested here
    res = CliRunner().invoke(main, ["import", *files, "--rate", str(RATE_HZ), "--layout", "3x3x1", "--label-pattern",
                                    "{texture}__V{speed_mm_s}__{rep}.csv", "--out", str(out)])
    assert res.exit_code == 0, res.output[-2000:]
    return out


def _dominant_hz(x: np.ndarray, rate_hz: float) -> float:
    x = x.astype(float) - x.mean()
    f = np.fft.rfftfreq(len(x), 1.0 / rate_hz)
    return float(f[np.argmax(np.abs(np.fft.rfft(x)))])


def test_app_replaying_a_9_channel_100hz_session(qapp, gui_home, finger_session, tmp_path):
    from rigctl.devices.wire import DrumState
    from rigctl_gui.app import MainWindow, configure_pyqtgraph
    from rigctl_gui.workers import RigSource

    configure_pyqtgraph()
    source = RigSource("replay", replay_dir=str(finger_session))
    w = MainWindow(source, autoconnect=False)
    cfg = str(tmp_path / "rig9.json")  # this rig's calibration, not the other GUI tests' 18-taxel one
    w.rig_config_path = lambda: cfg
    w.connect_source(source)
    w.resize(1400, 900)
    w.show()
    try:
        assert wait_for(qapp, lambda: w.handle is not None or "Could not" in w.banner.text, 90), \
            w.banner.text
        assert w.handle is not None, w.banner.text
        assert "session replay" in w.source_label.text()
        live, panel = w.live, w.control
        # the plots follow the stream's layout
        assert (live.sensor_layout.n_channels, live.sensor_layout.sample_rate_hz) == (9, 100.0)
        assert len(live.images) == 1 and live.images[0].image.shape == (3, 3)
        assert len(live.curves) == 9 and len(live.trace_plots) == 1
        assert "(9 trains)" in live.raster_plots["sa"].titleLabel.text
        assert w.encoder.layout.n_channels == 9
        assert len(w.calibration.norm_bars.opts["x"]) == 9
        # the plate list is the session's texture set; mounting Silk replays Silk's recordings
        assert [panel.plate.itemText(i) for i in range(panel.plate.count())] == sorted(TEXTURES)
        w.tabs.setCurrentWidget(live)
        panel.speed.setValue(40.0)
        panel.force.setValue(500.0)
        panel.mount_plate("silk")
        panel.command("run")
        assert wait_for(qapp, lambda: w.poller.latest is not None and w.poller.latest.state == DrumState.RUNNING
                        and w.handle.control.plate == "Silk", 60), (panel.message.text(),
                                                                                  w.poller.latest)
        n0 = live.buffer.n_samples if live.buffer else 0
        assert wait_for(qapp, lambda: live.buffer.n_samples >= n0 + 400, 30), live.info.text()
        assert live.buffer.decimate == 1
        t, x = live.buffer.view()
        t, x = t[-400:], x[-400:]  # 4 s of Silk, every sample streamed after it was mounted
        np.testing.assert_allclose(np.diff(t), 1.0 / RATE_HZ, rtol=1e-9)
        assert _dominant_hz(x[:, 0], RATE_HZ) == pytest.approx(TEXTURES["Silk"], abs=0.3)
        # the heat map shows a recent frame of the stream (it is redrawn every HEATMAP_EVERY refreshes, not every frame)
        shown = live.heatmap_frame
        np.testing.assert_array_equal(live.images[0].image, shown.astype(float).reshape(3, 3))
        assert any(np.array_equal(shown, row) for row in live.buffer.view()[1][-200:])
        # the streaming encoder: spikes on the 9 trains only
        enc = w.encoder
        assert wait_for(qapp, lambda: enc.ready and enc.sa.total > 0, 60), (enc.encoder_error, live.info.text())
        assert enc.sa.since(-1e9)[1].max() <= 8
        # taxel normalisation: a 1 s calibration run of the 9 taxels, shown and fed to the live encoder
        cal = w.calibration
        cal.norm_seconds.setValue(1)
        cal.record_normalisation()
        assert wait_for(qapp, lambda: cal.job is None, 30), cal.status.text()
        assert "stored" in cal.status.text(), cal.status.text()
        heights = cal.norm_bars.opts["height"]
        assert len(heights) == 9 and np.all(heights > 100)  # the recorded sines span ~300 counts
        assert enc.normaliser.n_taxels == 9 and np.all(enc.normaliser.maximum - enc.normaliser.minimum > 100)
        w.emergency_stop()
        # the Protocol tab records the replayed sensor: a session of 9 channels at 100 Hz, the plates' own labels
        proto = tmp_path / "finger_protocol.toml"
        proto.write_text(PROTOCOL)
        tab = w.protocol
        w.tabs.setCurrentWidget(tab)
        tab.load(str(proto))
        assert tab.table.rowCount() == 2, tab.summary.text()
        out = tmp_path / "recorded.h5"
        tab.out_edit.setText(str(out))
        tab.resume_box.setChecked(False)
        tab.start()
        assert wait_for(qapp, lambda: tab.job is None, 120), tab.status.text()
        assert "finished: 2/2" in tab.status.text(), tab.status.text()
        from rigctl.storage.session import open_session

        with open_session(out) as s:
            assert (s.layout.n_channels, s.layout.sample_rate_hz) == (9, 100.0)
            assert list(s.plan["texture"]) == ["Silk", "Denim"]
            for i, tex in enumerate(("Silk", "Denim")):
                tr = s.trial(i)
                assert tr.taxels.shape == (150, 9)  # 1.5 s at 100 Hz
                assert _dominant_hz(tr.taxels[:, 0], RATE_HZ) == pytest.approx(TEXTURES[tex], abs=0.7)
    finally:
        w.close()
        w.deleteLater()
        qapp.processEvents()
