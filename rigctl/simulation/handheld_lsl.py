"""A tracker over Lab Streaming Layer as the handheld rig's motion source (``--motion lsl:NAME``).

:class:`LslTracker` reads a tracker's stream (Vive, OptiTrack, Qualisys bridges publish their positions on LSL): the
channels chosen on the command line, either three (x, y, z in the tracker's frame, mm; the plate's axis calibrated in
the rig config's ``handheld`` block) or one (the position along the plate, mm). Its samples are put on the host clock
with liblsl's clock sync (the inlet's ``time_correction()``, applied to every sample: a tracker on another PC) and the
host <-> LSL offset (:func:`rigctl.core.clocksync.measure_clock_offset`).

:class:`TrackedFingerScans` is a :class:`rigctl.core.handheld.ScanSource` on it (or on any :class:`Tracker`: a
serial motion board, :class:`rigctl.devices.motion.SerialMotion`, ``--motion serial:PORT``): after the cue it waits for the
tracked finger to pass through the plate's used part and beyond, and returns the pass. Its taxel readings come from
the rig's physical sensor model along the tracked path (the simulated finger following a live tracker: a dry run of
the chain with a real tracker and no sensor, and the test of the tracker input); frames 1 ms apart on the host clock.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from rigctl.core.clocksync import measure_clock_offset
from rigctl.core.handheld import PlateAxis, RawScan, ScanError, Tracker, wait_for_pass
from rigctl.core.lsl import open_inlet, require_pylsl, time_correction_s
from rigctl.core.sensor import PAPER_FINGER, SensorLayout
from rigctl.core.textures import PAPER_TEXTURES, TextureSet
from rigctl.core.trial import PlannedTrial
from rigctl.simulation.model import RigConfig, SensorModel
from rigctl.simulation.textures import get_texture

__all__ = ["LslTracker", "Tracker", "TrackedFingerScans", "parse_motion"]

#: the position units a tracker stream may carry, and mm per unit (Motive and Vicon bridges publish metres)
UNITS = {"m": 1000.0, "mm": 1.0}
_UNIT_NAMES = {"m": "m", "meter": "m", "meters": "m", "metre": "m", "metres": "m",
               "mm": "mm", "millimeter": "mm", "millimeters": "mm", "millimetre": "mm", "millimetres": "mm"}


def _declared_units(info: Any, channels: tuple[int, ...]) -> str | None:
    """The unit the stream's channel metadata declares for ``channels`` (XDF's ``desc/channels/channel/unit``): "m",
    "mm", or None (none, another, or the channels disagree)."""
    try:
        ch = info.desc().child("channels").child("channel")
        found = []
        while not ch.empty():
            found.append(_UNIT_NAMES.get(ch.child_value("unit").strip().lower()))
            ch = ch.next_sibling()
    except Exception:  # noqa: BLE001 - metadata a bridge wrote otherwise: not declared
        return None
    units = {found[c] for c in channels if c < len(found)}
    return units.pop() if len(units) == 1 and None not in units and len(found) > max(channels) else None


class LslTracker:
    """The samples of the LSL tracker stream ``name`` (name or source id), channels ``channels``, on the host clock.

    Raises ScanError (no such stream, a channel it does not have), LslUnavailable (no pylsl).
    """

    def __init__(self, name: str, channels: tuple[int, ...] = (0, 1, 2), *, resolve_s: float = 5.0,
                 units: str | None = None) -> None:
        pylsl = require_pylsl()
        self.name = name.removeprefix("lsl:")
        found = (pylsl.resolve_byprop("name", self.name, minimum=1, timeout=resolve_s)
                 or pylsl.resolve_byprop("source_id", self.name, minimum=1, timeout=resolve_s))
        if not found:
            raise ScanError(f"no LSL stream named {self.name!r} (by name or source id) within {resolve_s:g} s")
        # liblsl's clock sync: each sample's time stamp (the publisher's clock, another PC's or another namespace's)
        # plus the inlet's time_correction(), re-measured as the stream goes: the stamps on this machine's LSL clock
        self.inlet = open_inlet(pylsl, found[0])
        n = int(self.inlet.info(timeout=resolve_s).channel_count())
        if len(channels) not in (1, 3) or any(not 0 <= c < n for c in channels):
            raise ScanError(f"LSL stream {self.name!r} has {n} channels: choose 3 (x, y, z, mm) or 1 (along the "
                            f"plate, mm) of 0..{n - 1}, not {list(channels)}")
        self.channels = tuple(channels)
        declared = _declared_units(self.inlet.info(timeout=resolve_s), self.channels)
        if units is not None and units not in UNITS:
            raise ScanError(f"--motion-units must be one of {', '.join(UNITS)}, not {units!r}")
        #: the positions' unit: given (``--motion-units``), else the stream's own channel metadata, else mm
        self.units = units or declared or "mm"
        self.units_from = "given" if units else "stream metadata" if declared else "assumed"
        self._to_mm = UNITS[self.units]
        self.offset_s, _ = measure_clock_offset(pylsl.local_clock, time.monotonic)  # LSL minus host
        self._t: list[np.ndarray] = []
        self._x: list[np.ndarray] = []
        self._arrived: list[np.ndarray] = []  # each sample's arrival on the host clock (its pull), s
        self._lock = threading.Lock()
        self._halt = threading.Event()
        self.inlet.open_stream(timeout=resolve_s)
        self._thread = threading.Thread(target=self._pull, name="lsl-tracker", daemon=True)
        self._thread.start()

    def _pull(self) -> None:
        while not self._halt.is_set():
            try:
                chunk, stamps = self.inlet.pull_chunk(timeout=0.05, max_samples=4096)
            except Exception:  # noqa: BLE001 - a lost stream: nothing arrives, the scan times out
                self._halt.wait(0.2)
                continue
            if stamps:
                arrived = time.monotonic()
                x = np.asarray(chunk, np.float64)[:, list(self.channels)] * self._to_mm
                t = np.asarray(stamps, np.float64) - self.offset_s
                with self._lock:
                    self._t.append(t)
                    self._x.append(x)
                    self._arrived.append(np.full(t.size, arrived))

    def since(self, t0: float) -> tuple[np.ndarray, np.ndarray]:
        """Samples received with host time >= ``t0``: times (k,) s and positions (k, n_channels) mm."""
        t, x, _ = self.since_received(t0)
        return t, x

    def since_received(self, t0: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`since` and each sample's arrival (its pull from the inlet, ``time.monotonic`` s): a sample stamped
        after it arrived, or a pass that arrived before its cue, is refused
        (:func:`rigctl.core.handheld.refuse_older_than_cue`)."""
        with self._lock:
            t = np.concatenate(self._t) if self._t else np.zeros(0)
            x = np.concatenate(self._x) if self._x else np.zeros((0, len(self.channels)))
            a = np.concatenate(self._arrived) if self._arrived else np.zeros(0)
            keep = a >= time.monotonic() - 60.0  # the last minute of arrivals is enough for any scan
            self._t, self._x, self._arrived = [t[keep]], [x[keep]], [a[keep]]
        sel = t >= t0
        return t[sel], x[sel], a[sel]

    def describe(self) -> dict[str, Any]:
        correction = time_correction_s(self.inlet)  # the publisher's clock minus this one's (0 on one machine)
        return {"lsl_stream": self.name, "channels": list(self.channels), "lsl_offset_s": self.offset_s,
                "motion_units": self.units, "motion_units_from": self.units_from,
                "lsl_time_correction_s": correction}

    def close(self) -> None:
        self._halt.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2)
        self.inlet.close_stream()


