"""The live view, the calibration tab and the control panel follow the sensor description (SensorLayout) and the
rig's texture set: a 3x3 single-layer sensor at 100 Hz, a 4x4 single layer (16 taxels) and the paper's 3x3x2 at
1 kHz, fed with frames directly through the widgets' update path (no rig), plus the real streaming encoder on a
9-channel 100 Hz stream."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from rigctl.core.sensor import PAPER_SENSOR, SensorLayout, parse_layout
from rigctl.core.textures import PAPER_TEXTURES, TextureSet
from rigctl_gui.events import wait_for

FINGER_100HZ = SensorLayout.grid(3, 3, 1, sample_rate_hz=100.0, name="finger 3x3 @ 100 Hz")
GRID_4X4 = parse_layout("4x4", sample_rate_hz=500.0, adc_bits=12)


class FrameRing:
    """The part of :class:`rigctl.devices.ring.RingBuffer` the GUI reads (``total``, ``read_since``), for any
    channel count; frames are appended by the test."""

    def __init__(self, n_channels: int, capacity: int = 100_000):
        self.samples = np.zeros((capacity, n_channels), np.uint16)
        self.host_t = np.zeros(capacity)
        self.total = 0
        self._lock = threading.Lock()

    def write(self, samples: np.ndarray) -> None:
        with self._lock:
            n = len(samples)
            self.samples[self.total : self.total + n] = samples
            self.host_t[self.total : self.total + n] = np.arange(n) * 1e-3
            self.total += n

    def read_since(self, cursor: int, max_frames=None):
        with self._lock:
            total = self.total
            s = slice(int(cursor), total)
            n = total - int(cursor)
            return total, self.samples[s].copy(), np.arange(n, dtype=np.uint16), self.host_t[s].copy()


class FakeStream:
    """A taxel source as the GUI sees it: ``ring`` and ``layout``."""

    def __init__(self, layout: SensorLayout):
        self.layout = layout
        self.ring = FrameRing(layout.n_channels)


def frames(layout: SensorLayout, seconds: float, seed: int = 0) -> np.ndarray:
    """``(n, n_channels)`` uint16 readings: a slow ramp per channel (channel k at level ~ k) plus noise."""
    rng = np.random.default_rng(seed)
    n = int(seconds * layout.sample_rate_hz)
    base = np.linspace(0.1, 0.9, layout.n_channels) * layout.adc_max
    wave = 0.05 * layout.adc_max * np.sin(2 * np.pi * 2.0 * np.arange(n) / layout.sample_rate_hz)[:, None]
    x = base[None, :] + wave + rng.normal(0, 2, (n, layout.n_channels))
    return np.clip(np.rint(x), 0, layout.adc_max).astype(np.uint16)


class FakeEncoder:
    """The part of :class:`gui.workers.LiveEncoder` the live view reads: SA/RA spike rings, ready, error."""

    def __init__(self, n_channels: int, now_s: float):
        from rigctl_gui.workers import SpikeRing

        self.sa, self.ra = SpikeRing(), SpikeRing()
        ch = np.arange(n_channels, dtype=np.int16)
        for ring, dt in ((self.sa, 0.1), (self.ra, 0.3)):
            t = now_s - dt - 0.01 * ch
            ring.extend(t, ch)
        self.ready, self.encoder_error = True, None


@pytest.fixture
def live_view(qapp):
    from rigctl_gui.app import configure_pyqtgraph
    from rigctl_gui.live_view import LiveView

    configure_pyqtgraph()
    views = []

    def make(layout=None):
        v = LiveView() if layout is None else LiveView(layout=layout)
        v.resize(1400, 800)
        v.show()
        qapp.processEvents()
        views.append(v)
        return v

    yield make
    for v in views:
        v.close()
        v.deleteLater()
    qapp.processEvents()


def _feed_and_refresh(qapp, view, layout, seconds=3.0):
    stream = FakeStream(layout)
    x = frames(layout, seconds)
    now_s = (len(x) - 1) / layout.sample_rate_hz
    enc = FakeEncoder(layout.n_channels, now_s)
    view.attach(stream, enc)
    stream.ring.write(x)
    assert view.refresh()
    qapp.processEvents()
    return x, enc


@pytest.mark.parametrize("layout", [FINGER_100HZ, GRID_4X4, PAPER_SENSOR], ids=["3x3@100Hz", "4x4@500Hz", "paper"])
def test_live_view_follows_the_layout(live_view, qapp, layout):
    view = live_view()
    view.set_window(0.5)
    x, _ = _feed_and_refresh(qapp, view, layout)
    n = layout.n_channels
    assert view.sensor_layout == layout
    # one trace plot and one heat map per layer, one curve per taxel
    assert len(view.trace_plots) == layout.n_layers
    assert len(view.images) == layout.n_layers
    assert len(view.curves) == n
    # heat maps: the newest frame, each layer as its rows x cols grid
    for i, la in enumerate(layout.layers):
        ch = layout.layer_channels(i)
        np.testing.assert_array_equal(view.images[i].image, x[-1, ch.start : ch.stop].reshape(la.rows, la.cols))
        assert tuple(view.images[i].levels) == (0, layout.adc_max)
    # traces: every frame of the last window_s seconds (0.5 s of the 3 s fed; fewer samples than pixels: no
    # decimation), x = seconds before now at the layout's rate
    assert view.buffer.decimate == 1
    in_window = int(round(view.window_s * layout.sample_rate_hz)) + 1
    assert in_window <= view.data_width_px()
    for k, c in enumerate(view.curves):
        tx, ty = c.getData()
        assert tx[-1] == 0.0 and tx[0] >= -view.window_s - 1e-9
        np.testing.assert_allclose(np.diff(tx), 1 / layout.sample_rate_hz, rtol=1e-9)
        np.testing.assert_array_equal(ty, x[-in_window:, k])
    # auto-ranged y: each layer's readings inside its plot's y range, which is no wider than needed (+ margins)
    for p, chans in zip(view.trace_plots, view._layer_channels):
        lo, hi = x[-in_window:, chans.start:chans.stop].min(), x[-in_window:, chans.start:chans.stop].max()
        y0, y1 = p.viewRange()[1]
        assert y0 <= lo and hi <= y1 and (y1 - y0) <= 1.3 * (hi - lo) + 0.03 * layout.adc_max
    view.set_auto_range(False)
    for p in view.trace_plots:
        assert p.viewRange()[1] == pytest.approx([0, layout.adc_max])
    view.set_auto_range(True)
    # rasters: n rows, every spike drawn in its taxel's row and its time's pixel column
    for key in ("sa", "ra"):
        p = view.raster_plots[key]
        assert p.viewRange()[1] == pytest.approx([-0.5, n - 0.5])
        assert f"({n} trains)" in p.titleLabel.text
        st, sc = view.drawn[key]
        assert sorted(sc) == list(range(n))
        img = view.raster_images[key].image
        h, w = img.shape
        for t, ch in zip(st, sc):
            col = int((t + view.window_s) / view.window_s * w)
            rows = np.flatnonzero(img[:, col])  # row 0 = bottom (taxel 0)
            assert len(rows) and np.all(np.abs((rows + 0.5) * n / h - 0.5 - ch) <= 0.41), (key, ch, rows)
        assert np.count_nonzero(img.any(axis=0)) == n  # nothing else lit
    assert f"{n} taxels" in view.sensor_label.text()


def test_default_live_view_is_the_papers(live_view, qapp):
    """The paper's rig looks as before: two layers of 3x3, 18 trains, 0-1023 counts, ticks every 3rd taxel."""
    view = live_view()
    assert view.sensor_layout == PAPER_SENSOR
    assert [p.titleLabel.text.split("&nbsp;")[0] for p in view.trace_plots] == [
        "Top layer (type I) taxels 0-8", "Bottom layer (type II) taxels 9-17"]
    assert [p.titleLabel.text for p in view.raster_plots.values()] == [
        "SA spike raster (18 trains)", "RA spike raster (18 trains)"]
    assert [img.image.shape for img in view.images] == [(3, 3), (3, 3)]
    ticks = view.raster_plots["sa"].getAxis("left")._tickLevels[0]
    assert [t for t, _ in ticks] == [0, 3, 6, 9, 12, 15]
    from rigctl_gui.live_view import layer_titles

    assert [layer_titles(PAPER_SENSOR, i)[1] for i in range(2)] == ["Top 3x3 (type I) now", "Bottom 3x3 (type II) now"]


