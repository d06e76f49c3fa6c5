"""Compile numba's kernels into numba's on-disk cache ($NUMBA_CACHE_DIR) once, before the test workers start.

scripts/test.sh runs its two parts (:data:`PARTS`) side by side while the firmware builds and ruff and lint-imports
run, and starts pytest when they are done: every pytest-xdist worker, every process the GUI tests spawn and every
``rigctl`` subprocess of the tests then loads the kernels from the cache instead of compiling the same ones again
(measured: tests/gui/test_gui_analysis.py alone takes 57 CPU-s on a cold cache, 33 on a warm one; compiled in the
background beside the tests, the cache was ready after 87 s of a loaded run, and the tests that came first compiled
their own). Calls the public functions with the input types the library and its tests use (uint16 counts and float64
readings; float32 and float64 state), so the signatures follow the code; a kernel missed here is still compiled on
first use, only slower.

    python scripts/compile_kernels.py [--if-stale] [serial|parallel ...]   (no part: both, one after the other)

Each part compiled leaves a stamp in the cache folder (``rigctl-kernels-<part>``: the digest of rigctl's modules that
cache kernels and of the interpreter's version); ``--if-stale`` compiles only the parts whose stamp is not the
current one, and otherwise imports nothing of rigctl's (tests/conftest.py runs it so at every test session's start:
a module run as the README says then never compiles the kernels inside a test's timeout, issue 79 item 7).
"""

from __future__ import annotations

import hashlib
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

#: the parts that can compile side by side (``python scripts/compile_kernels.py PART``): disjoint sets of kernels, so
#: two processes never write the same kernel's cache index at once (one kernel's signatures share one index):
#: ``serial``, the fused encoder's one build for every input type (~4 s of CPU each) and its spike
#: times (~14 s); ``parallel`` (the name scripts/test.sh passes), the rest: the simulated rig's kernels, the spike
#: trains' window counts and row gather and the float64 reference encoder (~5 s)
PARTS = ("serial", "parallel")


def compile_rig() -> None:
    """The rig's kernels: the simulated rig's taxel renderer, slow noise and mechanics, and the taxel link's frame encoders
    (the simulated Uno's stream), parser and CRC (every rig's host side; ~1.7 CPU-s to compile, which every process
    that started before the cache held them paid). Runs on the calling thread alone: none is a parallel build, so
    numba's thread pool does not start (tests/launcher.py loads these before it forks its commands; GNU OpenMP's pool
    must not be running at a fork)."""
    from rigctl.devices import wire
    from rigctl.devices.frames import FrameParser, encode_frames, encode_stream_frames
    from rigctl.simulation.model import RigModel, SensorModel
    from rigctl.simulation.noise import one_pole

    n = 64
    force_g = np.full(n, 300.0)
    force_g.flags.writeable = False  # as the dataset renderer passes it
    SensorModel().render("A", np.linspace(0.0, 10.0, n), force_g, np.random.default_rng(0))
    RigModel().advance(3, drum_step_rate_hz=0.0, actuator_velocity_mm_s=0.0)
    one_pole(0.5, 0.5, np.zeros(n))  # the dataset renderer's and the simulated operator's slow noise
    samples = np.zeros((4, wire.N_TAXELS), np.uint16)
    FrameParser().feed(encode_frames(np.arange(4), 0, samples)
                       + encode_stream_frames(4, np.zeros(4, bool), True, samples, wire.ADC_MAX))
    encode_frames(np.zeros(1), 0, samples[:1])  # one frame: read-only views, a signature of its own (the virtual Uno's warm-up)
    wire.crc16_rows(np.zeros((2, 5), np.uint8))


def compile_serial() -> None:
    """The fused encoder's build for every input type (one build: one block of trials, or more on threads) and its
    spike times."""
    from rigctl.encoding.fused import run_fused

    n = 64
    for data_dtype, dtype in ((np.uint16, np.float32), (np.float64, np.float32), (np.float64, np.float64),
                              (np.uint16, np.float64)):
        run_fused(np.full((n, 2), 512, dtype=data_dtype), np.array([0, n]), scale=1 / 1023, dtype=dtype)


def compile_parallel() -> None:
    """:func:`compile_rig`, then the features' binning, the spike trains' row gather, and the float64 reference and its
    spike times."""
    from rigctl.encoding import izhikevich
    from rigctl.encoding.spikes import SpikeTrains

    compile_rig()
    trains = SpikeTrains(np.linspace(0.0, 0.06, 8), np.array([4, 8]), 2)
    trains.window_counts(0.032, 2)  # the features' binning
    trains.select_trials([0])
    izhikevich.encode(np.full((1, 64, 2), 0.5), k=100.0)


def sources_digest() -> str:
    """The digest of rigctl's modules that cache numba kernels (``cache=True``) and of the interpreter's version."""
    h = hashlib.sha256(sys.version.encode())
    for path in sorted((REPO / "rigctl").rglob("*.py")):
        text = path.read_bytes()
        if b"cache=True" in text:
            h.update(path.relative_to(REPO).as_posix().encode() + b"\0" + text)
    return h.hexdigest()


def _stamp(part: str) -> Path:
    """The part's stamp in numba's cache folder (rigctl's choice of it: ``rigctl.core.caches.numba_cache_dir``)."""
    from rigctl.core.caches import numba_cache_dir

    return numba_cache_dir() / f"rigctl-kernels-{part}"


def main(argv: list[str]) -> int:
    if_stale = "--if-stale" in argv
    parts = [a for a in argv if a != "--if-stale"] or list(PARTS)
    if any(p not in PARTS for p in parts):
        print(f"usage: python scripts/compile_kernels.py [--if-stale] [{'|'.join(PARTS)}] ...", file=sys.stderr)
        return 2
    digest = sources_digest()
    if if_stale:
        parts = [p for p in parts if not (_stamp(p).is_file() and _stamp(p).read_text() == digest)]
        if not parts:
            return 0
    t0 = time.monotonic()
    if "parallel" in parts:  # first the taxel renderer and the mechanics every simulated rig runs
        compile_parallel()
    if "serial" in parts:
        compile_serial()
    for p in parts:
        os.makedirs(_stamp(p).parent, exist_ok=True)
        _stamp(p).write_text(digest)
    print(f"numba kernels ({', '.join(parts)}) compiled into the cache in {time.monotonic() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
