"""Issue 75's table, row by row, on the drum controller's firmware as it stands under simavr (the Mega alone), judged
on the harness's truth log (its spring: the true force), twice: the firmware alone (no stall) and the rig as built
(the actuator driver's current limit stalls the motor where the spring carries AS_BUILT_STALL_G, 1550 g: docs/hardware,
benchmarks/bench_fault_campaign.py). The bound is 1.1 x FORCE_LIMIT = 1650 g (docs/safety.md).

Each row is the issue's measurement repeated as an operator would meet it (the issue's numbers were firmware 1.3's):

- ``reversed-held``: the actuator's coil pair swapped while 1,450 g is held (10 SPS, 647 g/mm: seed 801696's rig),
  then a trial and the protocol's next force (1,000 g: the loop drives, the wrong way);
- ``reversed-retract``: the same as the release begins (800259's moment);
- ``switch-reset-home``: the home switch stuck closed, a reset under 1,000 g, HOME, then CLEAR_FAULT + HOME x3
  (10 SPS, 1 kg/mm);
- ``switch-idle``: the same switch fault with the rig idle at home, then three acknowledged starts (HOME if it is
  not homed, a press to 1,000 g);
- ``gain-0.5``: the load cell's gain halved before a 1,400 g press (10 SPS, 1 kg/mm);
- ``coupling-50``, ``coupling-10``: the coupling slipping 50 % / 10 % of the steps from the press's start (1,400 g,
  10 SPS, 1 kg/mm), caught up whenever the motor holds;
- ``reversed-reset-zero``: the actuator reversed, a reset under 1,450 g and four acknowledged HOMEs, the cell's zero
  250 g off the one stored with the calibration (a mount changed since), at 10 and 80 SPS;
- ``plate-stiff``: a plate of 50,000 g/mm is refused by the injector (the rig config's bound, 5,000 g/mm); the
  stiffest it accepts swapped in before a 1,400 g press (80 SPS, a 1 kg/mm rig).

Usage: python benchmarks/bench_issue75_rows.py [--rows NAME,...] [--json]
Prints one line a row and mode (the worst true force, what latched, simulated and CPU seconds) and the load average;
exits 1 if a row on the rig as built passed 1650 g, 2 for an unknown row.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import resource
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from rigctl.core.faults import FaultSpecError, parse_fault
from rigctl.devices import wire
from rigctl.devices.drum import DrumError
from rigctl.rigs import drum_answer_timeout_s
from rigctl.simulation.hil_bench import HilBench

State, Fault = wire.DrumState, wire.Fault
BOUND_G = 1650.0


def _stall_g() -> float:
    spec = importlib.util.spec_from_file_location("bench_fault_campaign", Path(__file__).with_name(
        "bench_fault_campaign.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return float(module.AS_BUILT_STALL_G)


def _settle(b: HilBench, seconds: float = 2.0) -> None:
    b.wait(lambda s: s.state not in (State.SEEKING_FORCE, State.HOMING), 30)
    b.sim_wait(seconds)


def _latched(b: HilBench, seen: list[str]) -> None:
    st = b.drum.read_status()
    name = "|".join(f.name or "" for f in Fault if f and f in st.faults) or st.state.name
    if not seen or seen[-1] != name:
        seen.append(name)


def reversed_held(b: HilBench, seen: list[str]) -> None:
    b.press_settled(1450)
    b.inject("reversed-actuator@0")
    b.drum.set_speed(80.0)
    b.drum.run()  # the trial
    b.sim_wait(2.0)
    b.drum.set_force(1000)  # the protocol's next force: the loop drives (the wrong way)
    b.wait(lambda s: s.state == State.FAULT, 10)
    _latched(b, seen)
    b.sim_wait(2.0)
    _latched(b, seen)


def reversed_retract(b: HilBench, seen: list[str]) -> None:
    b.press_settled(1450)
    b.drum.stop()  # the release: a back-off that proves its way first
    b.sim_wait(0.05)
    b.inject("reversed-actuator@0")
    b.wait(lambda s: s.state == State.FAULT or (s.state == State.IDLE and s.actuator_mm < 0.05), 10)
    _latched(b, seen)
    b.sim_wait(2.0)


def _home_rounds(b: HilBench, seen: list[str], rounds: int) -> None:
    for _ in range(rounds):
        try:
            b.drum.home()
        except DrumError as exc:
            seen.append(f"HOME refused ({exc})"[:60])
            break
        b.wait(lambda s: s.state != State.HOMING, 60)
        _latched(b, seen)
        b.sim_wait(0.5)
        if b.drum.read_status().state == State.FAULT:
            b.drum.clear_fault()


def switch_reset_home(b: HilBench, seen: list[str]) -> None:
    b.press_settled(1000)
    b.inject("home-switch=closed@0")
    b.reset_under_load()
    _home_rounds(b, seen, 4)


def switch_idle(b: HilBench, seen: list[str]) -> None:
    b.inject("home-switch=closed@0")
    b.sim_wait(0.5)
    for _ in range(3):
        st = b.drum.read_status()
        try:
            if st.state == State.FAULT:
                b.drum.clear_fault()
            if b.drum.read_status().state == State.NOT_HOMED:
                b.drum.home()
                b.wait(lambda s: s.state != State.HOMING, 60)
            if b.drum.read_status().state == State.IDLE:
                b.drum.set_force(1000)
                b.drum.press()
        except DrumError as exc:
            seen.append(f"refused ({exc})"[:60])
        _settle(b)
        _latched(b, seen)
        if b.drum.read_status().state == State.FORCE_SETTLED:
            b.drum.stop()
            b.sim_wait(3.0)


def _press_with(spec: str, force_g: float) -> Callable[[HilBench, list[str]], None]:
    def row(b: HilBench, seen: list[str]) -> None:
        b.drum.set_force(force_g)
        b.drum.press()
        b.inject(spec)
        _settle(b, 3.0)
        _latched(b, seen)
    return row


def _before_press(spec: str, force_g: float) -> Callable[[HilBench, list[str]], None]:
    def row(b: HilBench, seen: list[str]) -> None:
        b.inject(spec)
        b.sim_wait(0.5)
        b.drum.set_force(force_g)
        b.drum.press()
        _settle(b, 3.0)
        _latched(b, seen)
    return row


def reversed_reset_zero(b: HilBench, seen: list[str]) -> None:
    b.press_settled(1450)
    b.inject("reversed-actuator@0")
    b.reset_under_load()
    _home_rounds(b, seen, 4)


def plate_stiff(b: HilBench, seen: list[str]) -> None:
    try:
        b.inject("contact-stiffness=50000@0")
        seen.append("50000 g/mm ACCEPTED")
    except (FaultSpecError, ValueError) as exc:
        seen.append(f"50,000 g/mm refused: {str(exc)[:50]}")
    _before_press("contact-stiffness=5000@0", 1400)(b, seen)


#: name -> (the rig: HX711 rate, stiffness g/mm; a cell offset from power-up, g; the row)
ROWS: dict[str, tuple[int, float, float, Callable[[HilBench, list[str]], None]]] = {
    "reversed-held": (10, 647.0, 0.0, reversed_held),
    "reversed-retract": (10, 647.0, 0.0, reversed_retract),
    "switch-reset-home": (10, 1000.0, 0.0, switch_reset_home),
    "switch-idle": (10, 1000.0, 0.0, switch_idle),
    "gain-0.5": (10, 1000.0, 0.0, _before_press("cell-gain=0.5@0", 1400)),
    "coupling-50": (10, 1000.0, 0.0, _press_with("coupling-slip=50%@0", 1400)),
    "coupling-10": (10, 1000.0, 0.0, _press_with("coupling-slip=10%@0", 1400)),
    "reversed-reset-zero-10": (10, 1000.0, 250.0, reversed_reset_zero),
    "reversed-reset-zero-80": (80, 1000.0, 250.0, reversed_reset_zero),
    "plate-stiff": (80, 1000.0, 0.0, plate_stiff),
}


def run_row(name: str, stall_g: float) -> dict[str, object]:
    """One row on a fresh bench: its worst true force (g), what latched in order, simulated and CPU seconds."""
    sps, k, offset_g, row = ROWS[name]
    cpu0 = time.process_time() + resource.getrusage(resource.RUSAGE_CHILDREN).ru_utime
    seen: list[str] = []
    with tempfile.TemporaryDirectory() as tmp:
        b = HilBench(Path(tmp), sps=sps, k=k, stall_g=stall_g, answer_timeout_s=drum_answer_timeout_s("hil"))
        try:
            t0 = b.rig.next_telemetry().t_s
            if offset_g:
                b.inject(f"cell-offset={offset_g:g}@0")  # the zero moved since the calibration stored it
                b.sim_wait(0.5)
            b.drum.wait_hx711_rate(timeout_s=10)
            b.drum.home()
            b.wait(lambda s: s.state != State.HOMING, 30)
            row(b, seen)
            peak, sim_s = b.peak_g(), b.rig.next_telemetry().t_s - t0
        finally:
            b.close()
    cpu = time.process_time() + resource.getrusage(resource.RUSAGE_CHILDREN).ru_utime - cpu0
    return {"row": name, "stall_g": stall_g, "worst_true_force_g": round(peak, 1), "latched": seen,
            "sim_s": round(sim_s, 1), "cpu_s": round(cpu, 1), "within_bound": peak <= BOUND_G}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", default=",".join(ROWS), help="NAME,... (default: every row)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    names = [n for n in args.rows.split(",") if n]
    unknown = [n for n in names if n not in ROWS]
    if unknown:
        print(f"bench_issue75_rows: unknown row {unknown[0]!r}; one of {', '.join(ROWS)}", file=sys.stderr)
        return 2
    parse_fault("cell-gain=0.5@0")  # the fault names this bench uses exist
    load0 = os.getloadavg()[0]
    results = []
    for name in names:
        for stall in (0.0, _stall_g()):
            r = run_row(name, stall)
            results.append(r)
            if not args.json:
                mode = "firmware alone" if not stall else f"as built (stall {stall:g} g)"
                print(f"{name:24s} {mode:26s} {r['worst_true_force_g']:8.1f} g  {' -> '.join(r['latched'])}  "
                      f"[{r['sim_s']} s simulated, {r['cpu_s']} CPU-s]", flush=True)
    load = (load0, os.getloadavg()[0])
    if args.json:
        print(json.dumps({"results": results, "load_start_end": load}, indent=1))
    else:
        print(f"load average {load[0]:.2f} -> {load[1]:.2f}")
    return 1 if any(r["stall_g"] and not r["within_bound"] for r in results) else 0


if __name__ == "__main__":
    sys.exit(main())
