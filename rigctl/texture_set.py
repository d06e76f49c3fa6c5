"""The paper's texture set as labels (Fig. 2B): letters A-P, their four groups and five variants.

Shared vocabulary of the simulation (which adds the geometry, :mod:`rigctl.simulation.textures`), the encoding
pipeline (which writes each trial's group) and the analyses (texture-group task). No dependencies.

A is the smooth control; B-F circular ridges, G-K rectangular ridges, L-P waves, each group in the order base,
double height, double space, half height, half space.
"""

from __future__ import annotations

#: the four texture groups, in label order (group index = position in this tuple)
TEXTURE_GROUPS: tuple[str, ...] = ("smooth", "circular ridges", "rectangular ridges", "waves")

#: the five variants of each ridged group, in the paper's order
VARIANTS: tuple[str, ...] = ("base", "double height", "double space", "half height", "half space")

#: letter -> group, for the 16 textures A-P
GROUP_OF: dict[str, str] = {
    "A": "smooth",
    **{c: "circular ridges" for c in "BCDEF"},
    **{c: "rectangular ridges" for c in "GHIJK"},
    **{c: "waves" for c in "LMNOP"},
}

#: letter -> variant ("smooth" for A)
VARIANT_OF: dict[str, str] = {"A": "smooth", **{c: VARIANTS[i % 5] for i, c in enumerate("BCDEFGHIJKLMNOP")}}

LETTERS: tuple[str, ...] = tuple(GROUP_OF)


def texture_group(texture: str) -> str:
    """The paper's group of a texture letter (``"B"`` -> ``"circular ridges"``); ``""`` for labels outside A-P
    (e.g. the FabricSlide fabrics)."""
    return GROUP_OF.get(str(texture).strip().upper(), "") if len(str(texture).strip()) == 1 else ""
