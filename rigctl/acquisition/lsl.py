"""Lab Streaming Layer outlets of a rig (pylsl, the optional extra ``rigctl[lsl]``; its wheel ships liblsl).

A lab records the rig beside its other instruments with LabRecorder (every stream of the room into one XDF file,
with each stream's clock offsets). :class:`LslOutlets` publishes four streams, named ``<name>-<kind>`` with source
ids ``<source_id>-<kind>`` (a restarted rig is the same stream to LabRecorder):

- ``taxels`` (type ``Tactile``): ``n_channels + 1`` int32 channels at the sensor's rate: the taxels' ADC counts,
  then the board's frame sequence number (``frame_seq``, wraps at 65536: a gap is a lost frame). The XML
  description holds each channel's label, unit (``ADC counts``), type (``taxel`` with its receptor, or ``seq``) and
  grid position (layer, row, col, x/y in mm), and the sensor (``rigctl.core.sensor.SensorLayout``) as JSON.
- ``spikes`` (type ``Spikes``, irregular rate): one int32 channel, one sample per spike, the value the train
  ``type * n_channels + taxel`` (type 0 = SA, 1 = RA), timestamped at the spike's sample; the description lists
  each train.
- ``drum`` (type ``DrumState``): speed_mm_s, force_g, actuator_mm at the drum controller's poll rate (every status
  read, as it is made).
- ``markers`` (type ``Markers``, irregular, string): one JSON object per run event (``{"event": "trial_start",
  "trial_id", "texture", "speed_mm_s", "force_g", "protocol", ...}``, ``trial_end``, ``pause``, ``resume``,
  ``abort``, ``fault``, ...).

Timestamps are on the LSL clock: every sample's fitted host time (:mod:`rigctl.acquisition.clock`: the board's
sequence numbers against host receive times, not the nominal rate) plus the host <-> LSL offset measured when the
outlets open (:func:`rigctl.core.clocksync.measure_clock_offset`). Samples are pushed live, in chunks as the reader
receives them (:class:`rigctl.operations.LslPublisher`), with their acquisition timestamps (LSL and LabRecorder place
them by timestamp, not arrival).

Without pylsl nothing here loads it; :func:`require_pylsl` says what to install when LSL is asked for.
"""

from __future__ import annotations

import json
import platform
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from rigctl.core.clocksync import measure_clock_offset
from rigctl.core.lsl import LslUnavailable, require_pylsl
from rigctl.core.sensor import SensorLayout

__all__ = ["LslUnavailable", "LslOutlets", "require_pylsl", "spike_train_labels"]

#: the stream kinds, in the order they are made
KINDS = ("taxels", "spikes", "drum", "markers")


def spike_train_labels(layout: SensorLayout) -> list[str]:
    """The spike stream's train labels: value ``type * n_channels + taxel`` -> ``"<taxel label> SA"`` / ``RA``."""
    labels = layout.channel_labels()
    return [f"{label} {kind}" for kind in ("SA", "RA") for label in labels]


def _channels(desc: Any, rows: Sequence[Mapping[str, Any]]) -> None:
    chans = desc.append_child("channels")
    for row in rows:
        ch = chans.append_child("channel")
        for k, v in row.items():
            ch.append_child_value(k, str(v))


