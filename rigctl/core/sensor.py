"""The sensor description: how many taxels, how they sit in layers and grids, how fast and how finely they are read.

One :class:`SensorLayout` drives every shape in rigctl: the frames the host parses (channel count from the taxel
board's identify reply), :class:`rigctl.core.trial.TrialData`, the session and encoded files (stored as JSON in
both), the encoder (one model step per sample at ``sample_rate_hz``, or an explicit resampling step), the spiking
features (SA/RA x channels), the analyses, the GUI's traces, heat maps and rasters, and replay.

The default, :data:`PAPER_SENSOR`, is the paper's drum sensor (Results, "Rotating Drum Apparatus"; Methods): a 3x3x2
taxel array, 18 taxels, the top layer type I (SA-like) and the bottom layer type II, 5 mm pitch, read at 1 kHz with
a 10-bit ADC. The paper's real-time system used a single-layer 3x3 finger (:data:`PAPER_FINGER`). Channel order is
layer-major, then row-major within a layer (row 0 = leading edge of the travel, column 0 = left), as on the wire
(``docs/wire-protocol.md`` section 1).

Imports nothing else of rigctl's (``rigctl.core`` is the layer everything shares).
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["TaxelLayer", "SensorLayout", "PAPER_SENSOR", "PAPER_FINGER", "parse_layout", "LayoutError"]

#: receptor types of the paper's two layers (top, bottom)
RECEPTOR_TYPES: tuple[str, ...] = ("type I", "type II")


class LayoutError(ValueError):
    """A sensor description that cannot be (wrong counts, bad layout text, readings of the wrong shape)."""


@dataclass(frozen=True)
class TaxelLayer:
    """One layer of taxels on a regular grid.

    Attributes
    ----------
    name : str, e.g. ``"top"``.
    receptor : str, the receptor type the layer stands for (``"type I"`` / ``"type II"``; free text).
    rows, cols : int >= 1, grid shape; channels of the layer run row-major.
    """

    name: str
    receptor: str
    rows: int
    cols: int

    def __post_init__(self) -> None:
        if int(self.rows) < 1 or int(self.cols) < 1:
            raise LayoutError(f"layer {self.name!r}: rows and cols must be >= 1, got {self.rows}x{self.cols}")
        object.__setattr__(self, "rows", int(self.rows))
        object.__setattr__(self, "cols", int(self.cols))

    @property
    def n_channels(self) -> int:
        return self.rows * self.cols


@dataclass(frozen=True)
class SensorLayout:
    """A tactile sensor: taxel layers, pitch, sample rate and ADC resolution.

    Parameters
    ----------
    layers : sequence of :class:`TaxelLayer`, in channel order (layer 0's channels first).
    pitch_mm : centre-to-centre taxel spacing, mm.
    sample_rate_hz : readings per second per taxel, Hz (> 0).
    adc_bits : ADC resolution, bits (readings are integer counts 0 .. 2**adc_bits - 1); 1-16.
    channel_names : optional name per channel (default ``"<layer> r<row>c<col>"``).
    name : a short name for the sensor (``"paper 3x3x2"``).

    Raises
    ------
    LayoutError
        No layers, a rate <= 0, bits outside 1-16, or ``channel_names`` of the wrong length.
    """

    layers: tuple[TaxelLayer, ...]
    pitch_mm: float = 5.0
    sample_rate_hz: float = 1000.0
    adc_bits: int = 10
    channel_names: tuple[str, ...] | None = None
    name: str = ""

    def __post_init__(self) -> None:
        layers = tuple(self.layers)
        if not layers:
            raise LayoutError("a sensor needs at least one taxel layer")
        object.__setattr__(self, "layers", layers)
        rate = float(self.sample_rate_hz)
        if not (math.isfinite(rate) and rate > 0):
            raise LayoutError(f"sample_rate_hz must be > 0, got {self.sample_rate_hz}")
        object.__setattr__(self, "sample_rate_hz", rate)
        bits = int(self.adc_bits)
        if not 1 <= bits <= 16:
            raise LayoutError(f"adc_bits must be 1-16, got {self.adc_bits}")
        object.__setattr__(self, "adc_bits", bits)
        object.__setattr__(self, "pitch_mm", float(self.pitch_mm))
        if self.channel_names is not None:
            names = tuple(str(n) for n in self.channel_names)
            if len(names) != self.n_channels:
                raise LayoutError(f"{len(names)} channel names for {self.n_channels} channels")
            object.__setattr__(self, "channel_names", names)

    # -- constructors ----------------------------------------------------------------------------------------------
    @classmethod
    def grid(cls, rows: int, cols: int, n_layers: int = 1, *, sample_rate_hz: float = 1000.0, adc_bits: int = 10,
             pitch_mm: float = 5.0, layer_names: Sequence[str] | None = None,
             receptors: Sequence[str] | None = None, channel_names: Sequence[str] | None = None,
             name: str = "") -> "SensorLayout":
        """``n_layers`` layers of ``rows x cols`` taxels. Layer names default to top/bottom (two layers), ``layer<i>``
        otherwise; receptors to type I / type II for two layers, type I for one, ``""`` beyond."""
        n_layers = int(n_layers)
        if n_layers < 1:
            raise LayoutError(f"n_layers must be >= 1, got {n_layers}")
        if layer_names is None:
            layer_names = ("top", "bottom") if n_layers == 2 else ("taxels",) if n_layers == 1 else tuple(
                f"layer{i}" for i in range(n_layers))
        if receptors is None:
            receptors = RECEPTOR_TYPES if n_layers == 2 else ("type I",) if n_layers == 1 else ("",) * n_layers
        if len(layer_names) != n_layers or len(receptors) != n_layers:
            raise LayoutError(f"{n_layers} layers need {n_layers} layer names and receptor types")
        layers = tuple(TaxelLayer(str(n), str(r), rows, cols) for n, r in zip(layer_names, receptors))
        return cls(layers, pitch_mm=pitch_mm, sample_rate_hz=sample_rate_hz, adc_bits=adc_bits,
                   channel_names=None if channel_names is None else tuple(channel_names),
                   name=name or f"{rows}x{cols}x{n_layers}")

    @classmethod
    def for_channels(cls, n_channels: int, **kw: Any) -> "SensorLayout":
        """A layout for ``n_channels`` taxels when nothing more is known: the paper's 3x3x2 for 18, 3x3 for 9, a
        square grid when ``n_channels`` is a square, else a 1 x n row. Keywords as :meth:`grid`."""
        n = int(n_channels)
        if n < 1:
            raise LayoutError(f"a sensor needs at least one channel, got {n}")
        if n == 18:
            return cls.grid(3, 3, 2, **kw)
        side = int(round(math.sqrt(n)))
        if side * side == n:
            return cls.grid(side, side, 1, **kw)
        return cls.grid(1, n, 1, **kw)

    # -- derived ---------------------------------------------------------------------------------------------------
    @property
    def n_channels(self) -> int:
        """Total taxels (channels), all layers."""
        return sum(layer.n_channels for layer in self.layers)

    @property
    def n_layers(self) -> int:
        return len(self.layers)

    @property
    def adc_max(self) -> int:
        """Largest reading, ADC counts (1023 for 10 bits)."""
        return (1 << self.adc_bits) - 1

    @property
    def shape_text(self) -> str:
        """``"3x3x2"`` when every layer has the same grid, else ``"3x3+2x2"``."""
        grids = {(la.rows, la.cols) for la in self.layers}
        if len(grids) == 1:
            r, c = grids.pop()
            return f"{r}x{c}x{self.n_layers}"
        return "+".join(f"{la.rows}x{la.cols}" for la in self.layers)

    def layer_channels(self, layer: int | str) -> range:
        """Channel indices of a layer (by index or name).

        Raises
        ------
        KeyError for an unknown layer name, IndexError for an index out of range.
        """
        if isinstance(layer, str):
            names = [la.name for la in self.layers]
            if layer not in names:
                raise KeyError(f"no layer {layer!r} (layers: {', '.join(names)})")
            layer = names.index(layer)
        start = sum(la.n_channels for la in self.layers[:layer])
        return range(start, start + self.layers[layer].n_channels)

    def channel_position(self, channel: int) -> tuple[int, int, int]:
        """``(layer, row, col)`` of a channel. Raises IndexError outside ``0 .. n_channels - 1``."""
        ch = int(channel)
        if not 0 <= ch < self.n_channels:
            raise IndexError(f"channel {channel} outside 0..{self.n_channels - 1}")
        for i, la in enumerate(self.layers):
            if ch < la.n_channels:
                return i, ch // la.cols, ch % la.cols
            ch -= la.n_channels
        raise AssertionError("unreachable")

    def channel_labels(self) -> tuple[str, ...]:
        """A name per channel: ``channel_names`` if given, else ``"<layer> r<row>c<col>"``."""
        if self.channel_names is not None:
            return self.channel_names
        out = []
        for ch in range(self.n_channels):
            li, r, c = self.channel_position(ch)
            out.append(f"{self.layers[li].name} r{r}c{c}")
        return tuple(out)

    def describe(self) -> str:
        """One line for humans and the ``taxels_channels`` attribute, e.g.
        ``"0-8 top (type I), 9-17 bottom (type II); row-major 3x3; 1000 Hz, 10-bit"``."""
        parts = []
        for i, la in enumerate(self.layers):
            ch = self.layer_channels(i)
            span = f"{ch.start}-{ch.stop - 1}" if len(ch) > 1 else f"{ch.start}"
            parts.append(f"{span} {la.name}" + (f" ({la.receptor})" if la.receptor else ""))
        grids = sorted({f"{la.rows}x{la.cols}" for la in self.layers})
        return (f"{', '.join(parts)}; row-major {'/'.join(grids)}, row 0 leading edge; "
                f"{self.sample_rate_hz:g} Hz, {self.adc_bits}-bit")

    def with_rate(self, sample_rate_hz: float) -> "SensorLayout":
        """The same sensor read at another rate (after resampling)."""
        return SensorLayout(self.layers, self.pitch_mm, sample_rate_hz, self.adc_bits, self.channel_names, self.name)

    def check_readings(self, readings: Any, *, what: str = "taxels") -> np.ndarray:
        """Check that ``readings`` is ``(n_samples, n_channels)``; returns it as an array (no copy).

        Raises
        ------
        LayoutError naming the expected and the given shape.
        """
        arr = np.asarray(readings)
        if arr.ndim != 2 or arr.shape[1] != self.n_channels:
            raise LayoutError(f"{what} must be (n_samples, {self.n_channels}) for the {self.shape_text} sensor "
                              f"({self.describe()}), got {arr.shape}")
        return arr

    # -- storage ---------------------------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """JSON-able description (stored in session and encoded files as the ``sensor_layout`` attribute)."""
        return {
            "name": self.name,
            "layers": [{"name": la.name, "receptor": la.receptor, "rows": la.rows, "cols": la.cols}
                       for la in self.layers],
            "pitch_mm": self.pitch_mm,
            "sample_rate_hz": self.sample_rate_hz,
            "adc_bits": self.adc_bits,
            "channel_names": None if self.channel_names is None else list(self.channel_names),
            "n_channels": self.n_channels,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "SensorLayout":
        """Inverse of :meth:`to_dict`. Raises LayoutError on a missing or malformed key."""
        try:
            layers = tuple(TaxelLayer(str(la["name"]), str(la.get("receptor", "")), int(la["rows"]), int(la["cols"]))
                           for la in d["layers"])
            out = cls(layers, pitch_mm=float(d.get("pitch_mm", 5.0)),
                      sample_rate_hz=float(d.get("sample_rate_hz", 1000.0)), adc_bits=int(d.get("adc_bits", 10)),
                      channel_names=None if d.get("channel_names") is None else tuple(d["channel_names"]),
                      name=str(d.get("name", "")))
        except (KeyError, TypeError, ValueError) as exc:
            if isinstance(exc, LayoutError):
                raise
            raise LayoutError(f"malformed sensor layout {dict(d)!r}: {exc}") from exc
        if "n_channels" in d and int(d["n_channels"]) != out.n_channels:
            raise LayoutError(f"sensor layout says n_channels={d['n_channels']} but its layers have {out.n_channels}")
        return out

    def to_json(self) -> str:
        return json.dumps(self.to_dict())

    @classmethod
    def from_json(cls, text: str | bytes) -> "SensorLayout":
        try:
            return cls.from_dict(json.loads(text))
        except json.JSONDecodeError as exc:
            raise LayoutError(f"sensor layout is not JSON: {exc}") from exc

    @classmethod
    def from_identify(cls, reply: Mapping[str, Any], *, default: "SensorLayout | None" = None) -> "SensorLayout":
        """The layout a taxel board announces in its banner / identify reply (``ch``, ``rate_hz``, ``bits``; optional
        ``layout`` as ``ROWSxCOLSxLAYERS``). Keys missing from the reply come from ``default`` (the paper's sensor).
        """
        base = default or PAPER_SENSOR
        n = int(reply.get("ch", base.n_channels))
        rate = float(reply.get("rate_hz", base.sample_rate_hz))
        bits = int(reply.get("bits", base.adc_bits))
        if reply.get("layout"):
            out = parse_layout(str(reply["layout"]), sample_rate_hz=rate, adc_bits=bits, pitch_mm=base.pitch_mm)
            if out.n_channels != n:
                raise LayoutError(f"the board reports ch={n} but layout {reply['layout']} has {out.n_channels}")
            return out
        if n == base.n_channels:
            return SensorLayout(base.layers, base.pitch_mm, rate, bits, base.channel_names, base.name)
        return SensorLayout.for_channels(n, sample_rate_hz=rate, adc_bits=bits, pitch_mm=base.pitch_mm)


_LAYOUT_RE = re.compile(r"^\s*(\d+)\s*[xX]\s*(\d+)\s*(?:[xX]\s*(\d+))?\s*$")


def parse_layout(text: str, **kw: Any) -> SensorLayout:
    """``"3x3x2"`` (rows x cols x layers) or ``"4x4"`` (one layer) -> :class:`SensorLayout`; keywords as
    :meth:`SensorLayout.grid`.

    Raises
    ------
    LayoutError on text that is not ``ROWSxCOLS[xLAYERS]`` with positive integers.
    """
    m = _LAYOUT_RE.match(str(text))
    if not m:
        raise LayoutError(f"layout must be ROWSxCOLSxLAYERS (e.g. 3x3x2) or ROWSxCOLS, got {text!r}")
    rows, cols, layers = int(m.group(1)), int(m.group(2)), int(m.group(3) or 1)
    if min(rows, cols, layers) < 1:
        raise LayoutError(f"layout {text!r}: every dimension must be >= 1")
    return SensorLayout.grid(rows, cols, layers, **kw)


#: the paper's drum sensor: 3x3x2, top = type I, bottom = type II, 5 mm pitch, 1 kHz, 10-bit (Methods)
PAPER_SENSOR = SensorLayout.grid(3, 3, 2, sample_rate_hz=1000.0, adc_bits=10, pitch_mm=5.0, name="paper 3x3x2")
#: the paper's real-time finger: one 3x3 layer (Results, "Real-time texture classification"), 1 kHz, 10-bit
PAPER_FINGER = SensorLayout.grid(3, 3, 1, sample_rate_hz=1000.0, adc_bits=10, pitch_mm=5.0, name="paper finger 3x3")
