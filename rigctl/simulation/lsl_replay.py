"""A replay source fed live by a Lab Streaming Layer stream: a lab's own taxel device (or another rigctl) publishes
its readings on LSL and the simulated rig's taxel board streams them (``rigctl acquire --replay lsl:NAME``).

:class:`LslReplay` resolves the stream by name or source id (``lsl:NAME``), opens an inlet and hands the samples on
in order, ``read(n) -> (n, channels) uint16``, as the simulated board's clock asks for them. A reader thread pulls
the inlet; ``read`` never blocks (it is called from the simulation's physics step, which paces the drum controller
too): the source starts once ``prebuffer_s`` of samples are in, so the stream's delivery jitter is absorbed.

The layout is the stream's: a rigctl taxel stream's ``sensor_layout`` description (its ``frame_seq`` channel
dropped), else ``SensorLayout.for_channels(channel_count)`` at the stream's nominal rate and
``adc_bits`` (10 unless the description says). Values are clipped to the ADC range. When the stream falls behind
the board's clock (its delivery held up longer than ``prebuffer_s``), ``read`` gives what it has and the board sends
no frame for the rest: the host counts them as lost frames (a trial that lost frames is recorded again), none is
invented. The source then holds back until ``prebuffer_s`` of samples are in again, so the next jitter is absorbed
as the first was (without it, every later chunk of the stream would arrive just too late); the periods without a
sample are counted (:attr:`LslReplay.underrun_samples`, logged).
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from typing import Any

import numpy as np

from rigctl.core.lsl import open_inlet, require_pylsl, time_correction_s
from rigctl.core.sensor import SensorLayout

__all__ = ["LSL_PREFIX", "LslReplay", "LslReplayError"]

log = logging.getLogger(__name__)

#: the ``--replay`` prefix naming an LSL stream
LSL_PREFIX = "lsl:"


class LslReplayError(RuntimeError):
    """The LSL stream cannot be found or opened, or has no regular rate."""


class LslReplay:
    """The samples of the LSL stream ``name`` (a stream name or source id; ``lsl:`` prefix allowed).

    Parameters
    ----------
    name : stream name or source id.
    resolve_s : how long to look for the stream, s.
    prebuffer_s : samples (in s of the stream) held back before the first read, to absorb delivery jitter.
    adc_bits : the readings' ADC resolution when the stream's description does not give it.

    Raises LslReplayError (no such stream, an irregular-rate stream), LslUnavailable (no pylsl).
    """

    def __init__(self, name: str, *, resolve_s: float = 5.0, prebuffer_s: float = 0.25, adc_bits: int = 10) -> None:
        pylsl = require_pylsl()
        self.name = name.removeprefix(LSL_PREFIX)
        found = (pylsl.resolve_byprop("name", self.name, minimum=1, timeout=resolve_s)
                 or pylsl.resolve_byprop("source_id", self.name, minimum=1, timeout=resolve_s))
        if not found:
            raise LslReplayError(f"no LSL stream named {self.name!r} (by name or source id) within {resolve_s:g} s")
        self.inlet = open_inlet(pylsl, found[0])  # liblsl's clock sync: the stamps on this machine's LSL clock
        info = self.inlet.info(timeout=resolve_s)
        rate = float(info.nominal_srate())
        if not rate > 0:
            raise LslReplayError(f"LSL stream {self.name!r} has no regular rate (nominal_srate {rate:g}): it cannot "
                                 "feed a taxel board")
        n = int(info.channel_count())
        desc = info.desc()
        self.drop_seq = desc.child("channels").last_child().child_value("label") == "frame_seq"
        layout_json = desc.child_value("sensor_layout")
        bits = int(desc.child_value("adc_bits") or adc_bits)
        if layout_json:
            self.layout = SensorLayout.from_json(layout_json).with_rate(rate)
        else:
            self.layout = SensorLayout.for_channels(n - int(self.drop_seq), sample_rate_hz=rate, adc_bits=bits)
        self.underrun_samples = 0
        self.samples_read = 0
        #: the first and the last sample's stamps received, on this machine's LSL clock (the clock sync's), s
        self.first_stamp_s = self.last_stamp_s = float("nan")
        self._prebuffer = max(1, int(prebuffer_s * rate))
        self._refilling = False  # after an underrun: nothing is given until the prebuffer is full again
        self._pending: list[np.ndarray] = []
        self._n_pending = 0
        self._lock = threading.Lock()
        self._halt = threading.Event()
        self.inlet.open_stream(timeout=resolve_s)
        self._thread = threading.Thread(target=self._pull_loop, name="lsl-replay", daemon=True)
        self._thread.start()
        want = self._prebuffer
        deadline = time.monotonic() + resolve_s
        while self._n_pending < want and time.monotonic() < deadline:
            time.sleep(0.01)
        if self._n_pending < want:
            self.close()
            raise LslReplayError(f"LSL stream {self.name!r} delivered {self._n_pending} samples in {resolve_s:g} s, "
                                 f"fewer than the {want} of {prebuffer_s:g} s it must hold before streaming")

    def _pull_loop(self) -> None:
        while not self._halt.is_set():
            try:
                chunk, stamps = self.inlet.pull_chunk(timeout=0.1, max_samples=65536)
            except Exception as exc:  # noqa: BLE001 - a lost stream: read() fills and counts
                log.warning("LSL stream %r: %s", self.name, exc)
                self._halt.wait(0.5)
                continue
            if stamps:
                if math.isnan(self.first_stamp_s):  # the first chunk
                    self.first_stamp_s = float(stamps[0])
                self.last_stamp_s = float(stamps[-1])
                x = np.asarray(chunk, dtype=np.float64)
                if self.drop_seq:
                    x = x[:, :-1]
                x = np.clip(np.rint(x), 0, self.layout.adc_max).astype(np.uint16)
                with self._lock:
                    self._pending.append(x)
                    self._n_pending += len(x)

    def read(self, n: int) -> np.ndarray:
        """The next samples of ``n`` due, ``(m, n_channels)`` uint16 with ``m <= n``, at once: what the stream has
        delivered; fewer when it fell behind (the missing ``n - m`` are counted in :attr:`underrun_samples`; after an
        underrun none until the prebuffer is full again)."""
        with self._lock:
            if self._refilling and self._n_pending >= self._prebuffer:
                self._refilling = False
                log.info("LSL stream %r: %d samples buffered again, the taxel board streams it on", self.name,
                         self._n_pending)
            take = 0 if self._refilling else min(n, self._n_pending)
            have = np.concatenate(self._pending) if len(self._pending) > 1 else (
                self._pending[0] if self._pending else np.zeros((0, self.layout.n_channels), np.uint16))
            out, rest = have[:take], have[take:]
            self._pending = [rest] if len(rest) else []
            self._n_pending = len(rest)
            missing = n - len(out)
            started = missing > 0 and not self._refilling
            self._refilling = self._refilling or missing > 0
        self.samples_read += len(out)
        if missing:
            self.underrun_samples += missing
            if started:
                log.warning("LSL stream %r fell behind the taxel board: no frame until %d samples are buffered again "
                            "(%d periods without a sample so far)", self.name, self._prebuffer, self.underrun_samples)
        return out

    def describe(self) -> dict[str, Any]:
        return {"lsl_stream": self.name, "samples_read": self.samples_read, "underrun_samples": self.underrun_samples,
                "layout": json.loads(self.layout.to_json()), "lsl_time_correction_s": time_correction_s(self.inlet),
                "lsl_first_stamp_s": self.first_stamp_s, "lsl_last_stamp_s": self.last_stamp_s}

    def close(self) -> None:
        self._halt.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=2)
        self.inlet.close_stream()