class LslOutlets:
    """The rig's four LSL outlets (module docstring).

    Parameters
    ----------
    layout : the sensor streamed (channel count, rate, labels, grid).
    name : stream name prefix; source_id : stable source id prefix (default ``rigctl-<host name>-<name>``: the
        same streams to LabRecorder after a restart).
    host_clock : the clock the frames' host times are on (``Rig.drum.clock.now``: the host monotonic clock on a
        real or pty rig, simulated time in-process); the host <-> LSL offset is measured against it.
    extra_desc : more key/values for each stream's ``desc`` (e.g. the session id).

    Raises
    ------
    LslUnavailable
        pylsl (or its liblsl) is missing.
    """

    def __init__(self, layout: SensorLayout, *, name: str = "rigctl", source_id: str | None = None,
                 host_clock: Callable[[], float] = time.monotonic, extra_desc: Mapping[str, Any] | None = None):
        self.pylsl = pylsl = require_pylsl()
        self.layout = layout
        self.name = name
        self.source_id = source_id or f"rigctl-{platform.node() or 'host'}-{name}"
        self.host_clock = host_clock
        #: LSL clock minus host clock (s), and half the bracket it was measured in (s)
        self.lsl_offset_s, self.lsl_offset_uncertainty_s = measure_clock_offset(pylsl.local_clock, host_clock)
        extra = dict(extra_desc or {})
        self.outlets: dict[str, Any] = {}
        self._make("taxels", "Tactile", layout.n_channels + 1, layout.sample_rate_hz, pylsl.cf_int32,
                   self._taxel_channels(), extra)
        self._make("spikes", "Spikes", 1, pylsl.IRREGULAR_RATE, pylsl.cf_int32,
                   [{"label": "train", "unit": "index", "type": "spike"}],
                   {**extra, "trains": json.dumps(spike_train_labels(layout))})
        self._make("drum", "DrumState", 3, pylsl.IRREGULAR_RATE, pylsl.cf_float32,
                   [{"label": "speed_mm_s", "unit": "mm/s", "type": "speed"},
                    {"label": "force_g", "unit": "g", "type": "force"},
                    {"label": "actuator_mm", "unit": "mm", "type": "position"}], extra)
        self._make("markers", "Markers", 1, pylsl.IRREGULAR_RATE, pylsl.cf_string,
                   [{"label": "event", "unit": "JSON", "type": "marker"}], extra)

    def _taxel_channels(self) -> list[dict[str, Any]]:
        layout = self.layout
        rows = []
        for ch, label in enumerate(layout.channel_labels()):
            layer, row, col = layout.channel_position(ch)
            la = layout.layers[layer]
            rows.append({"label": label, "unit": "ADC counts", "type": "taxel", "receptor": la.receptor,
                         "layer": la.name, "row": row, "col": col, "x_mm": col * layout.pitch_mm,
                         "y_mm": row * layout.pitch_mm})
        rows.append({"label": "frame_seq", "unit": "count", "type": "seq"})
        return rows

    def _make(self, kind: str, stype: str, n: int, rate: float, fmt: Any, channels: Sequence[Mapping[str, Any]],
              extra: Mapping[str, Any]) -> None:
        pylsl = self.pylsl
        info = pylsl.StreamInfo(f"{self.name}-{kind}", stype, n, rate, fmt, f"{self.source_id}-{kind}")
        desc = info.desc()
        desc.append_child_value("manufacturer", "rigctl")
        desc.append_child_value("sensor_layout", self.layout.to_json())
        desc.append_child_value("adc_bits", str(self.layout.adc_bits))
        desc.append_child_value("clock", "fitted host time of each frame + host->LSL offset "
                                         f"{self.lsl_offset_s:.9f} s")
        for k, v in extra.items():
            desc.append_child_value(str(k), str(v))
        _channels(desc, list(channels))
        self.outlets[kind] = pylsl.StreamOutlet(info)

    # ------------------------------------------------------------------------------------------------- pushing
    def lsl_time(self, host_time_s: np.ndarray | float) -> np.ndarray:
        """Host times (s) on the LSL clock."""
        return np.asarray(host_time_s, dtype=np.float64) + self.lsl_offset_s

    def now(self) -> float:
        """The host clock's now on the LSL clock."""
        return float(self.lsl_time(self.host_clock()))

    def push_taxels(self, taxels: np.ndarray, seq: np.ndarray, host_time_s: np.ndarray) -> None:
        """``taxels`` (n, n_channels) ADC counts, their ``seq`` (n,) and fitted host times (n,) s."""
        if len(taxels) == 0:
            return
        block = np.empty((len(taxels), self.layout.n_channels + 1), dtype=np.int32)
        block[:, :-1] = taxels
        block[:, -1] = seq
        self.outlets["taxels"].push_chunk(block, self.lsl_time(host_time_s).tolist())

    def push_spikes(self, train: np.ndarray, host_time_s: np.ndarray) -> None:
        """Spikes: train indices (``type * n_channels + taxel``) and their host times (s), any order (sorted here)."""
        if len(train) == 0:
            return
        order = np.argsort(host_time_s, kind="stable")
        self.outlets["spikes"].push_chunk(np.asarray(train, dtype=np.int32)[order].reshape(-1, 1),
                                          self.lsl_time(np.asarray(host_time_s)[order]).tolist())

    def push_drum(self, host_time_s: np.ndarray, speed_mm_s: np.ndarray, force_g: np.ndarray,
                  actuator_mm: np.ndarray | None = None) -> None:
        """The drum state at the poll times (host s)."""
        if len(host_time_s) == 0:
            return
        act = np.full(len(host_time_s), np.nan) if actuator_mm is None else actuator_mm
        block = np.column_stack([speed_mm_s, force_g, act]).astype(np.float32)
        self.outlets["drum"].push_chunk(block, self.lsl_time(host_time_s).tolist())

    def marker(self, event: str, *, host_time_s: float | None = None, **fields: Any) -> dict[str, Any]:
        """Push one marker ``{"event": event, **fields}`` (JSON) at ``host_time_s`` (default now); returns it."""
        doc = {"event": event, **fields}
        t = self.now() if host_time_s is None else float(self.lsl_time(host_time_s))
        self.outlets["markers"].push_sample([json.dumps(doc, default=str)], t)
        return doc

    def describe(self) -> dict[str, Any]:
        """What a session stores about the streams: names, source ids, the host <-> LSL offset."""
        return {"streams": {k: {"name": f"{self.name}-{k}", "source_id": f"{self.source_id}-{k}"} for k in KINDS},
                "lsl_offset_s": self.lsl_offset_s, "lsl_offset_uncertainty_s": self.lsl_offset_uncertainty_s,
                "liblsl_version": int(self.pylsl.library_version())}

    def close(self) -> None:
        self.outlets.clear()

