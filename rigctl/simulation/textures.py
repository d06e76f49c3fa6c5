"""The paper's 16 3D-printed textures A-P (Fig. 2B) as surface height profiles.

The paper's set (Results, "Rotating Drum Apparatus and Tactile Texture Dataset"): a smooth control (A) and three
groups of ridged textures - circular ridges (B-F), rectangular ridges (G-K) and waves (L-P) - each in five variants,
in this order: base, double height, double space, half height, half space. "Height" is the height of the features
(it sets the amplitude of the measured force), "space" the distance between them (it sets the period).

The paper gives no dimensions; the base dimensions here are chosen for the paper's features (SA spike rate and RA
spike count in 100 ms windows, Methods "Feature Extraction") and plausible for 3D-printed plates (0.4 mm nozzle):
ridge period 15 mm (centre to centre), ridge height 1.0 mm, ridge width 5 mm. A 100 ms window covers 4-12 mm of
surface at 40-120 mm/s (12 mm after speed scaling to 120 mm/s), so a period of 15 mm (7.5 mm half space, 30 mm
double space) is comparable to or longer than a window and survives the window averaging, while the period does
not divide 12 mm (a 12 mm period would average out exactly in every speed-scaled window). The heights
(0.5 / 1.0 / 2.0 mm) bracket the pad's indentation (0.125-0.5 mm at 250-1000 g, :class:`rigctl.simulation.model.
SensorConfig`), so the height sets whether the pad bottoms out between the ridges, i.e. the depth of the pressure
modulation. "Double space" doubles the period, "half space" halves it, the feature width staying the same (so
half-space ridges keep a 2.5 mm gap).

Ridges run across the drum (parallel to its axis), so the profile varies only along the direction of travel ``x``
(surface coordinate on the plate, mm); it is the same under the three columns of the sensor.

Any texture set (:class:`rigctl.core.textures.TextureSet`) renders too: :func:`get_texture` takes a label and the
set it belongs to. The geometry comes from the set (``kind``, ``height_mm``, ``period_mm``, ``width_mm``); keys the
set leaves out are derived deterministically from the label (:func:`derived_geometry`: the SHA-256 of the UTF-8
label picks the kind among circular / rectangular / wave, the height among 0.5 / 1 / 2 mm and the period among
7.5 / 10 / 15 / 20 / 30 mm, ridge width 5 mm capped at 0.6 x the period), so a label always renders the same plate,
in every process, and different labels almost always render different plates.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
from collections.abc import Mapping
from typing import Any, Literal

import numpy as np

from rigctl.core.textures import PAPER_TEXTURES, TextureSet

Kind = Literal["smooth", "circular", "rectangular", "wave"]

#: the four texture groups of the paper, in label order (group index = position in this tuple)
TEXTURE_GROUPS: tuple[str, ...] = ("smooth", "circular ridges", "rectangular ridges", "waves")

#: the five variants of each ridged group, in the paper's order (Fig. 2B)
VARIANTS: tuple[str, ...] = ("base", "double height", "double space", "half height", "half space")

BASE_HEIGHT_MM = 1.0  #: mm, ridge / wave height of the base variant
BASE_PERIOD_MM = 15.0  #: mm, centre-to-centre spacing of the base variant
BASE_WIDTH_MM = 5.0  #: mm, ridge width at the base (circular and rectangular ridges)


@dataclasses.dataclass(frozen=True)
class Texture:
    """One texture plate.

    Attributes
    ----------
    letter : str
        The texture's label: "A" ... "P" as in the paper's Fig. 2B, or any label of a texture set ("HB3", "Linen").
    group : str
        One of :data:`TEXTURE_GROUPS` for the paper's plates; the set's group (or "") for others.
    variant : str
        "smooth" for A, else one of :data:`VARIANTS`; "" when the set names none.
    kind : {"smooth", "circular", "rectangular", "wave"}
        Cross-section of the features: circular-segment ridges (a half ellipse of the given width and height),
        rectangular ridges, or a cosine wave (peak-to-peak = height, crest-to-crest = period).
    height_mm : float
        Feature height above the plate's base surface, mm (0 for the smooth plate).
    period_mm : float
        Centre-to-centre feature spacing along the direction of travel, mm (``inf`` for the smooth plate).
    width_mm : float
        Ridge width at the base, mm (for waves: the period; for the smooth plate: 0).
    """

    letter: str
    group: str
    variant: str
    kind: Kind
    height_mm: float
    period_mm: float
    width_mm: float

    @property
    def label(self) -> str:
        """The texture's label (same as :attr:`letter`)."""
        return self.letter

    @property
    def group_index(self) -> int:
        """Index of :attr:`group` in :data:`TEXTURE_GROUPS` (0 = smooth); -1 for a group outside the paper's."""
        return TEXTURE_GROUPS.index(self.group) if self.group in TEXTURE_GROUPS else -1

    @property
    def index(self) -> int:
        """Position in the paper's set: 0 for A ... 15 for P; -1 for a texture outside it."""
        return PAPER_TEXTURES.code(self.letter) if self.letter in PAPER_TEXTURES else -1

    def height(self, x_mm) -> np.ndarray:
        """Surface height profile ``h(x)``.

        Parameters
        ----------
        x_mm : array_like of float
            Positions along the direction of travel on the plate, mm (any shape; the pattern is periodic, so any
            real value is valid).

        Returns
        -------
        numpy.ndarray of float64, same shape as ``x_mm``
            Height above the plate's base surface, mm, in ``[0, height_mm]``.
        """
        x = np.asarray(x_mm, dtype=np.float64)
        if self.kind == "smooth":
            return np.zeros_like(x)
        p = self.period_mm
        if self.kind == "wave":
            return self.height_mm * 0.5 * (1.0 + np.cos(2.0 * np.pi * x / p))
        # distance to the nearest ridge centre (ridge centres at k * period)
        d = np.abs(x - p * np.round(x / p))
        half = 0.5 * self.width_mm
        if self.kind == "rectangular":
            return np.where(d < half, self.height_mm, 0.0)
        # circular segment, approximated by a half ellipse of the given width and height
        r = np.clip(1.0 - (d / half) ** 2, 0.0, None)
        return self.height_mm * np.sqrt(r)

    def to_dict(self) -> dict:
        """JSON-able description (``period_mm`` of the smooth plate is written as ``None``)."""
        d = dataclasses.asdict(self)
        if not np.isfinite(d["period_mm"]):
            d["period_mm"] = None
        return d


