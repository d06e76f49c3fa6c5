"""The link health model (rigctl.acquisition.link_health): pure, fed made-up observations."""

from __future__ import annotations

import pytest

from rigctl.acquisition.link_health import LinkHealth, LinkState, dropped_frames_severity


def _feed(h: LinkHealth, seq):
    """Observations (t, connected, progress[, heartbeat]) -> the states of the events returned."""
    out = []
    for obs in seq:
        t, connected, progress, *hb = obs
        ev = h.observe(t, connected=connected, progress=progress, heartbeat=hb[0] if hb else None)
        if ev is not None:
            assert ev.time_s == t and ev.board == h.board and ev.text
            out.append(ev.state)
    return out


def test_a_streaming_link_that_pauses_stalls_then_reconnects_then_settles():
    h = LinkHealth("taxel board", stall_after_s=1.0, settle_s=5.0)
    frames = [(0.1 * i, True, 100 * i) for i in range(10)]  # streaming, 1 s
    paused = [(1.0 + 0.1 * i, True, 900) for i in range(1, 60)]  # 6 s without a frame, port open
    back = [(7.0 + 0.1 * i, True, 1000 + 100 * i) for i in range(1, 70)]
    states = _feed(h, frames + paused + back)
    assert states == [LinkState.CONNECTED, LinkState.STALLED, LinkState.RECONNECTED, LinkState.CONNECTED]
    # stalled exactly when 1 s passed without a frame (the last frame count changed at t=0.9)
    h2 = LinkHealth("taxel board", stall_after_s=1.0)
    _feed(h2, frames)
    assert h2.observe(1.85, connected=True, progress=900) is None
    ev = h2.observe(1.95, connected=True, progress=900)
    assert ev is not None and ev.state == LinkState.STALLED and "1 s" in ev.text


def test_a_lost_link_is_lost_until_something_arrives_again():
    h = LinkHealth("drum controller", stall_after_s=2.0, settle_s=1.0)
    assert _feed(h, [(0, True, 1), (0.1, True, 2), (0.2, False, 2), (0.7, False, 2)]) == \
        [LinkState.CONNECTED, LinkState.LOST]
    assert h.observe(0.8, connected=True, progress=2) is None  # the port is back, no answer yet
    assert h.state == LinkState.LOST
    assert h.observe(0.9, connected=True, progress=3).state == LinkState.RECONNECTED
    assert h.observe(1.5, connected=True, progress=9) is None  # held for settle_s
    assert h.observe(2.0, connected=True, progress=14).state == LinkState.CONNECTED
    assert h.observe(2.1, connected=None).state == LinkState.NOT_CONNECTED


def test_a_controller_reset_is_told_from_a_heartbeat_wrap():
    h = LinkHealth("drum controller", stall_after_s=2.0, settle_s=1.0)
    # the heartbeat wraps at 65536 while polled at 10 Hz: no reset
    seq = [(0.1 * i, True, i, (65500 + 10 * i) % 65536) for i in range(20)]
    assert _feed(h, seq) == [LinkState.CONNECTED]
    # it restarts from 0 (a reset): that is a reset even though the link never went down
    ev = h.observe(2.0, connected=True, progress=20, heartbeat=3)
    assert ev is not None and ev.state == LinkState.CONTROLLER_RESET and "homing" in ev.text
    assert ev.state.is_problem
    assert h.observe(2.1, connected=True, progress=21, heartbeat=13) is None
    assert h.observe(3.2, connected=True, progress=32, heartbeat=123).state == LinkState.CONNECTED


def test_bad_parameters_are_refused():
    with pytest.raises(ValueError):
        LinkHealth("x", stall_after_s=0)


def test_dropped_frames_are_graded_against_the_protocols_threshold():
    assert dropped_frames_severity(0, 0) == "ok"
    assert dropped_frames_severity(5385, 0) == "bad"
    assert dropped_frames_severity(3, 5) == "warn"
    assert dropped_frames_severity(6, 5) == "bad"
    assert dropped_frames_severity(2, None) == "warn"
