"""Compile numba's kernels into numba's on-disk cache ($NUMBA_CACHE_DIR) once, before the test workers start.

scripts/test.sh runs its two parts (:data:`PARTS`) side by side while the firmware builds and ruff and lint-imports
run, and starts pytest when they are done: every pytest-xdist worker, every process the GUI tests spawn and every
``rigctl`` subprocess of the tests then loads the kernels from the cache instead of compiling the same ones again
(measured: tests/gui/test_gui_analysis.py alone takes 57 CPU-s on a cold cache, 33 on a warm one; compiled in the
background beside the tests, the cache was ready after 87 s of a loaded run, and the tests that came first compiled
their own). Calls the public functions with the input types the library and its tests use (uint16 counts and float64
readings; float32 and float64 state; one trial and more than a SIMD block: numba's serial and parallel builds where a
kernel has both), so the signatures follow the code; a kernel missed here is still compiled on first use, only slower.

    python scripts/compile_kernels.py [serial|parallel ...]   (no part: both, one after the other)
"""

from __future__ import annotations

import sys
import time

import numpy as np

#: the parts that can compile side by side (``python scripts/compile_kernels.py PART``): disjoint sets of kernels, so
#: two processes never write the same kernel's cache index at once: the serial builds (the simulated rig's renderer
#: and mechanics, the fused encoder for every input type and its spike times, the float64 reference; ~18 s of CPU) and
#: numba's parallel builds (the fused encoder on raw counts, the spike trains' window counts; ~11 s)
PARTS = ("serial", "parallel")


def compile_rig() -> None:
    """The simulated rig's kernels: the taxel renderer and the mechanics (every simulated rig runs them). Runs on the
    calling thread alone: neither is a parallel build, so numba's thread pool does not start (tests/launcher.py
    loads these before it forks its commands; GNU OpenMP's pool must not be running at a fork)."""
    from rigctl.simulation.model import RigModel, SensorModel

    n = 64
    force_g = np.full(n, 300.0)
    force_g.flags.writeable = False  # as the dataset renderer passes it
    SensorModel().render("A", np.linspace(0.0, 10.0, n), force_g, np.random.default_rng(0))
    RigModel().advance(3, drum_step_rate_hz=0.0, actuator_velocity_mm_s=0.0)


def compile_serial() -> None:
    """The serial builds: :func:`compile_rig`, then the fused encoder's serial build for every input type (one block
    of trials, or more on threads) and its spike times, and the float64 reference (these start numba's thread pool:
    their spike times and counts use parallel helpers)."""
    from rigctl.encoding import izhikevich
    from rigctl.encoding.fused import run_fused

    compile_rig()
    n = 64
    for data_dtype, dtype in ((np.uint16, np.float32), (np.float64, np.float32), (np.float64, np.float64),
                              (np.uint16, np.float64)):
        run_fused(np.full((n, 2), 512, dtype=data_dtype), np.array([0, n]), scale=1 / 1023, dtype=dtype)
    izhikevich.encode(np.full((1, n, 2), 0.5), k=100.0)  # the float64 reference and its spike times


def compile_parallel() -> None:
    """numba's parallel builds: the fused encoder on raw counts (more than a SIMD block of trials), the features'
    binning."""
    from rigctl.encoding.fused import BLOCK_TRIALS, run_fused
    from rigctl.encoding.spikes import SpikeTrains

    n, n_trials_big = 64, BLOCK_TRIALS + 1
    starts = np.arange(n_trials_big + 1, dtype=np.int64) * n
    run_fused(np.full((n * n_trials_big, 2), 512, dtype=np.uint16), starts, scale=1 / 1023, want_times=False)
    SpikeTrains(np.linspace(0.0, 0.06, 8), np.array([4, 8]), 2).window_counts(0.032, 2)


def main(argv: list[str]) -> int:
    parts = argv or list(PARTS)
    if any(p not in PARTS for p in parts):
        print(f"usage: python scripts/compile_kernels.py [{'|'.join(PARTS)}] ...", file=sys.stderr)
        return 2
    t0 = time.monotonic()
    if "serial" in parts:  # first the taxel renderer and the mechanics every simulated rig runs
        compile_serial()
    if "parallel" in parts:
        compile_parallel()
    print(f"numba kernels ({', '.join(parts)}) compiled into the cache in {time.monotonic() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
