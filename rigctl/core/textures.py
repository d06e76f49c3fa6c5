"""Texture sets as data: labels of any length, optional groups, optional per-texture geometry, stable codes.

A :class:`TextureSet` names the textures a session can hold. Its order fixes each texture's integer code
(:meth:`TextureSet.code`), so codes never depend on the order in which trials were recorded or imported. Groups are
optional and user-defined (the paper's four; a lab's own); the groups task of the analysis uses a file's groups and
refuses data that has none. Geometry (kind, height, period, width; mm) is what the simulated rig renders.

The built-in default, :data:`PAPER_TEXTURES`, is the paper's 16 3D-printed plates A-P (Fig. 2B): A smooth; B-F
circular ridges, G-K rectangular ridges, L-P waves, each group in the order base, double height, double space, half
height, half space. The paper gives no dimensions; the base dimensions (15 mm period, 1 mm height, 5 mm ridge width)
are rigctl's choice, explained in :mod:`rigctl.simulation.textures`.

Imports nothing else of rigctl's.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

__all__ = ["TextureSpec", "TextureSet", "TextureSetError", "PAPER_TEXTURES", "PAPER_GROUPS", "PAPER_VARIANTS",
           "texture_set_from_labels"]

#: the paper's four texture groups (Fig. 2B), in label order
PAPER_GROUPS: tuple[str, ...] = ("smooth", "circular ridges", "rectangular ridges", "waves")
#: the five variants of each ridged group, in the paper's order
PAPER_VARIANTS: tuple[str, ...] = ("base", "double height", "double space", "half height", "half space")

#: geometry keys a texture may carry (all optional); lengths in mm
GEOMETRY_KEYS = ("kind", "variant", "height_mm", "period_mm", "width_mm")
#: kinds the simulated rig can render
KINDS = ("smooth", "circular", "rectangular", "wave")


class TextureSetError(ValueError):
    """A texture set that cannot be (empty or repeated labels, unknown label, malformed groups or geometry)."""


@dataclass(frozen=True)
class TextureSpec:
    """One texture of a set.

    Attributes
    ----------
    label : str, any non-empty text (``"A"``, ``"HB3"``, ``"Linen"``), stored as UTF-8, never truncated.
    group : str or None, the texture's group in the set (None: ungrouped).
    geometry : dict, optional ``kind`` (smooth | circular | rectangular | wave), ``variant``, ``height_mm``,
        ``period_mm``, ``width_mm`` (mm) for the simulated rig; empty when unknown.
    """

    label: str
    group: str | None = None
    geometry: Mapping[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict:
        geo = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in self.geometry.items()}
        return {"label": self.label, "group": self.group, "geometry": geo}


class TextureSet:
    """An ordered set of textures with optional groups and geometry; codes are positions in the set.

    Parameters
    ----------
    textures : sequence of :class:`TextureSpec` or labels (str).
    name : a short name (``"paper A-P"``).
    groups : optional group names in order (default: order of first appearance among the textures).

    Raises
    ------
    TextureSetError
        No textures, an empty or repeated label, a group not in ``groups``, or geometry with an unknown kind.
    """

    def __init__(self, textures: Iterable[TextureSpec | str], *, name: str = "", groups: Sequence[str] | None = None):
        specs = tuple(t if isinstance(t, TextureSpec) else TextureSpec(str(t)) for t in textures)
        if not specs:
            raise TextureSetError("a texture set needs at least one texture")
        seen: set[str] = set()
        for s in specs:
            if not isinstance(s.label, str) or not s.label.strip():
                raise TextureSetError(f"texture labels must be non-empty text, got {s.label!r}")
            if s.label in seen:
                raise TextureSetError(f"texture {s.label!r} is listed twice")
            seen.add(s.label)
            kind = s.geometry.get("kind")
            if kind is not None and kind not in KINDS:
                raise TextureSetError(f"texture {s.label!r}: geometry kind must be one of {KINDS}, got {kind!r}")
        used = [s.group for s in specs if s.group]
        if groups is None:
            groups = tuple(dict.fromkeys(used))
        else:
            groups = tuple(str(g) for g in groups)
            unknown = sorted(set(used) - set(groups))
            if unknown:
                raise TextureSetError(f"textures name groups {unknown} that are not in the set's groups {groups}")
        self.name = str(name)
        self.textures: tuple[TextureSpec, ...] = specs
        self.groups: tuple[str, ...] = tuple(groups)
        self._index = {s.label: i for i, s in enumerate(specs)}

    # -- queries -----------------------------------------------------------------------------------------------------
    @property
    def labels(self) -> tuple[str, ...]:
        return tuple(s.label for s in self.textures)

    @property
    def has_groups(self) -> bool:
        """True when every texture has a group (the groups task needs that)."""
        return all(s.group for s in self.textures)

    def __len__(self) -> int:
        return len(self.textures)

    def __contains__(self, label: object) -> bool:
        return label in self._index

    def __iter__(self):
        return iter(self.textures)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, TextureSet) and self.to_dict() == other.to_dict()

    def __repr__(self) -> str:
        return f"TextureSet({self.name!r}, {len(self)} textures, groups={list(self.groups)})"

    def resolve(self, label: str) -> str:
        """The set's spelling of ``label``: exact match first, then a unique case-insensitive match.

        Raises
        ------
        TextureSetError naming the set's labels.
        """
        if label in self._index:
            return label
        key = str(label).strip()
        if key in self._index:
            return key
        folded = [s.label for s in self.textures if s.label.casefold() == key.casefold()]
        if len(folded) == 1:
            return folded[0]
        shown = ", ".join(self.labels[:30]) + (" ..." if len(self) > 30 else "")
        raise TextureSetError(f"texture '{label}' is not in the texture set {self.name or ''!r} ({shown})")

    def spec(self, label: str) -> TextureSpec:
        return self.textures[self._index[self.resolve(label)]]

    def code(self, label: str) -> int:
        """Stable integer code: the texture's position in the set. Raises TextureSetError for an unknown label."""
        return self._index[self.resolve(label)]

    def group_of(self, label: str) -> str | None:
        """The texture's group, or None when it has none. Raises TextureSetError for an unknown label."""
        return self.spec(label).group

    def geometry(self, label: str) -> dict:
        return dict(self.spec(label).geometry)

    def subset(self, labels: Iterable[str]) -> "TextureSet":
        """The textures named, in the set's order (codes of a subset are its own positions)."""
        want = {self.resolve(t) for t in labels}
        return TextureSet([s for s in self.textures if s.label in want], name=self.name,
                          groups=[g for g in self.groups if any(s.group == g for s in self.textures
                                                                if s.label in want)])

    # -- storage -----------------------------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """JSON-able (stored in session and encoded files as the ``texture_set`` attribute)."""
        return {"name": self.name, "groups": list(self.groups), "textures": [s.to_dict() for s in self.textures]}

    def to_json(self) -> str:
        return json.dumps(self.to_dict())

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "TextureSet":
        """Inverse of :meth:`to_dict`; also accepts ``{"textures": ["A", "B"], "groups": {"g": ["A"]}}`` (a mapping
        of group -> labels, as a protocol file writes it). Raises TextureSetError on malformed input."""
        try:
            raw = list(d["textures"])
        except (KeyError, TypeError) as exc:
            raise TextureSetError(f"a texture set needs a 'textures' list, got {d!r}") from exc
        groups = d.get("groups")
        group_of: dict[str, str] = {}
        order = None
        if isinstance(groups, Mapping):
            order = list(groups)
            for g, members in groups.items():
                for m in members:
                    if str(m) in group_of:
                        raise TextureSetError(f"texture {m!r} is in two groups ({group_of[str(m)]!r} and {g!r})")
                    group_of[str(m)] = str(g)
        elif groups is not None:
            order = [str(g) for g in groups]
        geometry = d.get("geometry") or {}
        specs = []
        for t in raw:
            if isinstance(t, Mapping):
                label = str(t.get("label", ""))
                geo = {k: (math.inf if k == "period_mm" and v is None else v)
                       for k, v in (t.get("geometry") or {}).items()}
                specs.append(TextureSpec(label, t.get("group") or group_of.get(label), geo))
            else:
                label = str(t)
                specs.append(TextureSpec(label, group_of.get(label), dict(geometry.get(label, {}))))
        known = {s.label for s in specs}
        stray = sorted(set(group_of) - known)
        if stray:
            raise TextureSetError(f"groups name textures that are not in the set: {stray}")
        return cls(specs, name=str(d.get("name", "")), groups=order)

    @classmethod
    def from_json(cls, text: str | bytes) -> "TextureSet":
        try:
            return cls.from_dict(json.loads(text))
        except json.JSONDecodeError as exc:
            raise TextureSetError(f"texture set is not JSON: {exc}") from exc


