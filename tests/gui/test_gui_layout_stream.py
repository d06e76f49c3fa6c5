"""End to end over a real pty: a simulated taxel board (VirtualUno) streaming a 3x3 single-layer sensor at 100 Hz,
the host's TaxelStream reading the layout from the board's banner, and the live view with the real streaming encoder
built for that layout (one heat map, 9 traces, 9 raster rows per population, 100 Hz time axis)."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl.core.sensor import SensorLayout
from rigctl_gui.events import wait_for

# wall: a VirtualUno streaming 100 Hz on a pty into a real window's live view
pytestmark = pytest.mark.realtime

FINGER_100HZ = SensorLayout.grid(3, 3, 1, sample_rate_hz=100.0, name="finger 3x3")
STEP = 37  # channel c of frame k reads (k * 3 + c * STEP) % 1024


class StepSource:
    """Board samples for the 9 channels: channel c of frame k (from the board's start) = ``(3k + 37c) % 1024`` (a
    sawtooth per channel: SA fires on the high part, RA on the wrap-around)."""

    def __init__(self):
        self.k = 0

    def __call__(self, n):
        k = self.k + np.arange(n)
        self.k += n
        x = (k[:, None] * 3 + np.arange(9)[None, :] * STEP) % 1024
        return x.astype(np.uint16), None


@pytest.fixture
def finger_board(tmp_path):
    from rigctl.simulation.virtual_uno import VirtualUno

    try:
        board = VirtualUno(tmp_path / "taxel", reset_delay_s=0.1, layout=FINGER_100HZ)
    except TypeError:  # pragma: no cover - before the board took a layout
        pytest.skip("VirtualUno(layout=...) not available")
    board.run_paced(StepSource())
    yield board
    board.close()


def test_live_view_on_a_streamed_9_channel_100hz_sensor(qapp, finger_board):
    from rigctl.devices.taxel_stream import TaxelStream
    from rigctl_gui.app import configure_pyqtgraph
    from rigctl_gui.live_view import LiveView
    from rigctl_gui.workers import LiveEncoder

    configure_pyqtgraph()
    view = LiveView()
    view.resize(1400, 800)
    view.show()
    assert len(view.images) == 2  # the paper's view until a rig is attached
    with TaxelStream(finger_board.path, banner_timeout_s=3) as stream:
        layout = stream.layout
        assert (layout.n_channels, layout.sample_rate_hz, layout.n_layers) == (9, 100.0, 1)
        stream.start()
        enc = LiveEncoder(stream, poll_s=0.02)
        enc.start()
        try:
            view.attach(stream, enc)
            assert len(view.images) == 1 and view.images[0].image.shape == (3, 3)
            assert len(view.curves) == 9 and len(view.trace_plots) == 1
            assert "(9 trains)" in view.raster_plots["sa"].titleLabel.text
            assert wait_for(qapp, lambda: view.refresh() and view.buffer.n_samples >= 150, 20), view.info.text()
            cur = view.buffer.current.astype(int)
            # the frame's 9 channels in their places: one frame's readings differ by STEP per channel
            np.testing.assert_array_equal((cur - cur[0]) % 1024, (np.arange(9) * STEP) % 1024)
            np.testing.assert_array_equal(view.images[0].image, view.heatmap_frame.reshape(3, 3))  # at 10 Hz
            # every frame on screen at 100 Hz (no decimation), x spacing 10 ms
            tx, ty = view.curves[4].getData()
            assert view.buffer.decimate == 1
            np.testing.assert_allclose(np.diff(tx), 0.01, rtol=1e-9)
            assert np.all((np.diff(ty.astype(int)) % 1024) == 3)  # consecutive frames of channel 4, none lost
            # the real encoder: 9 SA and 9 RA trains, drawn in rows 0-8
            assert wait_for(qapp, lambda: enc.ready and enc.sa.total > 0 and enc.ra.total > 0, 60), (
                enc.encoder_error, enc.sa.total, enc.ra.total)
            assert enc.encoder_error is None
            view.refresh()
            for key in ("sa", "ra"):
                _st, drawn_ch = view.drawn[key]
                if len(drawn_ch):
                    assert drawn_ch.min() >= 0 and drawn_ch.max() <= 8
                    assert view.raster_images[key].image.shape[0] > 0
                _t, ch = getattr(enc, key).since(-1e9)
                assert ch.max() <= 8
        finally:
            enc.stop()
            enc.join(10)
            view.detach()
    view.close()
    view.deleteLater()
    qapp.processEvents()
