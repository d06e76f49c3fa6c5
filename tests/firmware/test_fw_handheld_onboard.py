"""The handheld real-time path with the encoder on the finger's board (issue 37, item 7): ``--handheld --hil
--onboard-encoder`` runs the simulated operator's passes on the Uno encoder image under simavr through the rig's owner
(:class:`rigctl.operations.RigControl`) and the run engine (:class:`rigctl.operations.ProtocolRun`); each scan is
classified from the board's counts frame, and the trial keeps the board's spikes, counts, applied speeds and flags
(no raw taxels). Held against the host's integer kernel (``ScanEncoder(kernel="fixed")``, ``FixedSAEncoder``) on
the readings the board's ADC converted and the speeds the board applied: every spike and all 180 features equal.
The scan's extent and the windows held are judged against the host's lateness it measured (:class:`rigctl.simulation
.hil_finger.PlayedScan`): a starved host sends ENCODE, SPEED and STOP late, and only that may stretch or hold them.
"""

from __future__ import annotations

import numpy as np
import pytest

from rigctl.acquisition.builtin import find_protocol
from rigctl.acquisition.protocol import load_protocol
from rigctl.acquisition.runner import run_protocol
from rigctl.core.normalisation import TaxelRange
from rigctl.devices import wire
from rigctl.devices.onboard_finger import POLL_S, WINDOW_SAMPLES
from rigctl.encoding.features import counted_realtime_features
from rigctl.encoding.fixed_sa import FixedSAEncoder
from rigctl.encoding.params import EncodeParams
from rigctl.encoding.pipeline import encode_session
from rigctl.encoding.realtime import ScanEncoder
from rigctl.operations import ProtocolRun, RigSource, ScanClassifier, open_control
from rigctl.operations._control import rig_of
from rigctl.rigs import board_range, open_rig
from rigctl.storage.session import open_session
from rigctl.storage.validate import usable_trials

from ..conftest import small_handheld_protocol

pytestmark = pytest.mark.hil

#: the host's own period: it polls every POLL_S and each read waits up to the port's timeout (HilFingerScans: 20 ms)
HOST_PERIOD_S = POLL_S + 0.02
#: a command is measurably late when the host's view had got this far past its cue, or it wrote this long after the
#: read that cued it: twice the host's period
LATE_S = 2 * HOST_PERIOD_S


def _judge_extent(p, o, attrs, what: str) -> None:
    """The board encoded the used part of the scan from the finger's entry, as the host's cut starts it (issue 78
    item 4): its first sample is the first at or after the interpolated entry, out of its ring of ARM's samples,
    unless the host's ENCODE came later than the ring reaches back (the host's own view of the pass then, past the
    entry); to the exit (+0.15 s), widened by how late the host measured itself to be beyond its own period at STOP
    (its view past the exit plus the time from its read to the write)."""
    t0 = p.first_row / 1000.0  # the board's first sample on the pass's clock
    assert attrs["trial_time_origin_s"] == pytest.approx(t0)
    assert p.first_row == p.arm_row + p.from_sample + attrs["onboard_late_start_samples"]
    late_view_ms = (p.encode_view_s - attrs["scan_enter_s"]) * 1000.0
    if attrs["onboard_late_start_samples"] == 0:
        assert 0.0 <= t0 - attrs["scan_enter_s"] < 0.001 + 1e-9, what
    else:  # the ring no longer held the entry: the host's ENCODE came more than its reach after it
        assert late_view_ms > wire.ENC_RING_MAX_BACK - 1, f"{what}; host's view at ENCODE {late_view_ms:.1f} ms"
    print(f"entry at row {attrs['scan_enter_s'] * 1000:.2f}, first encoded row {p.first_row} (ARM's {p.arm_row}), "
          f"host's view at ENCODE {late_view_ms:.1f} ms past the entry")
    seen, write_s = p.stop_sent
    late_stop = max(0.0, t0 + seen / 1000.0 - attrs["scan_leave_s"] - HOST_PERIOD_S) + max(0.0, write_s - HOST_PERIOD_S)
    extra = o.samples / 1000.0 - (attrs["scan_leave_s"] - t0)
    assert -0.002 < extra < 0.15 + late_stop, f"{what}; host late at STOP {late_stop:.3f} s"


