"""The composition root rigctl.rigs.open_rig: refusals in one line, and a replay rig opened on a session file
recorded in-process: the rig takes the session's texture set and sensor layout and records trials from it."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl.acquisition.protocol import parse_protocol
from rigctl.acquisition.rig import RigError
from rigctl.acquisition.runner import run_protocol
from rigctl.core import PlannedTrial, RigBackend
from rigctl.rigs import KINDS, make_backend, open_rig
from rigctl.storage.session import open_session


@pytest.mark.parametrize("kind,options,words", [
    ("moon", {}, "unknown rig kind"),
    ("hardware", {"drum_port": "/dev/null"}, "needs both drum_port and taxel_port"),
    ("sim", {"drum_port": "/dev/a", "taxel_port": "/dev/b"}, "select the hardware rig"),
    ("replay", {}, "needs a source"),
    ("replay", {"source": "/no/such/file.h5"}, "no such file"),
])
def test_open_rig_refusals(kind, options, words):
    with pytest.raises(RigError, match=words):
        open_rig(kind, **options)


def test_every_kind_builds_a_backend(tmp_path):
    for kind in ("sim", "hardware", "inprocess"):
        opts = {"drum_port": "/dev/x", "taxel_port": "/dev/y"} if kind == "hardware" else {}
        backend = make_backend(kind, **opts)
        assert isinstance(backend, RigBackend) and backend.mode == kind
    assert set(KINDS) == {"sim", "hil", "hardware", "replay", "inprocess", "handheld"}


def _source_session(tmp_path, lines: str):
    """``tmp_path/src.h5``: a session recorded on the in-process rig (120 mm/s, 300 g, 0.3 s trials, the texture set
    Linen-1 and Tweed-22) with the protocol ``lines`` (its textures, its trials per condition)."""
    proto = parse_protocol(f'name = "src"\n{lines}\nspeeds_mm_s = [120]\nforces_g = [300]\nduration_s = 0.3\n'
                           '[settle]\nsettle_time_ms = 50\n[texture_set]\ntextures = ["Linen-1", "Tweed-22"]\n')
    src = tmp_path / "src.h5"
    with open_rig("inprocess", seed=1, host_config_path=tmp_path / "rig.json") as rig:
        assert run_protocol(proto, src, rig=rig, progress=False).ok
    return src


def test_replay_rig_on_a_session_file(tmp_path):
    src = _source_session(tmp_path, 'textures = ["Linen-1", "Tweed-22"]')
    with open_session(src) as s:
        layout, textures = s.layout, s.textures
    with open_rig("replay", source=src, host_config_path=tmp_path / "rig.json") as rig:
        assert rig.mode == "replay" and rig.textures == textures and rig.layout == layout
        rig.mount_texture("Tweed-22")
        data = rig.record_trial(PlannedTrial(0, "Tweed-22", 120.0, 300.0, 0.2))
    assert data.taxels.shape == (200, layout.n_channels)


def test_a_replayed_trial_starts_at_its_source_trials_first_sample_however_late_the_host(tmp_path, monkeypatch):
    """The host thread may lose the CPU right after the replay source went on at its next trial, while the simulated
    board sends that trial's first frames (an unpaced rig runs ahead of a slow reader by seconds). The capture begins
    before the switch, so the trial still starts at the source trial's first sample. Before, the switch came first:
    those frames arrived before the capture began, the trial started wherever the capture did (10 to 3,336 samples
    into its source trial in 5 of 12 unpaced `acquire --replay` runs), and only the provenance said so."""
    src = _source_session(tmp_path, 'textures = ["Tweed-22"]\ntrials_per_condition = 2')
    with open_session(src) as s:
        sources = {int(t): s.trial(t).taxels for t in s.completed_ids()}
    with open_rig("replay", source=src, host_config_path=tmp_path / "rig.json") as rig:
        backend, clock = rig.backend, rig.drum.clock
        begin = backend.begin_source_trial

        def a_late_host():
            cue = begin()
            clock.sleep(0.2)  # the host loses the CPU: ~200 frames of the source trial are sent meanwhile
            return cue

        monkeypatch.setattr(backend, "begin_source_trial", a_late_host)
        rig.mount_texture("Tweed-22")
        for trial in range(2):
            data = rig.record_trial(PlannedTrial(trial, "Tweed-22", 120.0, 300.0, 0.2))
            a = data.attrs
            assert a["source_first_sample"] == 0 and a["source_last_sample"] == 199, a
            np.testing.assert_array_equal(data.taxels, sources[int(a["source_trial_id"])][:200])