def _build() -> dict[str, Texture]:
    textures = {"A": Texture("A", "smooth", "smooth", "smooth", 0.0, float("inf"), 0.0)}
    groups: tuple[tuple[str, Kind], ...] = (("circular ridges", "circular"), ("rectangular ridges", "rectangular"), ("waves", "wave"))
    letter = ord("B")
    for group, kind in groups:
        for variant in VARIANTS:
            h, p = BASE_HEIGHT_MM, BASE_PERIOD_MM
            if variant == "double height":
                h *= 2
            elif variant == "half height":
                h /= 2
            elif variant == "double space":
                p *= 2
            elif variant == "half space":
                p /= 2
            w = p if kind == "wave" else BASE_WIDTH_MM
            textures[chr(letter)] = Texture(chr(letter), group, variant, kind, h, p, w)
            letter += 1
    return textures


#: letter -> :class:`Texture`, "A" ... "P" in order
TEXTURES: dict[str, Texture] = _build()

#: the letters in order, "ABCDEFGHIJKLMNOP"
LETTERS: str = "".join(TEXTURES)


#: kinds, heights (mm) and periods (mm) :func:`derived_geometry` chooses from
_DERIVED_KINDS: tuple[Kind, ...] = ("circular", "rectangular", "wave")
_DERIVED_HEIGHTS_MM = (0.5, 1.0, 2.0)
_DERIVED_PERIODS_MM = (7.5, 10.0, 15.0, 20.0, 30.0)


def derived_geometry(label: str) -> dict:
    """A deterministic geometry for a texture the set gives none for: ``{"kind", "height_mm", "period_mm",
    "width_mm"}`` (mm) from the SHA-256 of the UTF-8 ``label`` (see the module docstring). Same label, same plate."""
    h = hashlib.sha256(str(label).encode("utf-8")).digest()
    kind = _DERIVED_KINDS[h[0] % len(_DERIVED_KINDS)]
    height = _DERIVED_HEIGHTS_MM[h[1] % len(_DERIVED_HEIGHTS_MM)]
    period = _DERIVED_PERIODS_MM[h[2] % len(_DERIVED_PERIODS_MM)]
    width = period if kind == "wave" else min(BASE_WIDTH_MM, 0.6 * period)
    return {"kind": kind, "height_mm": height, "period_mm": period, "width_mm": width}


def texture_from_spec(label: str, group: str | None, geometry: Mapping[str, Any]) -> Texture:
    """A :class:`Texture` from a texture set's entry: its geometry, missing keys from :func:`derived_geometry`.

    Raises ValueError for a geometry that cannot be rendered (unknown kind, non-positive period or width, negative
    height).
    """
    fill = derived_geometry(label)
    geo = dict(geometry or {})
    if "kind" not in geo:
        geo = {**fill, **{k: v for k, v in geo.items() if v is not None}}
    kind = str(geo["kind"])
    if kind == "smooth":
        return Texture(label, group or "", str(geo.get("variant", "smooth")), "smooth", 0.0, float("inf"), 0.0)
    if kind not in _DERIVED_KINDS:
        raise ValueError(f"texture {label!r}: cannot render geometry kind {kind!r}")
    height = float(geo["height_mm"] if geo.get("height_mm") is not None else fill["height_mm"])
    period = float(geo["period_mm"] if geo.get("period_mm") is not None else fill["period_mm"])
    if geo.get("width_mm") is not None:
        width = float(geo["width_mm"])
    else:
        width = period if kind == "wave" else min(BASE_WIDTH_MM, 0.6 * period)
    if not (height >= 0 and math.isfinite(period) and period > 0 and width > 0):
        raise ValueError(f"texture {label!r}: geometry must have height >= 0, period > 0 and width > 0 (mm), got "
                         f"{height}, {period}, {width}")
    return Texture(label, group or "", str(geo.get("variant", "")), kind, height, period, width)


def get_texture(texture: str | Texture, textures: TextureSet | None = None) -> Texture:
    """The :class:`Texture` to render for a label (or pass a Texture through).

    Parameters
    ----------
    texture : a label, or a :class:`Texture`.
    textures : the texture set the label belongs to; None = the paper's A-P (labels case-insensitive).
        For the paper's set (or None) the plates are :data:`TEXTURES`; for another set the geometry is the set's,
        completed by :func:`derived_geometry` for what it leaves out.

    Raises
    ------
    KeyError
        If the label is not in the set (the message lists the set's labels), or its geometry cannot be rendered.
    """
    if isinstance(texture, Texture):
        return texture
    if textures is None or textures is PAPER_TEXTURES:
        key = str(texture).strip().upper()
        if key not in TEXTURES:
            raise KeyError(f"unknown texture {texture!r}; expected one of {LETTERS}")
        return TEXTURES[key]
    try:
        spec = textures.spec(str(texture))
        return texture_from_spec(spec.label, spec.group, spec.geometry)
    except ValueError as exc:  # TextureSetError (not in the set) or unrenderable geometry
        raise KeyError(str(exc)) from None
