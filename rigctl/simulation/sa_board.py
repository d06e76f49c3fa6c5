"""The on-board SA encoder on a simulated AVR core: the firmware's ``common/sa_encoder.c`` built for the ATmega328P
or the ATmega2560 (``sa_bench/sa_bench.c``, avr-libc's IEEE software float, or the integer kernel) and run under simavr through the stream
harness ``simavr/sa_stream.c`` (docs/firmware.md, "The on-board SA encoder"): what the board computes for a scan's
readings and window speeds, and the core's cycles per 1 ms step.

The stream protocol (bytes served to the firmware's reads of GPIOR2, its writes of GPIOR0 read back, both
little-endian) is ``sa_bench.c``'s; this module is its one host-side home.
"""

from __future__ import annotations

import re
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rigctl import firmware

__all__ = ["CORES", "KERNELS", "BoardScan", "run_scan"]

#: board -> the simulated core of its stream image (``sa_bench_<board>.elf``); both at 16 MHz
CORES = {"uno": "atmega328p", "mega": "atmega2560"}

#: kernel -> its stream image's name part: the float32 build, or the integer one (-DSA_FIXED)
KERNELS = {"float32": "", "fixed": "fixed_"}

_N_TAXELS = 9  # SA_N_TAXELS
_N_WINDOWS = 20  # SA_N_WINDOWS
_WINDOW_MS = 100  # SA_WINDOW_MS


@dataclass(frozen=True)
class BoardScan:
    """One scan as the board encoded it.

    raster : (n_samples, 9) uint8, 1 where the taxel spiked at that 1 ms sample.
    counts : (9, 20) int64 spikes per 100 ms scaled-time window (speed-scaled, reference 100 mm/s).
    held_windows : real-time windows scaled with the previous speed (theirs came too late).
    cycles_mean, cycles_max : the core's cycles per 1 ms step of the 9 taxels (16 000 = a 1 kHz tick at 16 MHz).
    speed_cycles_mean, speed_cycles_max : the core's cycles per window speed received (``sa_speed``: scaling the
        window(s) waiting for it, once per 100 ms).
    """

    raster: np.ndarray
    counts: np.ndarray
    held_windows: int
    cycles_mean: int
    cycles_max: int
    speed_cycles_mean: int = 0
    speed_cycles_max: int = 0


def _stream_input(x: np.ndarray, taxel_min: np.ndarray, taxel_max: np.ndarray, speeds_cmm: np.ndarray) -> bytes:
    """sa_bench's input: the range, then each sample ('x'), window w's speed once its last sample is in ('s', as
    the host sends it), the speeds of the windows left (the last, partial one), the end of the scan ('f') and a stop
    byte."""
    out = [np.asarray(taxel_min, "<u2").tobytes(), np.asarray(taxel_max, "<u2").tobytes()]
    s = 0
    for t in range(x.shape[0]):
        out.append(b"x" + x[t].astype("<u2").tobytes())
        if (t + 1) % _WINDOW_MS == 0 and s < speeds_cmm.size:
            out.append(b"s" + int(speeds_cmm[s]).to_bytes(2, "little"))
            s += 1
    for w in range(s, speeds_cmm.size):  # the last, partial window's speed (and any the scan did not reach)
        out.append(b"s" + int(speeds_cmm[w]).to_bytes(2, "little"))
    out.append(b"f" + int(speeds_cmm[-1]).to_bytes(2, "little") + b"q")
    return b"".join(out)


def run_scan(x: np.ndarray, taxel_min: np.ndarray, taxel_max: np.ndarray, speeds_cmm: np.ndarray, *,
             board: str = "uno", build: Path | None = None, kernel: str = "float32") -> BoardScan:
    """Encode one scan on the simulated ``board``'s core.

    Parameters
    ----------
    x : (n_samples, 9) ADC counts at 1 kHz (the real-time taxels).
    taxel_min, taxel_max : (9,) ADC counts: the host's normalisation range (integers).
    speeds_cmm : (n_windows >= 1,) each 100 ms real-time window's mean speed, 0.01 mm/s (what the host sends).
    board : "uno" (ATmega328P) or "mega" (ATmega2560).
    build : the firmware build folder (default: :func:`rigctl.firmware.build` with the ``sa-bench`` target).
    kernel : "float32" (``sa_bench_<board>.elf``: the host's live float32 kernel) or "fixed" (``sa_bench_fixed_<board>
        .elf``, built with -DSA_FIXED: the integer kernel of :mod:`rigctl.encoding.fixed_sa`).

    Raises
    ------
    ValueError on shapes or values the board cannot take; subprocess.CalledProcessError if the harness fails.
    """
    x = np.asarray(x)
    speeds = np.asarray(speeds_cmm)
    lo, hi = np.asarray(taxel_min, np.float64), np.asarray(taxel_max, np.float64)
    if x.ndim != 2 or x.shape[1] != _N_TAXELS or x.shape[0] == 0:
        raise ValueError(f"x must be (n > 0, {_N_TAXELS}) ADC counts, got {x.shape}")
    if lo.shape != (_N_TAXELS,) or hi.shape != (_N_TAXELS,) or np.any(lo != np.round(lo)) or np.any(
            hi != np.round(hi)) or np.any(lo < 0) or np.any(hi > 0xFFFF):
        raise ValueError("taxel_min and taxel_max must be 9 integer ADC counts")
    if speeds.ndim != 1 or speeds.size == 0 or np.any(speeds < 0) or np.any(speeds > 0xFFFF):
        raise ValueError("speeds_cmm must be >= 1 speeds in 0.01 mm/s (0..65535)")
    if board not in CORES:
        raise ValueError(f"board must be one of {sorted(CORES)}, got {board!r}")
    if kernel not in KERNELS:
        raise ValueError(f"kernel must be one of {sorted(KERNELS)}, got {kernel!r}")
    build = build if build is not None else firmware.build(targets=("sa-bench",))
    proc = subprocess.run([str(build / "sa_stream"), CORES[board], str(build / f"sa_bench_{KERNELS[kernel]}{board}.elf")],
                          input=_stream_input(x, lo, hi, speeds), capture_output=True, check=True)
    n = x.shape[0]
    out = np.frombuffer(proc.stdout, "<u2")
    err = proc.stderr.decode(errors="replace")
    line = re.search(r"^CYCLES (.*)$", err, re.M)
    speed_line = re.search(r"^SPEEDS (.*)$", err, re.M)
    if out.size != n + _N_TAXELS * _N_WINDOWS + 1 or line is None or speed_line is None:
        raise RuntimeError(f"sa_stream gave {out.size} words for {n} samples: {proc.stderr.decode()[-300:]}")
    cyc = {k: int(v) for k, v in (kv.split("=") for kv in line.group(1).split())}
    spd = {k: int(v) for k, v in (kv.split("=") for kv in speed_line.group(1).split())}
    raster = ((out[:n, None] >> np.arange(_N_TAXELS)) & 1).astype(np.uint8)
    counts = out[n:n + _N_TAXELS * _N_WINDOWS].reshape(_N_TAXELS, _N_WINDOWS).astype(np.int64)
    return BoardScan(raster, counts, int(out[-1]), cyc["mean"], cyc["max"], spd["mean"], spd["max"])