def texture_set_from_labels(labels: Iterable[str], *, name: str = "",
                            groups: Mapping[str, Sequence[str]] | None = None) -> TextureSet:
    """A set of the distinct ``labels`` in sorted order (codes do not depend on the order trials come in); the
    paper's A-P set (with its groups and geometry) when every label is one of A-P and no groups are given."""
    distinct = sorted({str(t) for t in labels})
    if groups is None and distinct and set(distinct) <= set(PAPER_TEXTURES.labels):
        return PAPER_TEXTURES
    return TextureSet.from_dict({"name": name, "textures": distinct, "groups": dict(groups) if groups else None})


def _paper_set() -> TextureSet:
    base_h, base_p, base_w = 1.0, 15.0, 5.0
    specs = [TextureSpec("A", "smooth", {"kind": "smooth", "variant": "smooth", "height_mm": 0.0,
                                         "period_mm": math.inf, "width_mm": 0.0})]
    letter = ord("B")
    for group, kind in (("circular ridges", "circular"), ("rectangular ridges", "rectangular"), ("waves", "wave")):
        for variant in PAPER_VARIANTS:
            h, p = base_h, base_p
            h = h * 2 if variant == "double height" else h / 2 if variant == "half height" else h
            p = p * 2 if variant == "double space" else p / 2 if variant == "half space" else p
            w = p if kind == "wave" else base_w
            specs.append(TextureSpec(chr(letter), group, {"kind": kind, "variant": variant, "height_mm": h,
                                                          "period_mm": p, "width_mm": w}))
            letter += 1
    return TextureSet(specs, name="paper A-P", groups=PAPER_GROUPS)


#: the paper's 16 textures A-P with their four groups and geometry (Fig. 2B): the default texture set
PAPER_TEXTURES: TextureSet = _paper_set()
