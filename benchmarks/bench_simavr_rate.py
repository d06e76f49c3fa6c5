"""simavr on the rig's one clock (issue 54): simulated seconds per wall second of the firmware under simavr, unpaced
(``HilRig(paced=False)``) and paced, for the Mega alone and for both boards, side by side.

The host waits on the rig's clock (``rig.clock.sleep``: it grants the cores time as it goes, docs/architecture.md
"Time on a simulated rig") for ``--seconds`` of simulated time; each run is idle firmware after boot (the Mega's
loop and its HX711 at 80 SPS; the Uno stopped: since 2026-11-28 it scans nothing then and sleeps with its ADC off),
then the same with the drum turning at 60 mm/s and the Uno streaming 1000 frames/s to a TaxelStream reader.
Reported: simulated s / wall s, and the CPU seconds of the harness processes per simulated second (both, and each
board's). The fault campaign drives the firmware this way: ``with HilRig(paced=False, ...) as rig``, its clients on
``rig.clock`` (found by the port), its waits ``rig.clock.sleep`` / ``rig.clock.wait_for``.

Usage: python benchmarks/bench_simavr_rate.py [--seconds 10] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import time

from rigctl.devices.drum import DrumClient
from rigctl.devices.taxel_stream import TaxelStream
from rigctl.devices.wire import DrumState
from rigctl.simulation.hil import HilRig


def _children_cpu() -> float:
    t = os.times()
    return t.children_user + t.children_system


def _harness_cpu(rig: HilRig) -> tuple[float, float]:
    """CPU seconds of the live harness processes so far (/proc/PID/stat utime + stime): (Mega's, Uno's)."""
    cpu = []
    for h in (rig._mega, rig._uno):
        total = 0.0
        if h is not None:
            with open(f"/proc/{h.proc.pid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
            total = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
        cpu.append(total)
    return cpu[0], cpu[1]


def run(paced: bool, with_uno: bool, seconds: float, busy: bool) -> dict:
    with HilRig(paced=paced, with_uno=with_uno, live=False) as rig:
        drum = DrumClient(rig.drum_port, timeout_s=2.0).open()
        stream = TaxelStream(rig.taxel_port, banner_timeout_s=10.0) if with_uno and busy else None
        try:
            if busy:
                drum.home()
                drum.wait_state([DrumState.IDLE], timeout_s=30)
                drum.set_speed(60.0)
                drum.run()
                if stream is not None:
                    stream.open()
                    stream.start()
            rig.clock.sleep(0.5)  # settled
            t0, w0, c0 = rig.clock.now(), time.monotonic(), _harness_cpu(rig)
            rig.clock.sleep(seconds)
            (mega1, uno1), (mega0, uno0) = _harness_cpu(rig), c0
            sim_s, wall_s = rig.clock.now() - t0, time.monotonic() - w0
            cpu_s, mega_s, uno_s = mega1 + uno1 - mega0 - uno0, mega1 - mega0, uno1 - uno0
            frames = stream.stats.frames if stream is not None else None
        finally:
            if stream is not None:
                stream.close()
            drum.close()
    return {"paced": paced, "boards": "both" if with_uno else "mega", "load": "busy" if busy else "idle",
            "sim_s": round(sim_s, 3), "wall_s": round(wall_s, 3), "sim_per_wall": round(sim_s / wall_s, 3),
            "harness_cpu_per_sim_s": round(cpu_s / sim_s, 3), "mega_cpu_per_sim_s": round(mega_s / sim_s, 3),
            "uno_cpu_per_sim_s": round(uno_s / sim_s, 3) if with_uno else None, "frames": frames}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=10.0, help="simulated seconds per run")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    rows = [run(paced, with_uno, args.seconds, busy)
            for busy in (False, True) for with_uno in (False, True) for paced in (False, True)]
    if args.json:
        print(json.dumps({"load_avg": os.getloadavg(), "cpus": os.cpu_count(), "rows": rows}, indent=1))
        return
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores, {args.seconds:g} simulated s a run")
    print(f"{'boards':6} {'firmware':8} {'paced':6} {'sim s/wall s':>12} {'harness CPU s/sim s':>20} {'Mega':>5} "
          f"{'Uno':>5} {'frames':>7}")
    for r in rows:
        uno = f"{r['uno_cpu_per_sim_s']:5.3f}" if r["uno_cpu_per_sim_s"] is not None else "    -"
        print(f"{r['boards']:6} {r['load']:8} {str(r['paced']):6} {r['sim_per_wall']:12.2f} "
              f"{r['harness_cpu_per_sim_s']:20.2f} {r['mega_cpu_per_sim_s']:5.3f} {uno} "
              f"{r['frames'] if r['frames'] is not None else '-':>7}")


if __name__ == "__main__":
    main()
