"""The handheld rig's real finger: the taxel board's frames beside a live motion source (``--taxel-port PORT`` with
``--motion lsl:NAME`` or ``serial:PORT``).

:class:`BoardFingerScans` is a :class:`rigctl.core.handheld.ScanSource`: after each cue it waits for the tracked
finger to pass the plate's used part (:func:`rigctl.core.handheld.wait_for_pass`) and takes every frame the taxel
board sent from a second before the cue until the frame of the pass's last tracker sample, waited for when a host
starved on a loaded machine has not read it yet as the tracker shows the finger past (the Uno's CRC-checked frames,
from the live ring of its :class:`rigctl.devices.taxel_stream.TaxelStream`; the layout from its identify reply:
``layout=3x3x1`` for the paper's finger; a finger already on its way when a busy host cued it late still has its
entry's frames), and returns the frames with their sequence numbers and host receive times beside the tracker's
samples. The cut
(:func:`rigctl.acquisition.handheld.cut_scan`) puts the frames on the host clock by the board's clock fit
(:class:`rigctl.core.clocksync.DeviceClockFit`: sequence numbers against receive times, the lower envelope, over every
frame every scan took, from the first on) and the tracker's samples are on the host clock already (an LSL stream's
timestamps less the measured LSL <-> host offset; a motion board's own clock fit), so both are cut on one clock.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from rigctl.core.clocksync import DeviceClockFit
from rigctl.core.handheld import PlateAxis, RawScan, ScanError, Tracker, wait_for_pass
from rigctl.core.sensor import SensorLayout
from rigctl.core.textures import PAPER_TEXTURES, TextureSet
from rigctl.core.trial import PlannedTrial
from rigctl.devices.errors import TaxelStreamError
from rigctl.devices.ring import RingBuffer
from rigctl.devices.taxel_stream import StreamStats, TaxelStream

__all__ = ["BoardFingerScans", "open_finger_board"]

#: a scan keeps the board's frames from this long before its cue, s (the tracker's from MARGIN_S before it)
PRE_CUE_S = 1.0
#: the board's ring holds this much more than the longest wait for a pass, s
RING_SPARE_S = 10.0
#: how long a scan waits for the board's frames up to the pass's end once the tracker has shown it, s
FRAMES_WAIT_S = 5.0
#: how often it looks, s
FRAMES_POLL_S = 0.01
#: the frames the board must have sent before the first scan, s of its rate (the stream is flowing)
WARM_UP_S = 0.5
#: how long the board may take to send them, s
WARM_UP_TIMEOUT_S = 10.0


class BoardFingerScans:
    """Scans of the real finger: the taxel board ``taxels`` (open and streaming) and the motion source ``tracker``
    (module docstring). ``axis``: the plate's axis when the tracker gives x, y, z; ``timeout_s`` bounds the wait for
    one pass. Raises ScanError for x, y, z without an axis."""

    def __init__(self, taxels: TaxelStream, tracker: Tracker, axis: PlateAxis | None, *,
                 textures: TextureSet | None = None, timeout_s: float = 60.0) -> None:
        if len(tracker.channels) == 3 and axis is None:
            raise ScanError("a tracker's x, y, z need the plate's axis: calibrate it (the rig config's handheld block, "
                            "docs/guides/handheld.md), or give the position along the plate as one channel")
        self.taxels, self.tracker, self.axis, self.timeout_s = taxels, tracker, axis, float(timeout_s)
        self.textures = textures or PAPER_TEXTURES
        #: the finger's sensor, as the open board's banner announces it (``layout=3x3x1``)
        self.layout: SensorLayout = taxels.layout
        #: the board's clock, fitted over every scan's frames (the cut adds each scan's): a burst of frames held up by
        #: a busy host in one scan is an outlier of a long fit, not the slope of a short one
        self.clock_fit = DeviceClockFit(self.layout.sample_rate_hz)
        self.scans = 0
        self._ring, self._cursor = taxels.ring, 0  # the frames a scan may take: any the ring holds, each once

    @property
    def ring(self) -> RingBuffer:
        """The board's live ring buffer (a live view, the LSL feed): every frame, between scans too."""
        return self.taxels.ring

    @property
    def stats(self) -> StreamStats:
        """The board's link statistics (frames, dropped, CRC errors, connected)."""
        return self.taxels.stats

    def _along(self, x: np.ndarray) -> np.ndarray:
        return x[:, 0] if x.shape[1] != 3 else self.axis.along_mm(x)  # type: ignore[union-attr]  # checked above

    def scan(self, planned: PlannedTrial, *, stop: Callable[[], bool] | None = None) -> RawScan | None:
        """The board's frames from :data:`PRE_CUE_S` before the cue until the finger has passed the plate's used part
        (from its ring: a finger already on its way when a busy host gave the cue late entered the plate with frames
        kept; up to the frame of the pass's last tracker sample, waited for), the pass's tracker samples; None when
        ``stop()``. Raises ScanError (no pass within ``timeout_s``, no frame from the board up to the pass's end
        within :data:`FRAMES_WAIT_S`)."""
        t_cue = time.monotonic()
        ring, before = self.taxels.ring, self.taxels.stats
        # never a frame an earlier scan took: the clock fit takes each frame once, in order
        start = max(ring.total - int(PRE_CUE_S * self.layout.sample_rate_hz), self._cursor if ring is self._ring else 0)
        got = wait_for_pass(self.tracker, self._along, t_cue, stop=stop, timeout_s=self.timeout_s)
        if got is None:
            return None
        t, x = got
        if not self._frames_cover(ring, start, float(t[-1]), t_cue, stop):
            return None
        self._cursor, samples, seq, host_time_s = ring.read_since(start)
        self._ring = ring
        after = self.taxels.stats
        self.scans += 1
        xyz = x.shape[1] == 3
        velocity = x[:, 1] if x.shape[1] == 2 and np.all(np.isfinite(x[:, 1])) else None  # a motion board's own
        return RawScan(taxels=samples, seq=seq, host_time_s=host_time_s, tracker_time_s=t,
                       tracker_xyz=x if xyz else None, along_mm=None if xyz else x[:, 0], velocity_mm_s=velocity,
                       attrs={"tracker_stream": self.tracker.name, "taxels_from": f"taxel board on {self.taxels.port}",
                              "taxel_crc_errors": int(after.crc_errors - before.crc_errors),
                              "taxel_dropped_frames": int(after.dropped - before.dropped),
                              **getattr(self.tracker, "counters", dict)()}, clock_fit=self.clock_fit)

    def _frames_cover(self, ring: RingBuffer, start: int, until_s: float, t_cue: float,
                      stop: Callable[[], bool] | None) -> bool:
        """Wait until the ring holds the board's frames up to host time ``until_s`` (the pass's last tracker sample):
        until its newest frame's time on the board's fitted clock is at or past it. The board sent them on time; a
        host starved on a loaded machine may not have read them yet when the tracker shows the finger past the plate,
        and a scan that took its frames then would lose the pass's last ones. False when ``stop()`` turned true.
        Raises ScanError when the board sent no frame since the cue, or none that late within
        :data:`FRAMES_WAIT_S`."""
        deadline = time.monotonic() + FRAMES_WAIT_S
        while True:
            _, seq, host_time_s = ring.timing_since(start)
            if len(seq) and host_time_s[-1] >= t_cue:
                newest = float(self.clock_fit.preview(seq, host_time_s)[-1])
                if not newest < until_s:  # past it, or no fit yet (NaN): the frames received are all there is
                    return True
            if stop is not None and stop():
                return False
            if time.monotonic() > deadline:
                raise ScanError(f"no frame from the taxel board on {self.taxels.port} up to the end of the pass "
                                f"within {FRAMES_WAIT_S:g} s (is it streaming?)")
            time.sleep(FRAMES_POLL_S)

    def describe(self) -> dict[str, Any]:
        banner = dict(self.taxels.banner or {})
        return {"kind": "taxel_board_finger", **self.tracker.describe(), "taxels": "taxel board",
                "taxel_port": self.taxels.port, "taxel_board": {k: banner[k] for k in sorted(banner)
                                                                if isinstance(banner[k], str | int | float)}}

    def link_problem(self) -> str | None:
        """The taxel board or the motion source not answering, in words; None when both are up."""
        if not self.taxels.stats.connected:
            return f"the taxel board on {self.taxels.port} is not connected"
        problem = getattr(self.tracker, "link_problem", None)
        return problem() if callable(problem) else None

    def close(self) -> None:
        try:
            self.taxels.close()
        finally:
            self.tracker.close()