class TrackedFingerScans:
    """Scans of a tracked finger (module docstring); ``timeout_s`` bounds the wait for one pass."""

    layout: SensorLayout = PAPER_FINGER

    def __init__(self, tracker: Tracker, axis: PlateAxis | None, *, rig_config: RigConfig | None = None,
                 seed: int = 0, textures: TextureSet | None = None, timeout_s: float = 60.0) -> None:
        if len(tracker.channels) == 3 and axis is None:
            raise ScanError("a tracker's x, y, z need the plate's axis: calibrate it (the rig config's handheld block, "
                            "docs/guides/handheld.md), or give the position along the plate as one channel")
        self.tracker, self.axis, self.timeout_s = tracker, axis, float(timeout_s)
        self.sensor = SensorModel((rig_config or RigConfig()).sensor)
        self.textures = textures or PAPER_TEXTURES
        self.seed, self.scans, self.count = int(seed), 0, 0

    def _along(self, x: np.ndarray) -> np.ndarray:
        return x[:, 0] if x.shape[1] != 3 else self.axis.along_mm(x)  # type: ignore[union-attr]  # checked above

    def scan(self, planned: PlannedTrial, *, stop: Callable[[], bool] | None = None) -> RawScan | None:
        """Wait for the finger to enter the used part and pass its end; the pass with rendered readings. Raises
        ScanError when no pass comes within ``timeout_s``."""
        got = wait_for_pass(self.tracker, self._along, time.monotonic(), stop=stop, timeout_s=self.timeout_s)
        if got is None:
            return None
        t, x = got
        along = self._along(x)
        rng = np.random.default_rng([self.seed, 3738, self.scans])
        self.scans += 1
        frames = np.arange(t[0], t[-1], 1e-3)
        pos = np.interp(frames, t, along)
        taxels = self.sensor.render(get_texture(planned.texture, self.textures), pos, 500.0, rng)
        n = frames.size
        seq = ((self.count + np.arange(n)) % 65536).astype(np.uint16)
        self.count += n
        xyz = x.shape[1] == 3
        velocity = x[:, 1] if x.shape[1] == 2 and np.all(np.isfinite(x[:, 1])) else None  # the board's own
        return RawScan(taxels=np.ascontiguousarray(taxels[:, : self.layout.n_channels]), seq=seq, host_time_s=frames,
                       tracker_time_s=t, tracker_xyz=x if xyz else None, along_mm=None if xyz else along,
                       velocity_mm_s=velocity,
                       attrs={"tracker_stream": self.tracker.name, "taxels_from": "sensor model on the tracked path",
                              **getattr(self.tracker, "counters", dict)()})

    def describe(self) -> dict[str, Any]:
        return {"kind": "tracked_finger", **self.tracker.describe(), "taxels": "sensor model on the tracked path",
                "seed": self.seed}

    def link_problem(self) -> str | None:
        problem = getattr(self.tracker, "link_problem", None)
        return problem() if callable(problem) else None

    def close(self) -> None:
        self.tracker.close()


def parse_motion(motion: str) -> tuple[str, tuple[int, ...]]:
    """``lsl:NAME`` -> (NAME, (0, 1, 2)); ``lsl:NAME@3`` -> (NAME, (3,)); ``lsl:NAME@4,5,6`` -> (NAME, (4, 5, 6)):
    the stream and its position channels (x, y, z in mm, or one: along the plate, mm). Raises ScanError."""
    name = motion.removeprefix("lsl:")
    if "@" not in name:
        return name, (0, 1, 2)
    name, _, chans = name.rpartition("@")
    try:
        channels = tuple(int(c) for c in chans.split(","))
    except ValueError:
        raise ScanError(f"{motion}: the channels after @ must be indices, e.g. lsl:{name}@0,1,2 or lsl:{name}@0") \
            from None
    if not name or len(channels) not in (1, 3):
        raise ScanError(f"{motion}: give a stream name and 3 channels (x, y, z) or 1 (along the plate)")
    return name, channels