def test_live_view_rebuilds_for_a_new_rig(live_view, qapp):
    """Connecting to another sensor rebuilds the plots; going back gives the paper's view again."""
    view = live_view()
    _feed_and_refresh(qapp, view, FINGER_100HZ)
    assert len(view.images) == 1 and len(view.curves) == 9
    _feed_and_refresh(qapp, view, PAPER_SENSOR)
    assert len(view.images) == 2 and len(view.curves) == 18
    two_4x4 = parse_layout("4x4x2")
    _feed_and_refresh(qapp, view, two_4x4)
    assert [img.image.shape for img in view.images] == [(4, 4), (4, 4)] and len(view.curves) == 32


def test_live_encoder_on_a_9_channel_100hz_stream(qapp):
    """The real streaming encoder on a 9-taxel stream at 100 Hz: 9 SA and 9 RA trains, times in s at 100 Hz."""
    from rigctl_gui.workers import LiveEncoder

    stream = FakeStream(FINGER_100HZ)
    enc = LiveEncoder(stream, poll_s=0.01)
    assert enc.layout == FINGER_100HZ
    assert enc.normaliser.n_taxels == 9 and float(enc.normaliser.maximum.max()) == FINGER_100HZ.adc_max
    enc.start()
    try:
        assert wait_for(qapp, lambda: enc.ready or enc.encoder_error, 120), enc.encoder_error
        assert enc.encoder_error is None
        x = np.zeros((400, 9), np.uint16)
        x[100:] = np.linspace(200, 900, 9).astype(np.uint16)  # a step at 1 s: SA fires on, RA on the onset
        stream.ring.write(x)
        assert wait_for(qapp, lambda: enc.n_samples >= 400 and enc.sa.total > 0 and enc.ra.total > 0, 30), (
            enc.n_samples, enc.sa.total, enc.ra.total, enc.encoder_error)
        assert enc.stream_time_s == pytest.approx(4.0)
        for ring in (enc.sa, enc.ra):
            t, ch = ring.since(-1.0)
            assert ch.min() >= 0 and ch.max() <= 8
            # after the step (less the resampling filter's 100 ms reach, when the encoder resamples the 100 Hz
            # stream to its 1 ms step), within the 4 s fed
            assert t.min() >= 0.9 and t.max() <= 4.0
        assert set(enc.ra.since(-1.0)[1]) == set(range(9))
    finally:
        enc.stop()
        enc.join(10)


