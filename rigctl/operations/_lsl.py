"""A protocol run published on Lab Streaming Layer: :class:`LslPublisher` feeds
:class:`rigctl.acquisition.lsl.LslOutlets` (taxels, SA/RA spikes, drum state, markers).

The taxel stream, its spikes and the drum state are live (:class:`rigctl.operations._lsl_live.LiveLslFeed`): frames
pushed every 25 ms as the reader receives them, for as long as the publisher is open (between trials too), with
their fitted times (the online host <-> board clock fit) on the LSL clock; the spikes of the streaming Izhikevich
encoder (:class:`rigctl.encoding.izhikevich.StreamingEncoder`, paper eqs. 3-5, run over the whole stream, normalised
with the rig's taxel normalisation or the full ADC range); the drum state at every status poll (speed, force,
actuator position). Every run and trial event is one marker (a trial's end at its last sample's fitted time). A
:class:`ProtocolRun` made with ``lsl=`` does this (``rigctl acquire --lsl``, the GUI's toggle, the rig config's
``lsl.enabled``, ``rigctl serve``).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from typing import Any

import numpy as np

from rigctl.acquisition.clock import fitted_times
from rigctl.acquisition.lsl import LslOutlets
from rigctl.acquisition.runner import TrialEvent
from rigctl.core.normalisation import TaxelRange
from rigctl.operations._control import RigControl
from rigctl.operations._lsl_live import LiveLslFeed

log = logging.getLogger(__name__)

__all__ = ["LslPublisher", "lsl_requested"]

#: the marker each trial event becomes
_MARKERS = {"start": "trial_start", "complete": "trial_end", "failed": "fault", "retry": "retry",
            "link_down": "fault", "waiting": "waiting", "texture": "plate_change", "paused": "pause",
            "resumed": "resume"}


def lsl_requested(flag: bool | None, host_config: dict[str, Any] | None) -> bool:
    """Whether a run publishes on LSL: the command's flag when given, else the rig config's ``lsl.enabled``
    (default off)."""
    if flag is not None:
        return bool(flag)
    block = (host_config or {}).get("lsl") or {}
    return bool(block.get("enabled", False))


def _planned_fields(planned: Any) -> dict[str, Any]:
    if planned is None:
        return {}
    d = dataclasses.asdict(planned)
    return {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in d.items()}


class LslPublisher:
    """Publishes a run on the rig ``control`` owns (a :class:`rigctl.operations.RigControl`: a face of it, as the
    CLI and the GUI are) over LSL.

    The taxels, spikes and drum state stream live from here on (:attr:`live`) until :meth:`close` (which pushes what
    is left). Pass :meth:`on_trial` as (or from) the run's ``on_trial``; :meth:`run_marker` for run-level events
    (start, end, abort, STOP); :meth:`session_attrs` for the session file (the streams and the host <-> LSL offset).

    Raises :class:`rigctl.acquisition.lsl.LslUnavailable` when pylsl is missing.
    """

    def __init__(self, control: RigControl, *, name: str | None = None, source_id: str | None = None,
                 protocol_name: str = "", wait_s: float = 0.0) -> None:
        self.control = control
        #: how long a run's ``run_start`` waits for a consumer of the marker stream (:meth:`wait_for_recorder`), s
        self.wait_s = float(wait_s)
        block = control.host_config.get("lsl") or {}
        clock = getattr(control.drum, "clock", None)
        self.outlets = LslOutlets(control.layout, name=name or block.get("name", "rigctl"),
                                  source_id=source_id or block.get("source_id"),
                                  host_clock=clock.now if clock is not None else time.monotonic,
                                  extra_desc={"protocol": protocol_name, "rig": control.mode})
        self.protocol_name = protocol_name
        norm = control.taxel_normalisation()
        layout = control.layout
        self.normaliser = (TaxelRange.from_dict(norm) if norm else
                           TaxelRange(np.zeros(layout.n_channels), np.full(layout.n_channels, float(layout.adc_max))))
        #: markers pushed (their JSON documents), in order
        self.markers: list[dict[str, Any]] = []
        #: the live taxel / spike / drum feed (started here); None on the handheld rig (no drum, no live ring: its
        #: scans' entry and exit go out as ``scan_enter`` / ``scan_leave`` markers at their times)
        self.live: LiveLslFeed | None = None
        self._unlisten = control.on_marker(self._scan_marker)
        if self._unlisten is None:
            self.live = LiveLslFeed(self.outlets, control.taxels, control.drum, self.normaliser)
            self.live.start()

    def session_attrs(self) -> dict[str, Any]:
        """``{"lsl": JSON}``: the streams' names and source ids, the host <-> LSL clock offset."""
        return {"lsl": json.dumps(self.outlets.describe())}

    def wait_for_recorder(self, timeout_s: float | None = None) -> bool:
        """Wait at most ``timeout_s`` (default :attr:`wait_s`) until a consumer (a recorder such as LabRecorder) has
        the marker stream open; True if one has (at once when one already does). liblsl reports whether any
        consumer is connected (``StreamOutlet.wait_for_consumers``), not how many."""
        outlet = self.outlets.outlets.get("markers")
        if outlet is None:
            return False
        timeout = self.wait_s if timeout_s is None else float(timeout_s)
        if outlet.have_consumers():
            return True
        return bool(timeout > 0 and outlet.wait_for_consumers(timeout))

    def run_marker(self, event: str, **fields: Any) -> None:
        """Push a run-level marker (``run_start``, ``run_end``, ``abort``, ``stop``); ``run_start`` first waits up to
        :attr:`wait_s` for a recorder (:meth:`wait_for_recorder`), logging when none came."""
        if event == "run_start" and self.wait_s > 0 and not self.wait_for_recorder():
            log.warning("no LSL consumer of the marker stream after %.1f s: the run starts unrecorded on LSL",
                        self.wait_s)
        self.markers.append(self.outlets.marker(event, protocol=self.protocol_name, **fields))

    def on_trial(self, event: TrialEvent) -> None:
        kind = _MARKERS.get(event.kind)
        if kind is None:
            return
        fields: dict[str, Any] = {"protocol": self.protocol_name, **_planned_fields(event.planned),
                                  "index": event.index, "total": event.total, "attempt": event.attempt}
        if event.error:
            fields["error"] = event.error
        at = None
        if event.kind == "complete" and event.data is not None:
            if self.live is not None:
                self.live.push_pending()  # the trial's frames are out before its end marker
            at, span = self.trial_span(event.data)
            fields.update(span)
        self.markers.append(self.outlets.marker(kind, host_time_s=at, **fields))

    def _scan_marker(self, event: str, host_time_s: float, fields: dict[str, Any]) -> None:
        """A handheld scan's boundary (``scan_enter`` / ``scan_leave``) at its host time."""
        self.markers.append(self.outlets.marker(event, host_time_s=host_time_s, protocol=self.protocol_name,
                                                **fields))

    def trial_span(self, data: Any) -> tuple[float | None, dict[str, Any]]:
        """A recorded trial (:class:`rigctl.core.trial.TrialData`, its frames already streamed live): the fitted host
        time of its last sample (the trial_end marker's time) and its span on the LSL clock."""
        times = fitted_times(data.attrs, data.seq)
        if times is None:  # a trial without clock attributes: its receive times
            origin = float(data.attrs.get("host_time_origin_s", 0.0))
            times = origin + np.asarray(data.host_time_s, dtype=np.float64)
        if not len(times):
            return None, {"n_samples": 0}
        lsl = self.outlets.lsl_time(times[[0, -1]])
        return float(times[-1]), {"first_sample_lsl_s": float(lsl[0]), "last_sample_lsl_s": float(lsl[1]),
                                  "n_samples": int(data.n_samples)}

    def close(self) -> None:
        """Push what the reader has received, stop the live feed, close the outlets (once)."""
        if self.outlets.outlets:
            if self.live is not None:
                self.live.stop()
            if self._unlisten is not None:
                self._unlisten()
            self.outlets.close()
