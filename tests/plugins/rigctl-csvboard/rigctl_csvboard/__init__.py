"""rigctl-csvboard: a taxel board that sends one text line per sample, its ADC counts separated by commas, as a rigctl
rig (docs/guides/my-hardware.md writes it step by step).

The board has no drum: :func:`open_board` returns a :class:`rigctl.core.rig_plugins.SampleSource`, which rigctl
streams through its simulated rig's taxel board (the drum simulated: ``drum=sim``, real time, or ``drum=inprocess``,
a simulated clock). Options (``--rig-option KEY=VALUE``):

- ``port``: the board's serial port (``/dev/ttyUSB0``, or any URL pyserial opens), or ``file``: a CSV file of
  samples, played from the start again at its end (a recording of the board, a bench test);
- ``channels`` (default 4), ``rate_hz`` (default 200), ``adc_bits`` (default 10), ``baud`` (default 115200).
"""

from __future__ import annotations

import collections
import threading
import time
from pathlib import Path

import numpy as np
import numpy.typing as npt

from rigctl.core.rig_plugins import RigOptionError, RigRequest, SampleSource
from rigctl.core.sensor import SensorLayout

__all__ = ["CsvBoard", "open_board", "parse_line"]

#: how many samples the serial reader keeps while rigctl has not taken them, s of samples (more: the oldest go, and
#: rigctl is told: a gap of dropped frames)
BUFFER_S = 10.0
#: how long opening the port waits for the board's first sample, s
FIRST_SAMPLE_S = 5.0
#: the samples held back before the first is handed on, s: the board's lines come in bursts (a USB serial chip sends
#: every few ms), so rigctl's clock asks for a sample a little before its line is there
LATENCY_S = 0.25


def parse_line(line: str, channels: int) -> list[int] | None:
    """One sample of a line: ``channels`` integer counts, or None for a line that is not one (a banner, noise)."""
    words = line.strip().split(",")
    if len(words) != channels:
        return None
    try:
        return [int(w) for w in words]
    except ValueError:
        return None


class CsvBoard:
    """The board's samples (:class:`rigctl.core.rig_plugins.SampleSource`): ``layout``, ``read(n)``, ``close()``.

    From a serial port a reader thread keeps the samples as they come (opening waits for the first); ``read(n)``
    hands on the oldest, at most ``n``, each once: fewer when the board is late (rigctl stores the periods without a
    sample as dropped frames; a repeated sample would be stored as a reading the board never sent). The first ones
    wait until :data:`LATENCY_S` of them are there. When rigctl falls more than :data:`BUFFER_S` behind the board,
    the oldest samples go, and the next reads hand on none for at least as many periods: a gap where they were lost,
    never a silent jump in the counts. From a file ``read(n)`` reads the next ``n`` lines, from the start
    again at the end.
    """

    def __init__(self, layout: SensorLayout, *, port: str | None = None, file: Path | None = None,
                 baud: int = 115200) -> None:
        self.layout = layout
        self._primed = False
        self._buffer: collections.deque[list[int]] = collections.deque(
            maxlen=int(BUFFER_S * layout.sample_rate_hz))
        self._lost = 0  # samples the full buffer let go that rigctl has not yet been told of
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._serial = None
        self._thread: threading.Thread | None = None
        self._lines: list[list[int]] = []
        self._next = 0
        if file is not None:
            rows = [parse_line(line, layout.n_channels) for line in file.read_text().splitlines()]
            self._lines = [r for r in rows if r is not None]
            if not self._lines:
                raise RigOptionError(f"file={file}: no line of {layout.n_channels} comma-separated counts")
        elif port is not None:
            import serial

            try:
                self._serial = serial.serial_for_url(port, baudrate=baud, timeout=0.1)
            except serial.SerialException as exc:
                raise RigOptionError(f"port={port}: {exc}") from None
            self._thread = threading.Thread(target=self._read_port, name="csvboard", daemon=True)
            self._thread.start()
            deadline = time.monotonic() + FIRST_SAMPLE_S
            while not self._buffer and time.monotonic() < deadline:
                time.sleep(0.01)
            if not self._buffer:
                self.close()
                raise RigOptionError(f"port={port}: no line of {layout.n_channels} comma-separated counts came "
                                     f"within {FIRST_SAMPLE_S:g} s (baud {baud}?)")

    def _read_port(self) -> None:
        pending = b""
        while not self._stop.is_set() and self._serial is not None:
            try:
                pending += self._serial.read(max(1, self._serial.in_waiting))
            except Exception:  # noqa: BLE001 - the port is gone: the samples stop (rigctl counts them dropped)
                return
            *lines, pending = pending.split(b"\n")
            for line in lines:
                row = parse_line(line.decode("ascii", "replace"), self.layout.n_channels)
                if row is not None:
                    with self._lock:
                        if len(self._buffer) == self._buffer.maxlen:  # full: the oldest goes, told at the next read
                            self._lost += 1
                        self._buffer.append(row)

    def read(self, n: int) -> npt.NDArray[np.uint16]:
        """At most the next ``n`` samples, ``(m, channels)`` uint16, ``m <= n`` (fewer: the board is late)."""
        out = []
        if self._lines:
            for _ in range(n):
                out.append(self._lines[self._next])
                self._next = (self._next + 1) % len(self._lines)
        elif self._primed or len(self._buffer) >= LATENCY_S * self.layout.sample_rate_hz:
            self._primed = True
            with self._lock:
                if self._lost:  # no sample for these periods: a gap before the samples after the loss
                    self._lost = max(0, self._lost - n)
                else:
                    while self._buffer and len(out) < n:
                        out.append(self._buffer.popleft())
        top = self.layout.adc_max
        rows = np.asarray(out, dtype=np.int64).reshape(len(out), self.layout.n_channels)
        return np.clip(rows, 0, top).astype(np.uint16)

    def describe(self) -> dict[str, object]:
        return {"board": "csvboard", "port": None if self._serial is None else self._serial.port,
                "lines": len(self._lines)}

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2)
        if self._serial is not None:
            self._serial.close()


def open_board(request: RigRequest) -> SampleSource:
    """A taxel board sending one line of comma-separated ADC counts per sample (options port or file, channels,
    rate_hz, adc_bits, baud)."""
    request.check_known(("port", "file", "channels", "rate_hz", "adc_bits", "baud"))
    if ("port" in request.options) == ("file" in request.options):
        raise RigOptionError("the csvboard rig needs port=DEVICE or file=CSV (one of them)")
    layout = SensorLayout.for_channels(request.integer("channels", 4), sample_rate_hz=request.number("rate_hz", 200.0),
                                       adc_bits=request.integer("adc_bits", 10))
    file = Path(request.text("file")) if "file" in request.options else None
    return CsvBoard(layout, port=request.options.get("port") and request.text("port"), file=file,
                    baud=request.integer("baud", 115200))