def _spikes(enc, t0: float = -1.0) -> dict:
    return {key: sorted(zip(*(a.tolist() for a in ring.since(t0)))) for key, ring in (("sa", enc.sa), ("ra", enc.ra))}


def test_a_paused_live_encoder_reads_nothing_and_catches_up_when_resumed(qapp):
    """``LiveEncoder(active=False)`` / ``set_active``: paused, the encoder reads nothing; resumed, it encodes the
    frames it missed as if it had never paused (the same spikes as an encoder that ran all along); after a pause
    longer than a live view's longest window plus the warm-up it encodes only that much of the newest stream (from
    rest), its spikes at their stream times and, over that window, as many per train as the encoder that ran all
    along drew."""
    from rigctl.operations._live import LIVE_WINDOW_MAX_S, RESUME_WARM_UP_S
    from rigctl_gui.workers import LiveEncoder

    stream = FakeStream(FINGER_100HZ)
    rate = FINGER_100HZ.sample_rate_hz
    steady = LiveEncoder(stream, poll_s=0.01)
    paused = LiveEncoder(stream, poll_s=0.01, active=False)
    steady.start()
    paused.start()
    try:
        assert wait_for(qapp, lambda: steady.ready or steady.encoder_error, 120), steady.encoder_error
        step = np.zeros((400, 9), np.uint16)
        step[100:] = np.linspace(200, 900, 9).astype(np.uint16)
        stream.ring.write(step)
        assert wait_for(qapp, lambda: steady.n_samples == 400, 30)
        wait_for(qapp, lambda: False, 0.2)
        assert paused.n_samples == 0 and paused.sa.total == 0 and not paused.ready and not paused.active
        paused.set_active(True)
        assert wait_for(qapp, lambda: paused.n_samples == 400, 30), paused.encoder_error
        assert _spikes(paused) == _spikes(steady) and _spikes(steady)["ra"]
        # a short pause: the frames missed are encoded on resuming, as if never paused
        paused.set_active(False)
        wait_for(qapp, lambda: False, 0.1)
        stream.ring.write(frames(FINGER_100HZ, 3.0, seed=1))
        assert wait_for(qapp, lambda: steady.n_samples == 700, 30)
        wait_for(qapp, lambda: False, 0.2)
        assert paused.n_samples == 400
        paused.set_active(True)
        assert wait_for(qapp, lambda: paused.n_samples == 700, 30)
        assert _spikes(paused) == _spikes(steady)
        # a long pause (15 s of stream): only the window a view can show and the warm-up before it are encoded
        paused.set_active(False)
        wait_for(qapp, lambda: False, 0.1)
        long = frames(FINGER_100HZ, 15.0, seed=2)
        long[(np.arange(len(long)) // 50) % 2 == 1] -= 100  # a step every 0.5 s: RA fires too
        stream.ring.write(long)
        assert wait_for(qapp, lambda: steady.n_samples == 2200, 30)
        wait_for(qapp, lambda: False, 0.2)
        paused.set_active(True)
        keep = int(round((LIVE_WINDOW_MAX_S + RESUME_WARM_UP_S) * rate))
        assert wait_for(qapp, lambda: paused.n_samples == 700 + keep, 30), paused.n_samples
        wait_for(qapp, lambda: False, 0.2)
        assert paused.n_samples == 700 + keep  # nothing older was read
        start_s = (2200 - keep) / rate
        shown_s = start_s + RESUME_WARM_UP_S  # the oldest time a 10 s window shows
        late = {k: [t for t, _ in v if t > 9.0] for k, v in _spikes(paused).items()}
        assert all(start_s <= min(v) and max(v) <= 22.0 for v in late.values()), late
        # over the window a view shows, each train fires as the encoder's that never paused: the same count within
        # 2 % (+1), also the train near threshold that the never-paused encoder keeps silent (started 0.5 s before the
        # window instead of 2 s, that one fired 20 spikes)
        for key in ("sa", "ra"):
            ours, theirs = (np.bincount([c for _, c in _spikes(e, shown_s)[key]], minlength=9) for e in (paused, steady))
            assert theirs.sum() > 0 and np.all(np.abs(ours - theirs) <= 0.02 * theirs + 1), (key, ours, theirs)
    finally:
        for enc in (steady, paused):
            enc.stop()
            enc.join(10)


class _Main:
    """What the calibration tab asks of the main window."""

    def __init__(self, cfg_path):
        self.cfg_path = str(cfg_path)
        self.encoder = None

    def rig_config_path(self):
        return self.cfg_path


def test_calibration_tab_per_taxel_normalisation_follows_the_layout(qapp, tmp_path):
    from rigctl.acquisition.calibration import update_rig_config
    from rigctl_gui.calibration_tab import CalibrationTab

    cfg = tmp_path / "rig.json"
    tab = CalibrationTab(_Main(cfg))
    # default: the paper's 18 taxels
    assert len(tab.norm_bars.opts["x"]) == 18
    assert tab.norm_plot.getAxis("bottom").labelText == "taxel (0-8 top, 9-17 bottom)"
    tab.set_layout(FINGER_100HZ)
    tab.show_config()
    assert len(tab.norm_bars.opts["x"]) == 9
    assert tab.norm_plot.getAxis("bottom").labelText == "taxel (0-8)"
    assert "full ADC range 0-1023" in tab.norm_info.text()
    # a 9-taxel normalisation is shown and used for the 9-taxel sensor
    lo, hi = np.arange(9) * 10.0, 500 + np.arange(9) * 20.0
    update_rig_config(cfg, taxel_normalisation={"taxel_min": lo.tolist(), "taxel_max": hi.tolist(),
                                                "n_trials": 1, "source": "test"})
    tab.show_config()
    np.testing.assert_array_equal(tab.norm_bars.opts["height"], hi - lo)
    rng = tab.taxel_range()
    assert rng is not None and rng.n_taxels == 9
    # ... and refused for the paper's 18-taxel sensor (not used by the live encoder)
    tab.set_layout(PAPER_SENSOR)
    tab.show_config()
    assert tab.taxel_range() is None
    assert "stored for 9 taxels, but this sensor has 18" in tab.norm_info.text()
    assert len(tab.norm_bars.opts["height"]) == 18
    tab.set_layout(GRID_4X4)
    tab.show_config()
    assert len(tab.norm_bars.opts["x"]) == 16 and "0-4095" in tab.norm_info.text()
    # the load cell's calibration says whether the contact's stiffness is stored (each probe checked against it)
    loadcell = {"counts_per_g": 420.0, "scale_x100": 42000, "mass_g": 500.0, "check_force_g": 500.2}
    update_rig_config(cfg, loadcell=loadcell)
    tab.show_config()
    assert "no contact stiffness stored: the scale is not checked" in tab.loadcell_info.text()
    update_rig_config(cfg, loadcell={**loadcell, "contact_stiffness_g_per_mm": 1234.0})
    tab.show_config()
    assert "contact 1,234 g/mm (each press's probe is checked against it)" in tab.loadcell_info.text()
    tab.deleteLater()


def test_control_panel_offers_the_rigs_texture_set(qapp):
    from rigctl_gui.control_panel import ControlPanel

    panel = ControlPanel()
    assert [panel.plate.itemText(i) for i in range(panel.plate.count())] == list(PAPER_TEXTURES.labels)

    class Commands:
        def __init__(self):
            self.sent = []

        def submit(self, name, fn, *args):
            self.sent.append((name, args[0]))

    class Rig:
        textures = TextureSet([f"{a}{b}{n}" for a, b, n in zip("HBCDEFGHIJKLMNOPQRSTUVWXYZ", "B" * 26, range(26))],
                              name="lab26")

        def mount_plate(self, label, prompt):  # pragma: no cover - not called (queued only)
            pass

    panel.commands, panel.ops = Commands(), Rig()  # the operator layer's RigControl mounts plates
    panel.set_textures(Rig.textures)
    assert panel.plate.count() == 26 and panel.plate.itemText(0) == "HB0"
    panel.mount_plate("hb0")  # the set's spelling
    assert panel.commands.sent == [("mount plate HB0", "HB0")]
    panel.mount_plate("ZZ")
    assert len(panel.commands.sent) == 1 and "not in the texture set" in panel.message.text()
    panel.set_textures(None)  # hardware: any label
    assert panel.plate.isEditable()
    panel.deleteLater()


def test_heat_map_of_a_row_of_taxels_is_a_strip_not_a_line(live_view, qapp):
    """Square taxels for grids up to 4:1 (the paper's 3x3 unchanged); a 1x16 row (FabricSlide) is shown 4:1."""
    from rigctl_gui.live_view import heatmap_aspect

    assert heatmap_aspect(3, 3) == 1.0 and heatmap_aspect(2, 8) == 1.0
    assert heatmap_aspect(1, 16) == pytest.approx(0.25) and heatmap_aspect(16, 1) == pytest.approx(4.0)
    view = live_view(parse_layout("1x16"))
    vb = view.images[0].getViewBox()
    assert vb.state["aspectLocked"] == pytest.approx(0.25)
    qapp.processEvents()
    rect = view.images[0].sceneBoundingRect()  # on screen
    assert rect.width() / rect.height() == pytest.approx(4.0, rel=0.05)
    view = live_view()
    assert [img.getViewBox().state["aspectLocked"] for img in view.images] == [1.0, 1.0]


def test_channel_names_label_the_rasters_and_heat_maps(live_view, qapp):
    """A layout with its own channel names: the raster rows are named, and each heat map's tooltip maps grid
    positions to channels; without names, the rasters keep numbered ticks."""
    names = [f"pad{k}" for k in range(4)]
    layout = SensorLayout.grid(2, 2, 1, channel_names=names)
    view = live_view(layout)
    ticks = view.raster_plots["ra"].getAxis("left")._tickLevels[0]
    assert ticks == list(enumerate(names))
    assert view.images[0].toolTip().splitlines() == ["0: pad0   1: pad1", "2: pad2   3: pad3"]
    assert [c.name() for c in view.curves] == names
    view = live_view(FINGER_100HZ)
    assert view.images[0].toolTip().splitlines()[2] == "6: taxels r2c0   7: taxels r2c1   8: taxels r2c2"
    assert [t for t, _ in view.raster_plots["sa"].getAxis("left")._tickLevels[0]] == [0, 2, 4, 6, 8]


# wall: a real window's live view following a taxel board streaming on a pty
@pytest.mark.realtime
def test_main_window_follows_a_new_sensor_on_the_taxel_link(qapp, gui_home, tmp_path):
    """Another taxel board on the link (the stream's layout and ring change): the live view, its encoder and the
    calibration tab are rebuilt for it; nothing is rebuilt while the sensor stays the same."""
    from rigctl_gui.app import MainWindow, configure_pyqtgraph
    from rigctl_gui.workers import LiveEncoder

    class Control:  # the rig's RigControl as the window reads it: no layout of its own, no stored normalisation
        layout = None
        textures = PAPER_TEXTURES

        def taxel_normalisation(self):
            return None

    class Handle:
        def __init__(self, stream):
            self.taxels, self.control = stream, Control()

        def close(self):
            pass

    configure_pyqtgraph()
    w = MainWindow(autoconnect=False)
    w.rig_config_path = lambda: str(tmp_path / "rig.json")
    stream = FakeStream(PAPER_SENSOR)
    w.handle = Handle(stream)
    w.encoder = LiveEncoder(stream, layout=PAPER_SENSOR)  # not started: only its layout is read
    w.live.attach(stream, w.encoder)
    w.calibration.attach(w.handle)
    try:
        assert not w.follow_sensor()
        first = w.encoder
        stream.layout, stream.ring = FINGER_100HZ, FrameRing(9)  # a 3x3 board at 100 Hz now
        assert w.follow_sensor()
        assert w.encoder is not first and w.encoder.layout == FINGER_100HZ
        assert len(w.live.images) == 1 and len(w.live.curves) == 9 and w.live.buffer.ring is stream.ring
        assert len(w.calibration.norm_bars.opts["x"]) == 9
        assert "3x3" in w.banner.text or "0-8" in w.banner.text
        assert not w.follow_sensor()
    finally:
        w.close()
        w.deleteLater()
        qapp.processEvents()


def test_traces_and_rasters_share_one_time_axis(live_view, qapp):
    """Traces and rasters: the same x range, the same data-area pixels (a spike sits above or below its trace
    sample), and one window setting moves them all."""
    from PySide6 import QtCore

    view = live_view()
    _, enc = _feed_and_refresh(qapp, view, PAPER_SENSOR)

    def pixel_span(p):  # scene x of t = -window and t = 0 in a plot's data area
        vb = p.getViewBox()
        return (vb.mapViewToScene(QtCore.QPointF(-view.window_s, 0)).x(),
                vb.mapViewToScene(QtCore.QPointF(0.0, 0)).x())

    for window in (2.0, 5.0):
        view.set_window(window)
        qapp.processEvents()
        plots = view.time_plots
        assert len(plots) == 4  # two trace plots (layers), SA and RA
        for p in plots:
            assert p.viewRange()[0] == pytest.approx([-window, 0.0])
        spans = [pixel_span(p) for p in plots]
        assert spans[0][1] - spans[0][0] > 600  # a real width on a 1400 px window
        for s in spans[1:]:
            assert s == pytest.approx(spans[0], abs=0.5)
        # the raster images cover exactly the data area, so pixel column j of the image is the same screen column
        # as the traces' time -window + (j + 0.5) * window / width
        for img in view.raster_images.values():
            r = img.mapRectToScene(img.boundingRect())
            assert (r.left(), r.right()) == pytest.approx(spans[0], abs=0.5)
    assert view.window_box.value() == 5.0


def test_raster_draws_every_spike_at_high_rates(live_view, qapp):
    """No spike budget: 18 trains at 400 spikes/s over a 10 s window (72,000 spikes per population) are all drawn,
    the oldest second as well as the newest."""
    from rigctl_gui.workers import SpikeRing, spike_capacity

    view = live_view()
    view.set_window(10.0)
    stream = FakeStream(PAPER_SENSOR)
    x = frames(PAPER_SENSOR, 11.0)
    now = (len(x) - 1) / PAPER_SENSOR.sample_rate_hz
    enc = FakeEncoder(18, now)
    enc.sa = SpikeRing(spike_capacity(PAPER_SENSOR))
    t = np.arange(now - 10.0 + 1e-3, now, 1 / 400.0)
    for ch in range(18):
        enc.sa.extend(t + ch * 1e-4, np.full(len(t), ch, np.int16))
    view.attach(stream, enc)
    stream.ring.write(x)
    assert view.refresh()
    st, sc = view.drawn["sa"]
    assert len(st) == 18 * len(t) > 70_000
    img = view.raster_images["sa"].image
    h, w = img.shape
    lit = img.any(axis=0)
    assert lit[: w // 10].mean() > 0.9 and lit[-w // 10:].mean() > 0.9  # the left (oldest) part is not blank
    for ch in (0, 17):  # each taxel's row is lit across the window
        row = int((ch + 0.5) / 18 * h)
        assert img[row].astype(bool).mean() > 0.9


def test_legend_colour_bar_and_taxel_numbers(live_view, qapp):
    """Each trace plot's title carries its taxels' numbers in their traces' colours; the heat maps share a colour
    bar over 0-adc_max and show every taxel's number in its cell."""
    view = live_view()
    for p, chans in zip(view.trace_plots, view._layer_channels):
        title = p.titleLabel.text
        for ch in chans:
            colour = view.curves[ch].opts["pen"].color().name()
            assert f"color:{colour}'>&#9632;{ch}<" in title
    assert view.colour_bar.values == (0, 1023)
    view.fit_taxel_labels()
    assert all(t.isVisible() for t in view.taxel_labels)  # 1400 x 800: cells of ~40 px
    assert sorted(int(t.textItem.toPlainText()) for t in view.taxel_labels) == list(range(18))
    for t in view.taxel_labels:  # each number inside its own cell of its layer's map
        ch = int(t.textItem.toPlainText())
        layer, r, c = PAPER_SENSOR.channel_position(ch)
        assert t.getViewBox() is view.images[layer].getViewBox()
        assert (int(t.pos().x()), int(t.pos().y())) == (c, r)


def test_peak_decimation_keeps_the_extremes():
    from rigctl_gui.live_view import peak_decimate

    rng = np.random.default_rng(1)
    n, width = 10_000, 700
    t = np.arange(n) / 1000.0
    x = rng.integers(0, 1024, (n, 3)).astype(np.uint16)
    x[4321, 1] = 1023
    x[777, 2] = 0
    dt, dx = peak_decimate(t, x, width, first_index=13)
    step = -(-n // (width // 2))
    assert len(dt) <= width + 2 * step
    assert dx.max(axis=0).tolist() == x.max(axis=0).tolist() and dx.min(axis=0).tolist() == x.min(axis=0).tolist()
    assert dt[-1] == t[-1]  # the newest sample's time is always the last point's
    assert np.all(np.diff(dt) >= 0)
    # bins start at absolute sample numbers that are multiples of the step: scrolling does not shimmer
    idx = np.round(dt * 1000).astype(int) + 13  # absolute sample numbers
    # between the raw partial bins at both ends, each bin is a (min, max) pair at its first and last samples' times
    head = (-13) % step
    tail = (n - head) % step
    pairs = idx[head:len(idx) - tail].reshape(-1, 2)
    assert len(pairs) == (n - head) // step
    assert np.all(pairs[:, 0] % step == 0) and np.all(pairs[:, 1] - pairs[:, 0] == step - 1)
    dt2, dx2 = peak_decimate(t[:700], x[:700], width)
    assert len(dt2) == 700  # at most a sample per pixel: unchanged


def test_a_refused_setpoint_never_moves_apply_press_or_run(qapp):
    """Issue 38 part 8: a refusal under the setpoint boxes pushed Apply/Press/Run down 38 px (a QFormLayout drops a
    hidden row's room); a click meant for Apply hit the message."""
    from rigctl_gui.control_panel import ControlPanel
    from rigctl_gui.events import wait_for

    panel = ControlPanel()
    panel.resize(1024, 640)
    panel.set_enabled(True)
    panel.show()
    wait_for(qapp, lambda: False, 0.1)

    def tops():
        return [w.mapTo(panel, w.rect().topLeft()).y() for w in (panel.apply_btn, panel.buttons["press"],
                                                                    panel.buttons["run"])]

    before = tops()
    panel.speed.setValue(5000.0)
    panel.force.setValue(9000.0)  # two refusal lines
    panel.apply_setpoints()
    wait_for(qapp, lambda: False, 0.1)
    assert panel.setpoint_error.isVisible() and "refused" in panel.setpoint_error.text()
    assert tops() == before
    panel.speed.setValue(80.0)
    panel.force.setValue(500.0)
    wait_for(qapp, lambda: False, 0.1)
    assert not panel.setpoint_error.isVisible() and tops() == before
    panel.close()
    panel.deleteLater()


def test_a_taxel_outage_takes_its_real_width_on_the_live_time_axis(live_view, qapp):
    """Issue 38 part 8: a 3.5 s outage (its frames lost, so no frame numbers) took no width: everything left of it
    was drawn 3.5 s too late. Now the time axis has a 3.5 s gap there, the trace starts 7.5 s back, and SA/RA
    spikes (stream time, as the encoder counts) shift with the traces."""
    from types import SimpleNamespace

    from rigctl.devices.ring import RingBuffer

    layout = FINGER_100HZ
    view = live_view()
    view.set_window(10.0)
    ring = RingBuffer(4000, layout.n_channels)
    enc = FakeEncoder(layout.n_channels, 3.99)  # spikes 0.1 s / 0.3 s before the last frame's stream time
    view.attach(SimpleNamespace(ring=ring, layout=layout), enc)
    x = frames(layout, 4.0)
    n = len(x) // 2
    zeros = np.zeros(n, np.uint16)
    ring.write(x[:n], zeros, zeros.astype(np.uint8), 100.0 + np.arange(n) / layout.sample_rate_hz)
    assert view.refresh()
    after = 100.0 + (n - 1) / layout.sample_rate_hz + 3.5  # the first frame after the outage, host clock
    ring.write(x[n:], zeros, zeros.astype(np.uint8), after + np.arange(n) / layout.sample_rate_hz)
    assert view.refresh()
    qapp.processEvents()
    (where, length), = view.shown_gaps
    assert length == pytest.approx(3.5, abs=0.01)
    assert where == pytest.approx(-(n - 1) / layout.sample_rate_hz, abs=0.02)  # the mark at the first frame after
    oldest = float(view._trace_points[0, 0, 0])
    assert oldest == pytest.approx(-(2 * n - 1) / layout.sample_rate_hz - 3.5 + 1 / layout.sample_rate_hz, abs=0.02)
    st, _ = view.drawn["sa"]
    assert np.allclose(st, -0.1 - 0.01 * np.arange(layout.n_channels))  # after the outage: not shifted