def _judge_held(p, held: list[int], what: str) -> None:
    """Each window the board held (its speed came after the board began the next window but one) was the host's
    lateness: it sent that window's SPEED measurably late (:data:`LATE_S`) after the window ended (sample
    WINDOW_SAMPLES * (w + 1), its cue)."""
    for w in held:
        seen, write_s = p.speeds_sent[w] if w < len(p.speeds_sent) else p.stop_sent
        lag_s = (seen - WINDOW_SAMPLES * (w + 1)) / 1000.0
        assert lag_s >= LATE_S or write_s >= LATE_S, \
            f"window {w} held, though the host sent its speed {lag_s:.3f} s after the window ended, " \
            f"{write_s:.3f} s after its read: {what}"


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A calibration block of plates B and L (10 scans, host-encoded) on the simulated operator: the training block."""
    tmp = tmp_path_factory.mktemp("hh_onboard")
    proto = load_protocol(find_protocol("handheld_calibration"))
    proto = type(proto)(**{**proto.__dict__, "textures": ("B", "L"), "trials_per_condition": 1})
    with open_rig("handheld", seed=4, host_config_path=tmp / "rig.json") as rig:
        assert run_protocol(proto, tmp / "cal.h5", rig=rig).ok
    enc = encode_session(tmp / "cal.h5", tmp / "cal.enc.h5", variants=["realtime_speed_scaled"])
    (tmp / "small.toml").write_text(small_handheld_protocol("B", "L"))
    return tmp, enc


def test_a_realtime_run_encoded_on_the_simulated_finger_board(fw_build, trained):
    tmp, enc = trained
    clf = ScanClassifier(enc, n_pcs=5)
    source = RigSource.from_flags(handheld=True, hil=True, onboard_encoder=str(enc))
    assert source.hil_finger and source.onboard_encoder == str(enc)
    with open_control(source, seed=5, host_config_path=tmp / "rig.json") as control:
        summary = ProtocolRun(control, load_protocol(tmp / "small.toml"), tmp / "rt.h5", on_trial=clf.on_trial).run()
        played = list(rig_of(control).source.played)  # type: ignore[attr-defined]  # HilFingerScans
    assert summary.ok, summary.lines()
    assert len(clf.predictions) == 4 == len(played)
    assert {p.predicted for p in clf.predictions} <= {"B", "L"}
    print("on-board predictions:", [p.line() for p in clf.predictions])
    board = board_range(enc)
    rng = TaxelRange(board.taxel_min.astype(np.float64), board.taxel_max.astype(np.float64))
    with open_session(tmp / "rt.h5") as s:
        report = usable_trials(s)
        assert not report.excluded and report.ids == s.completed_ids()  # 0 taxel frames, not damaged
        for tid, p, pred in zip(s.completed_ids(), played, clf.predictions):
            d = s.trial(tid)
            o = d.onboard
            assert o is not None and d.n_samples == 0 and d.attrs["encoded_on_board"]
            what = (f"scan {tid}: {o.samples} samples encoded from row {p.first_row}, scan {d.attrs['scan_duration_s']:.3f} "
                    f"s, {o.speeds_mm_s.size} speeds, held {o.held_windows.tolist()}, dropped {o.dropped_samples}")
            print(what)
            # the board encoded the whole used part: its samples span the scan between the boundaries (+-0.15 s and
            # the host's measured lateness)
            _judge_extent(p, o, d.attrs, what)
            assert o.dropped_samples == 0 and o.samples == p.samples, what
            assert o.speeds_mm_s.size == -(-o.samples // 100)
            _judge_held(p, o.held_windows.tolist(), what)
            x = p.encoded()
            assert x.shape == (o.samples, wire.ENC_N_TAXELS)
            # every spike the board sent (stored per taxel) is the host integer kernel's on the same readings
            host = FixedSAEncoder(rng, k_sa=float(board.k)).process(x)
            for i in range(wire.ENC_N_TAXELS):
                assert np.array_equal(np.rint(host.train(0, i) * 1000.0).astype(np.int64),
                                      np.rint(o.spike_times_s(i) * 1000.0).astype(np.int64)), f"taxel {i}"
            assert o.spike_sample.size > 100
            # the classifier's features: the board's counts frame and applied speeds = the live host path's with the
            # integer kernel on the same readings and a velocity trace of the same window speeds
            live = ScanEncoder(rng, EncodeParams(), taxels=list(range(wire.ENC_N_TAXELS)), kernel="fixed")
            live.feed(x)
            edges = np.arange(o.speeds_mm_s.size) * 0.1
            live.feed_speed(np.stack([edges + 1e-6, edges + 0.1 - 1e-6], axis=1).ravel(), np.repeat(o.speeds_mm_s, 2))
            feats = counted_realtime_features(o.counts, o.speeds_mm_s)
            assert feats.shape == (180,) and feats.sum() > 0
            assert np.array_equal(feats, live.features()["realtime_speed_scaled"])
            assert np.array_equal(clf.features(d), feats)
            assert clf.model.predict(feats)[0] == pred.predicted  # the prediction is the stored record's
