"""Protocols with their own texture sets: [texture_set] in TOML (labels of any length, groups, geometry), refusals
with the line at fault, and a protocol with custom multi-character labels recorded on the simulated rig (real ptys,
pymodbus, pyserial) into a session whose plan and texture set keep the labels."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl.acquisition.protocol import ProtocolError, parse_protocol
from rigctl.acquisition.runner import run_protocol
from rigctl.core import PAPER_TEXTURES
from rigctl.rigs import open_rig
from rigctl.simulation.textures import derived_geometry, get_texture
from rigctl.storage.session import open_session

CUSTOM = '''name = "lab fabrics"
textures = ["Linen", "HB3", "Denim-02"]
speeds_mm_s = [120]
forces_g = [300]
duration_s = 0.4
[settle]
settle_time_ms = 50

[texture_set]
name = "lab fabrics"
textures = ["Linen", "HB3", "Denim-02", "Velvet"]
groups = { woven = ["Linen", "Denim-02"], knit = ["HB3"], pile = ["Velvet"] }

[texture_set.geometry]
Linen = { kind = "wave", height_mm = 1.0, period_mm = 10.0 }
HB3 = { kind = "rectangular", height_mm = 2.0, period_mm = 20.0, width_mm = 6.0 }
'''


def test_default_set_is_the_papers():
    p = parse_protocol('name = "x"\ntextures = ["a", "P"]\nspeeds_mm_s = [40]\nforces_g = [300]\n')
    assert p.texture_set is PAPER_TEXTURES and p.textures == ("A", "P")


def test_declared_texture_set():
    p = parse_protocol(CUSTOM)
    ts = p.texture_set
    assert ts.labels == ("Linen", "HB3", "Denim-02", "Velvet") and ts.name == "lab fabrics"
    assert ts.group_of("HB3") == "knit" and ts.group_of("Denim-02") == "woven"
    assert ts.geometry("Linen")["kind"] == "wave"
    assert [t.texture for t in p.plan()] == ["Linen", "HB3", "Denim-02"]


@pytest.mark.parametrize("text,line,words", [
    ('name = "x"\ntextures = ["A", "HB3"]\nspeeds_mm_s = [40]\nforces_g = [300]\n', 2, "declare a [texture_set]"),
    (CUSTOM.replace('"Denim-02", "Velvet"]\ngroups', '"Velvet"]\ngroups').replace(
        'woven = ["Linen", "Denim-02"]', 'woven = ["Linen"]'), 2, "is not a texture of the set"),
    (CUSTOM.replace('knit = ["HB3"]', 'knit = ["HB4"]'), 13, "not in textures"),
    (CUSTOM.replace('kind = "wave", height_mm', 'kind = "zigzag", height_mm'), 15, "zigzag"),
    (CUSTOM.replace('period_mm = 10.0', 'period_mm = -1'), 15, "outside"),
])
def test_bad_texture_sets_name_the_line(text, line, words):
    with pytest.raises(ProtocolError) as err:
        parse_protocol(text, path="p.toml")
    assert words in str(err.value) and err.value.line is not None
    assert abs(err.value.line - line) <= 2, str(err.value)


def test_any_label_renders():
    p = parse_protocol(CUSTOM)
    linen = get_texture("Linen", p.texture_set)
    assert (linen.kind, linen.period_mm, linen.height_mm) == ("wave", 10.0, 1.0)
    velvet = get_texture("Velvet", p.texture_set)  # no geometry in the set: derived from the label
    assert velvet == get_texture("Velvet", p.texture_set)
    assert (velvet.kind, velvet.height_mm, velvet.period_mm) == tuple(derived_geometry("Velvet")[k] for k in
                                                                      ("kind", "height_mm", "period_mm"))
    with pytest.raises(KeyError):
        get_texture("Silk", p.texture_set)


def test_custom_labels_recorded_on_the_simulated_rig(tmp_path):
    """On the in-process rig (the model renders any label; the pty rig's wire is covered elsewhere)."""
    proto = parse_protocol(CUSTOM)
    out = tmp_path / "fabrics.h5"
    with open_rig("inprocess", seed=2, host_config_path=tmp_path / "rig.json") as rig:
        summary = run_protocol(proto, out, rig=rig, progress=False)
        assert rig.texture == "Denim-02"
    assert summary.ok and summary.recorded == 3, summary.lines()
    with open_session(out) as s:
        assert [str(t) for t in s.plan["texture"]] == ["Linen", "HB3", "Denim-02"]
        assert s.textures.labels == ("Linen", "HB3", "Denim-02", "Velvet")
        assert s.textures.group_of("HB3") == "knit"
        assert s.textures.code("Denim-02") == 2
        trials = [s.trial(i) for i in range(3)]
    assert all(t.taxels.shape == (400, 18) for t in trials)
    # three different plates: the top layer's modulation differs between them
    stds = [t.taxels[:, :9].astype(float).std(axis=0).mean() for t in trials]
    assert len({round(x, 1) for x in stds}) == 3, stds
    assert not np.array_equal(trials[0].taxels, trials[1].taxels)
