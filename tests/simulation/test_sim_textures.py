"""The paper's 16 textures (Fig. 2B): groups, variants, and distinct height profiles."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl.simulation.textures import LETTERS, TEXTURE_GROUPS, TEXTURES, VARIANTS, get_texture


def test_letters_groups_and_variant_order():
    assert LETTERS == "ABCDEFGHIJKLMNOP"
    assert TEXTURE_GROUPS == ("smooth", "circular ridges", "rectangular ridges", "waves")
    assert TEXTURES["A"].group == "smooth" and TEXTURES["A"].height_mm == 0
    for first, group in (("B", "circular ridges"), ("G", "rectangular ridges"), ("L", "waves")):
        block = [TEXTURES[chr(ord(first) + i)] for i in range(5)]
        assert [t.group for t in block] == [group] * 5
        assert [t.variant for t in block] == list(VARIANTS)
        base, dh, ds, hh, hs = block
        assert dh.height_mm == pytest.approx(2 * base.height_mm) and dh.period_mm == base.period_mm
        assert ds.period_mm == pytest.approx(2 * base.period_mm) and ds.height_mm == base.height_mm
        assert hh.height_mm == pytest.approx(base.height_mm / 2)
        assert hs.period_mm == pytest.approx(base.period_mm / 2)
        assert 0.3 <= base.height_mm <= 1.5 and 8 <= base.period_mm <= 20  # plausible printed plates
        if group != "waves":  # half-space ridges still leave a gap between them
            assert hs.period_mm > hs.width_mm


def test_height_profiles_are_distinct_and_bounded():
    x = np.linspace(0, 48, 4801)
    profiles = {}
    for letter, tex in TEXTURES.items():
        h = tex.height(x)
        assert h.shape == x.shape
        assert h.min() >= 0 and h.max() <= tex.height_mm + 1e-12
        if letter != "A":
            assert h.max() == pytest.approx(tex.height_mm, rel=0.05)
            # periodic with the texture's period
            np.testing.assert_allclose(tex.height(x + tex.period_mm), h, atol=1e-9)
        profiles[letter] = h
    letters = list(profiles)
    for i, a in enumerate(letters):
        for b in letters[i + 1:]:
            assert np.abs(profiles[a] - profiles[b]).max() > 0.1, (a, b)


def test_get_texture_rejects_unknown():
    assert get_texture("b") is TEXTURES["B"]
    with pytest.raises(KeyError, match="ABCDEFGHIJKLMNOP"):
        get_texture("Q")


def test_spacing_is_comparable_to_the_feature_window():
    """The paper's features average 100 ms windows: 4-12 mm of surface at 40-120 mm/s, 12 mm after speed scaling to
    120 mm/s. The spacings span that scale (so the ridges are not averaged away in every window), and no period
    is a divisor of 12 mm (a whole number of periods per scaled window would average out exactly)."""
    periods = sorted({t.period_mm for t in TEXTURES.values() if t.letter != "A"})
    assert periods[0] >= 4.0 and periods[-1] >= 2 * 12.0
    for p in periods:
        assert abs(12.0 / p - round(12.0 / p)) > 0.1, p



def test_any_texture_set_renders():
    from rigctl.core import TextureSet, TextureSpec
    from rigctl.simulation.textures import derived_geometry

    ts = TextureSet([TextureSpec("Linen", "woven", {"kind": "wave", "height_mm": 0.5, "period_mm": 12.0}),
                     TextureSpec("HB3", "knit", {"period_mm": 8.0}), "Velvet"], name="lab")
    linen = get_texture("Linen", ts)
    assert (linen.label, linen.kind, linen.height_mm, linen.period_mm, linen.width_mm) == ("Linen", "wave", 0.5,
                                                                                           12.0, 12.0)
    hb3 = get_texture("hb3", ts)  # case-insensitive when unique; the kind and height come from the label
    assert hb3.label == "HB3" and hb3.period_mm == 8.0 and hb3.kind == derived_geometry("HB3")["kind"]
    velvet = get_texture("Velvet", ts)
    geo = derived_geometry("Velvet")
    assert (velvet.kind, velvet.height_mm, velvet.period_mm) == (geo["kind"], geo["height_mm"], geo["period_mm"])
    assert derived_geometry("Velvet") == geo  # deterministic
    assert velvet.index == -1 and get_texture("B").index == 1
    x = np.linspace(0, 60, 601)
    assert velvet.height(x).max() == pytest.approx(velvet.height_mm, rel=0.05)
    with pytest.raises(KeyError):
        get_texture("Silk", ts)
    with pytest.raises(KeyError):
        get_texture("Linen")  # not one of the paper's plates
