"""Compile numba's kernels into numba's on-disk cache ($NUMBA_CACHE_DIR) once, before the test workers start.

scripts/test.sh runs this in the background while the firmware builds and ruff, lint-imports and mypy run (one core
each): every pytest-xdist worker and every ``rigctl`` subprocess of the tests then loads the kernels from the cache
instead of compiling the same ones again (measured: a cold cache adds ~30 s of CPU to the first encoding test of each
process, 165 s of wall time to one test on the loaded 2-core machine). Calls the public functions with the input
types the library and its tests use (uint16 counts and float64 readings; float32 and float64 state; one trial: the
serial kernels, more than a SIMD block: the parallel ones), so the signatures follow the code; a kernel missed here is
still compiled on first use, only slower.
"""

from __future__ import annotations

import time

import numpy as np


def main() -> None:
    t0 = time.monotonic()
    from rigctl.encoding import izhikevich
    from rigctl.encoding.fused import BLOCK_TRIALS, run_fused
    from rigctl.simulation.model import SensorModel

    n = 64
    # first the taxel renderer every simulated rig runs, then the encoder
    force_g = np.full(n, 300.0)
    force_g.flags.writeable = False  # as the dataset renderer passes it
    SensorModel().render("A", np.linspace(0.0, 10.0, n), force_g, np.random.default_rng(0))
    for n_trials in (1, BLOCK_TRIALS + 1):  # the serial and the parallel builds
        starts = np.arange(n_trials + 1, dtype=np.int64) * n
        for data_dtype, dtype in ((np.uint16, np.float32), (np.float64, np.float32), (np.float64, np.float64),
                                  (np.uint16, np.float64)):
            if n_trials > BLOCK_TRIALS and (data_dtype, dtype) == (np.uint16, np.float64):
                continue  # float64 state on counts: the reference checks, one trial at a time
            data = np.full((n * n_trials, 2), 512, dtype=data_dtype)
            # the spike trains (times kernels) and their window counts (the features' binning)
            res = run_fused(data, starts, scale=1 / 1023, dtype=dtype)
            res.ra.window_counts(0.032, 2)
        izhikevich.run_izhikevich(np.full((n_trials, n, 2), 0.5), k=100.0)  # the float64 reference kernels
    print(f"numba kernels compiled into the cache in {time.monotonic() - t0:.0f} s")


if __name__ == "__main__":
    main()
