"""Brian2 side of bench_encoder.py: the same tonic-spiking Izhikevich SA neurons (eqs. 3-5, k = 100) on the same
input, with Brian2's default runtime code-generation target. Run by bench_encoder.py with the Python of
benchmarks/.venv-brian2 (made by brian2_venv.sh) or any Python that imports brian2.

Usage: python brian2_izhikevich.py INPUT.npy OUT.json [runtime|cpp_standalone]
(INPUT: (n_samples, n_neurons) float64, 1 kHz). ``runtime`` (default): Brian2's default target (code generated
per object, cython when it compiles); ``cpp_standalone``: the whole network compiled to one C++ program (its run
time is the program's own measurement, compile time reported apart).

Integration: Euler at dt = 0.5 ms (two updates per 1 ms sample, the closest Brian2 equivalent of our two 0.5 ms
v half-steps; Brian2 also advances u every 0.5 ms). Neuron-steps are counted per 1 ms sample, as for our encoder.
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np


def main(inp: str, out: str, target: str = "runtime") -> None:
    import tempfile

    import brian2 as b2

    x = np.load(inp)
    n_samples, n_neurons = x.shape
    standalone = target == "cpp_standalone"
    build_dir = tempfile.mkdtemp(prefix="brian2_standalone_") if standalone else None
    if standalone:
        b2.set_device("cpp_standalone", directory=build_dir, build_on_run=False)
    t0 = time.perf_counter()
    b2.start_scope()
    b2.defaultclock.dt = 0.5 * b2.ms
    drive = b2.TimedArray(100.0 * x, dt=1 * b2.ms)  # k * I, already dimensionless
    eqs = """
    dv/dt = (0.04*v**2 + 5*v + 140 - u + drive(t, i)) / ms : 1
    du/dt = a*(b*v - u) / ms : 1
    """
    ns = {"a": 0.02, "b": 0.2, "drive": drive}
    g = b2.NeuronGroup(n_neurons, eqs, threshold="v >= 30", reset="v = -65; u = u + 6", method="euler",
                       namespace=ns)
    g.v = -65.0
    g.u = 0.2 * -65.0
    mon = b2.SpikeMonitor(g)
    net = b2.Network(g, mon)
    if standalone:
        net.run(n_samples * b2.ms)
        b2.device.build(directory=build_dir, compile=True, run=True, debug=False)
        total = time.perf_counter() - t0
        t_run = float(b2.device._last_run_time)
        cpu_run = t_run  # one thread: the program's own run time
        t_compile = total - t_run
        steps = int(n_samples * n_neurons)
    else:
        # a short first run compiles the generated code; the timed run is the whole input
        net.run(10 * b2.ms)
        t_compile = time.perf_counter() - t0
        t1, c1 = time.perf_counter(), time.process_time()
        net.run((n_samples - 10) * b2.ms)
        t_run = time.perf_counter() - t1
        cpu_run = time.process_time() - c1
        steps = int((n_samples - 10) * n_neurons)
    counts = np.bincount(np.asarray(mon.i), minlength=n_neurons)
    json.dump({
        "brian2_version": b2.__version__,
        "target": target if standalone else str(b2.get_device().__class__.__name__) + "/" + str(b2.prefs.codegen.target),
        "compile_s": t_compile,
        "run_s": t_run,
        "run_cpu_s": cpu_run,
        "neuron_steps": steps,
        "spike_counts": counts.tolist(),
    }, open(out, "w"))


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], *(sys.argv[3:4]))
