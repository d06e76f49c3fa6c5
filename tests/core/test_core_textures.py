"""Texture sets: labels of any length, groups, geometry, stable codes, JSON round trip, refusals."""

from __future__ import annotations

import string

import pytest

from rigctl.core import PAPER_TEXTURES, TextureSet, TextureSetError, texture_set_from_labels


def test_paper_set():
    assert PAPER_TEXTURES.labels == tuple("ABCDEFGHIJKLMNOP")
    assert PAPER_TEXTURES.groups == ("smooth", "circular ridges", "rectangular ridges", "waves")
    assert [PAPER_TEXTURES.group_of(t) for t in "AFGL"] == ["smooth", "circular ridges", "rectangular ridges",
                                                           "waves"]
    assert PAPER_TEXTURES.geometry("D")["period_mm"] == 2 * PAPER_TEXTURES.geometry("B")["period_mm"]
    assert PAPER_TEXTURES.code("a") == 0 and PAPER_TEXTURES.code("P") == 15 and PAPER_TEXTURES.has_groups


def test_multi_character_labels_and_codes_are_stable():
    labels = [f"{c}{c.lower()}{i}" for i, c in enumerate(string.ascii_uppercase)]  # 26 textures, 3+ characters
    a = texture_set_from_labels(labels)
    b = texture_set_from_labels(list(reversed(labels)) * 3)  # another import order, repeats
    assert len(a) == 26 and a.labels == b.labels
    assert [a.code(t) for t in labels] == [b.code(t) for t in labels]
    assert "HB3" not in a and a.resolve("hh7") == "Hh7"
    assert not a.has_groups and a.group_of("Aa0") is None


def test_groups_from_a_mapping_and_round_trip():
    s = TextureSet.from_dict({"name": "fabrics", "textures": ["Linen", "Canvas", "Silk ünï"],
                              "groups": {"woven": ["Linen", "Canvas"], "fine": ["Silk ünï"]},
                              "geometry": {"Linen": {"kind": "wave", "height_mm": 0.2, "period_mm": 1.0}}})
    assert s.groups == ("woven", "fine") and s.has_groups and s.group_of("Silk ünï") == "fine"
    assert s.geometry("Linen")["kind"] == "wave" and s.geometry("Canvas") == {}
    assert TextureSet.from_json(s.to_json()) == s
    assert TextureSet.from_json(PAPER_TEXTURES.to_json()) == PAPER_TEXTURES  # inf period survives JSON


@pytest.mark.parametrize("doc, match", [
    ({"textures": []}, "at least one"),
    ({"textures": ["A", "A"]}, "twice"),
    ({"textures": ["A", ""]}, "non-empty"),
    ({"textures": ["A"], "groups": {"g": ["B"]}}, "not in the set"),
    ({"textures": ["A", "B"], "groups": {"g": ["A"], "h": ["A"]}}, "two groups"),
    ({"textures": ["A"], "geometry": {"A": {"kind": "knurled"}}}, "kind"),
    ({"labels": ["A"]}, "'textures' list"),
])
def test_bad_sets_refused(doc, match):
    with pytest.raises(TextureSetError, match=match):
        TextureSet.from_dict(doc)


def test_unknown_label_names_the_set():
    with pytest.raises(TextureSetError, match="'Q' is not in the texture set 'paper A-P'"):
        PAPER_TEXTURES.code("Q")


def test_paper_labels_give_the_paper_set_and_subset_keeps_groups():
    assert texture_set_from_labels("CBA") is PAPER_TEXTURES
    sub = PAPER_TEXTURES.subset(["L", "B"])
    assert sub.labels == ("B", "L") and sub.groups == ("circular ridges", "waves")
