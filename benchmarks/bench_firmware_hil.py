"""Firmware-in-the-loop benchmark: Modbus round trip, stream rate and the Uno's ISR budget, side by side with the
Python virtual boards of the simulated rig (ratios, one run).

- Modbus round trip of DrumClient.read_status() (13 input registers) and of a one-register write: firmware under
  simavr vs rigctl.simulation.virtual_mega, against the wire's own floor (request + t3.5 + reply at the link's rate, wire.DRUM_BAUD).
- Taxel stream: frames/s received by TaxelStream over --seconds, firmware vs virtual Uno (target 1000, zero lost).
- Uno sampler ISR cycles per 1 ms tick (probe pins timed by the harness), against the tick's 16000 cycles.

Usage: python benchmarks/bench_firmware_hil.py [--seconds 5] [--json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

from rigctl.devices import wire
from rigctl.devices.drum import DrumClient
from rigctl.devices.taxel_stream import TaxelStream
from rigctl.devices.wire import HoldingRegister as HR

_KBAUD = wire.DRUM_BAUD / 1000  # bits per ms; 11 bit times a byte in simavr, t3.5 = 1.75 ms above 19200 baud
WIRE_FLOOR_MS = {"read_status": (8 + 31) * 11 / _KBAUD + 1.75, "write_1": (8 + 8) * 11 / _KBAUD + 1.75}


def measure(rig, seconds: float) -> dict:
    out = {}
    with DrumClient(rig.drum_port) as d:
        d.read_status()
        for name, fn in (("read_status", d.read_status), ("write_1", lambda: d.write_holding(HR.SETTLE_TIME_MS, 300))):
            ts = []
            for _ in range(60):
                t = time.perf_counter()
                fn()
                ts.append((time.perf_counter() - t) * 1e3)
            out[f"rtt_{name}_median_ms"] = statistics.median(ts)
            out[f"rtt_{name}_p10_ms"] = sorted(ts)[6]
    with TaxelStream(rig.taxel_port) as s:
        s.start()
        time.sleep(0.5)
        s.begin_capture()
        time.sleep(seconds)
        cap = s.end_capture()
        span = cap.host_time_s[-1] - cap.host_time_s[0] if len(cap.seq) > 1 else float("nan")
        out["frames_per_s"] = (len(cap.seq) - 1) / span
        out["frames_lost"] = cap.dropped + cap.crc_errors
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    from rigctl.simulation.hil import HilRig
    from rigctl.simulation.rig import SimulatedRig

    with SimulatedRig() as sim:
        py = measure(sim, args.seconds)
    with HilRig() as hil:
        fw = measure(hil, args.seconds)
        isr = dict(hil.isr)
    if args.json:
        print(json.dumps({"python": py, "firmware": fw, "isr": isr, "wire_floor_ms": WIRE_FLOOR_MS}, indent=1))
        return
    print(f"{'metric':32s} {'virtual boards':>15s} {'firmware/simavr':>16s} {'ratio fw/py':>12s}")
    for k in py:
        print(f"{k:32s} {py[k]:15.2f} {fw[k]:16.2f} {fw[k] / py[k] if py[k] else float('nan'):12.2f}")
    for k, v in WIRE_FLOOR_MS.items():
        print(f"wire floor {k:21s} {v:15.2f} ms; firmware median / floor = {fw[f'rtt_{k}_median_ms'] / v:.2f}")
    if isr:
        print(f"Uno sampler ISR: {isr['sampler_cycles_per_tick']:.0f} cycles/tick mean, {isr['sampler_max_per_tick']:.0f}"
              f" max = {isr['sampler_max_per_tick'] / 16000:.1%} of the tick; UART TX ISR {isr['tx_cycles_per_tick']:.0f}")


if __name__ == "__main__":
    main()