def open_finger_board(port: str, tracker: Tracker, axis: PlateAxis | None, *, textures: TextureSet | None = None,
                      timeout_s: float = 60.0, banner_timeout_s: float = 3.0) -> BoardFingerScans:
    """Open the taxel board on ``port`` (its banner and identify reply give the layout), start it streaming, and make
    the scan source on it and ``tracker``. On any failure the board and the tracker are closed. Raises ScanError
    (one line naming the port) or TaxelStreamError."""
    stream = TaxelStream(port, banner_timeout_s=banner_timeout_s, ring_seconds=timeout_s + PRE_CUE_S + RING_SPARE_S)
    try:
        try:
            stream.open()
            stream.start()
            # the stream flowing before the first cue: the frame parser's kernel is loaded by the first frames, and
            # frames held up meanwhile would arrive in a burst that bends the first scan's clock fit
            stream.begin_capture()
            flowing = stream.wait_capture(int(WARM_UP_S * stream.layout.sample_rate_hz), WARM_UP_TIMEOUT_S)
            stream.end_capture()
        except (OSError, TaxelStreamError) as exc:
            raise ScanError(f"cannot open the finger's taxel board on {port}: {exc}") from None
        if not flowing:
            raise ScanError(f"the finger's taxel board on {port} sent no frames within {WARM_UP_TIMEOUT_S:g} s of "
                            "START")
        # the fit starts with the first scan's frames (a second before its cue on), each frame fed once, in order
        return BoardFingerScans(stream, tracker, axis, textures=textures, timeout_s=timeout_s)
    except BaseException:
        stream.close()
        tracker.close()
        raise
