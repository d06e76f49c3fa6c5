"""GUI benchmark: the desktop app under Xvfb on the simulated rig for N minutes with the live view (taxel traces,
heat map, SA/RA rasters from the streaming encoder) on screen and the drum running over a ridged texture.

Measured, side by side with the targets of issue 5:

- display frame rate: paints of the live view per second (target >= 30 /s);
- frame-to-screen latency: from a frame's host receive timestamp (``TaxelStream``'s ``time.monotonic`` stamp) to
  the end of the paint that first shows it, p50 / p99 (target p99 < 50 ms);
- memory: the GUI process's RSS at the start (after a 30 s warm-up), at the end, and the slope of a least-squares
  line through the samples (target: flat, |slope| well under 1 MB/min);
- CPU: the GUI process's CPU use (user + system) as % of one core (target < 25 %, issue 12), split into the GUI
  thread (drawing, Qt) and the other threads (taxel stream reader, streaming encoder, drum poll), so a missed target
  names where the time goes.

The simulated rig runs as a separate process (``rigctl sim``), so the GUI process's CPU and memory are its own: the
taxel stream reader, the streaming encoder, the drum status poll and the drawing. Xvfb is started here (Debian
``xvfb``); the app writes its statistics as JSON lines (``--stats-out``).

Usage: python benchmarks/bench_gui.py [--minutes 10] [--json] [--screenshot PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

from rigctl.cli.sim import start_sim_process

WARMUP_S = 30.0


def start_xvfb() -> tuple[subprocess.Popen, str]:
    if shutil.which("Xvfb") is None:
        raise SystemExit("Xvfb not found (Debian package xvfb)")
    for n in range(90, 140):
        if not os.path.exists(f"/tmp/.X11-unix/X{n}") and not os.path.exists(f"/tmp/.X{n}-lock"):
            proc = subprocess.Popen(["Xvfb", f":{n}", "-screen", "0", "1600x1000x24", "-nolisten", "tcp"],
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            for _ in range(50):
                if os.path.exists(f"/tmp/.X11-unix/X{n}"):
                    return proc, f":{n}"
                time.sleep(0.1)
            proc.kill()
    raise SystemExit("could not start Xvfb")


def run(minutes: float, screenshot: str | None) -> dict:
    import psutil

    duration = minutes * 60.0
    with tempfile.TemporaryDirectory(prefix="rigctl-bench-gui-") as tmp:
        sim, ports = start_sim_process(os.path.join(tmp, "ports"), texture="G")
        xvfb, display = start_xvfb()
        stats_path = os.path.join(tmp, "stats.jsonl")
        env = dict(os.environ, DISPLAY=display, QT_QPA_PLATFORM="xcb", RIGCTL_CONFIG=os.path.join(tmp, "rig.json"),
                   XDG_CONFIG_HOME=os.path.join(tmp, "config"))
        cmd = [sys.executable, "-m", "rigctl_gui.app", "--drum-port", ports["drum"], "--taxel-port", ports["taxel"],
               "--tab", "live", "--run", "--stats-out", stats_path, "--quit-after", str(duration + WARMUP_S + 15)]
        if screenshot:
            cmd += ["--screenshot", screenshot]
        gui = subprocess.Popen(cmd, env=env, cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        ps = psutil.Process(gui.pid)
        others = {"sim": psutil.Process(sim.pid), "xvfb": psutil.Process(xvfb.pid)}
        other_cpu = {}
        threads = {}  # "start" / "end": (main thread cpu s, other threads cpu s) at the measured window's edges
        samples = []  # (t, rss bytes, cpu s)
        t_start = time.monotonic()
        try:
            while gui.poll() is None:
                t = time.monotonic() - t_start
                try:
                    c = ps.cpu_times()
                    samples.append((t, ps.memory_info().rss, c.user + c.system))
                    if WARMUP_S <= t <= WARMUP_S + duration:
                        main = sum(th.user_time + th.system_time for th in ps.threads() if th.id == gui.pid)
                        threads.setdefault("start", (t, main, c.user + c.system - main))
                        threads["end"] = (t, main, c.user + c.system - main)
                        for name, p in others.items():
                            oc = p.cpu_times()
                            other_cpu.setdefault(name, []).append((t, oc.user + oc.system))
                except psutil.NoSuchProcess:
                    break
                time.sleep(2.0)
            out = gui.stdout.read()
        finally:
            for p in (gui, sim, xvfb):
                if p.poll() is None:
                    p.terminate()
                    try:
                        p.wait(10)
                    except subprocess.TimeoutExpired:
                        p.kill()
        lines = [json.loads(x) for x in open(stats_path)] if os.path.exists(stats_path) else []
    if not lines:
        raise SystemExit(f"the app wrote no statistics; its output:\n{out[-3000:]}")
    t0 = lines[0]["time"]
    # the measured window: after the warm-up, before the app starts shutting down
    live = [ln for ln in lines if WARMUP_S <= ln["time"] - t0 <= WARMUP_S + duration and ln["connected"]]
    lat = np.array([v for ln in live for v in ln["latency_s"]])
    paints = np.array([ln["paints"] for ln in live], float)
    tt = np.array([ln["time"] for ln in live])
    per_s = np.diff(paints) / np.diff(tt)
    s = np.array(samples)
    s = s[(s[:, 0] >= WARMUP_S) & (s[:, 0] <= WARMUP_S + duration)]
    rss_mb = s[:, 1] / 2**20
    slope = np.polyfit(s[:, 0] / 60.0, rss_mb, 1)[0] if len(s) > 2 else float("nan")
    cpu = 100.0 * (s[-1, 2] - s[0, 2]) / (s[-1, 0] - s[0, 0])
    frames = live[-1]["frames"] - live[0]["frames"]
    ctx = {name: round(100.0 * (v[-1][1] - v[0][1]) / (v[-1][0] - v[0][0]), 1) for name, v in other_cpu.items()
           if len(v) > 1}
    (ta, ma, oa), (tb, mb, ob) = threads["start"], threads["end"]
    span = max(tb - ta, 1e-9)
    return {
        "minutes_measured": round((tt[-1] - tt[0]) / 60.0, 2),
        "display_fps_mean": round(float((paints[-1] - paints[0]) / (tt[-1] - tt[0])), 1),
        "display_fps_min_1s": round(float(per_s.min()), 1),
        "display_fps_p5_1s": round(float(np.percentile(per_s, 5)), 1),
        "latency_ms_p50": round(1e3 * float(np.percentile(lat, 50)), 1),
        "latency_ms_p99": round(1e3 * float(np.percentile(lat, 99)), 1),
        "latency_ms_max": round(1e3 * float(lat.max()), 1),
        "latency_samples": int(len(lat)),
        "rss_mb_start": round(float(rss_mb[0]), 1),
        "rss_mb_end": round(float(rss_mb[-1]), 1),
        "rss_slope_mb_per_min": round(float(slope), 3),
        "gui_cpu_percent_of_one_core": round(float(cpu), 1),
        "gui_thread_cpu_percent": round(100.0 * (mb - ma) / span, 1),
        "worker_threads_cpu_percent": round(100.0 * (ob - oa) / span, 1),
        "taxel_frames_per_s": round(frames / (tt[-1] - tt[0]), 1),
        "sa_spikes": live[-1]["sa_spikes"] - live[0]["sa_spikes"],
        "ra_spikes": live[-1]["ra_spikes"] - live[0]["ra_spikes"],
        "encoder_error": live[-1]["encoder_error"],
        "sim_cpu_percent": ctx.get("sim"),
        "xvfb_cpu_percent": ctx.get("xvfb"),
        "cores": os.cpu_count(),
        "load_average": [round(v, 2) for v in os.getloadavg()],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--screenshot", default=None, help="PNG of the app at the end of the run")
    args = ap.parse_args()
    r = run(args.minutes, args.screenshot)
    if args.json:
        print(json.dumps(r, indent=2))
        return
    rows = [
        ("display frame rate (mean)", f"{r['display_fps_mean']} /s", ">= 30 /s",
         r["display_fps_mean"] / 30.0),
        ("display frame rate (worst 1 s)", f"{r['display_fps_min_1s']} /s", ">= 30 /s", r["display_fps_min_1s"] / 30.0),
        ("frame-to-screen latency p99", f"{r['latency_ms_p99']} ms (p50 {r['latency_ms_p50']})", "< 50 ms",
         50.0 / max(r["latency_ms_p99"], 1e-9)),
        ("GUI RSS start -> end", f"{r['rss_mb_start']} -> {r['rss_mb_end']} MB", "flat", None),
        ("GUI RSS slope", f"{r['rss_slope_mb_per_min']} MB/min", "~0", None),
        ("GUI process CPU", f"{r['gui_cpu_percent_of_one_core']} % of one core", "< 25 %",
         25.0 / max(r["gui_cpu_percent_of_one_core"], 1e-9)),
        ("  GUI thread / worker threads", f"{r['gui_thread_cpu_percent']} / {r['worker_threads_cpu_percent']} %", "-",
         None),
        ("(same machine) rigctl sim / Xvfb CPU", f"{r['sim_cpu_percent']} / {r['xvfb_cpu_percent']} %",
         f"{r['cores']} cores", None),
    ]
    print(f"rigctl GUI under Xvfb, simulated rig, {r['minutes_measured']} min measured after {WARMUP_S:.0f} s warm-up "
          f"({r['taxel_frames_per_s']} taxel frames/s, {r['sa_spikes']} SA / {r['ra_spikes']} RA spikes drawn; "
          f"load average {' '.join(map(str, r['load_average']))})")
    for name, val, target, ratio in rows:
        print(f"  {name:32s} {val:34s} target {target:10s}" + (f" ratio {ratio:.2f}" if ratio is not None else ""))


if __name__ == "__main__":
    main()
