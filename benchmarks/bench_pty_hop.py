"""How long the kernel holds a pty hop, beside what a simulated rig's processes do (issue 54: the shared clock's
``KERNEL_HOP_MAX_S``).

A pty hands a writer's bytes to its reader through a kernel worker (``tty_flip_buffer_push`` queues
``flush_to_ldisc`` on the kernel's default unbound workqueue), so a hop's latency is the scheduler's, not the
copy's. Each condition runs side by side in one run: a probe process writes an 8-byte Modbus request to a raw pty's
slave side every 10 ms and times until its master side has read it (select), while beside it run ``--hogs`` CPU hogs
(``while :; do :; done``, as the CI's loaded runs) and ``--procs`` processes of ``--threads`` Python threads that each
sleep ``STEP`` s in ``select`` and compute ~0.1 ms between sleeps (the short waits of a simulated rig's world loop,
heartbeat and answer waits). Prints per condition the hops measured, their median, 99th percentile and maximum
(ms), and how many took longer than 1 s, beside the machine's load average.

    python benchmarks/bench_pty_hop.py                      # the four conditions of docs/architecture.md
    python benchmarks/bench_pty_hop.py --seconds 60 --steps 0.001,0.02

Measured on the 2-core machine of this project (Linux 6.18, 2026-11-28), 30 s each: two hogs alone, max 0.15 s;
two hogs and 4 x 10 threads sleeping 1 ms, max 4.7 s (8 hops over 1 s); 5 ms, max 14.5 s; 20 ms, max 1.0 s; no
hogs and 4 x 10 threads sleeping 1 ms, max 16.4 s; the same threads at nice 5, max 9.7 s (with hogs) and 27.8 s
(without). The threads that wake often, not the CPU hogs, set the tail.
"""

from __future__ import annotations

import argparse
import itertools
import os
import pty
import select
import statistics
import subprocess
import sys
import time
import tty

PROBE = "--probe"
POLLERS = "--pollers"


def probe(seconds: float) -> list[float]:
    """Hop latencies (s) of an 8-byte write to a raw pty's slave until its master has read it, every 10 ms for
    ``seconds`` s."""
    master, slave = pty.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    request = bytes.fromhex("0104000000213012")
    hops: list[float] = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        t0 = time.monotonic()
        os.write(slave, request)
        got = 0
        while got < len(request):
            if select.select([master], [], [], 120.0)[0]:
                got += len(os.read(master, 64))
        hops.append(time.monotonic() - t0)
        time.sleep(0.01)
    os.close(master)
    os.close(slave)
    return hops


def pollers(threads: int, step_s: float, seconds: float) -> None:
    """``threads`` threads that sleep ``step_s`` s in select and compute ~0.1 ms between sleeps, for ``seconds`` s."""
    import threading

    r, _w = os.pipe()
    end = time.monotonic() + seconds

    def loop() -> None:
        x = 0
        while time.monotonic() < end:
            select.select([r], [], [], step_s)
            for i in range(2000):
                x += i

    ts = [threading.Thread(target=loop) for _ in range(threads)]
    for t in ts:
        t.start()
    for t in ts:
        t.join()


def condition(hogs: int, procs: int, threads: int, step_s: float, seconds: float, own: bool) -> list[float]:
    """The probe's hops beside ``hogs`` CPU hogs and ``procs`` x ``threads`` short-sleeping threads; ``own``: the
    probe, each hog and each pollers' process in a session of its own (``setsid``: with Linux's autogroups, a
    scheduling group of its own), else all in this one's."""
    beside = [subprocess.Popen(["bash", "-c", "while :; do :; done"], start_new_session=own) for _ in range(hogs)]
    beside += [subprocess.Popen([sys.executable, __file__, POLLERS, str(threads), str(step_s), str(seconds + 2)],
                                start_new_session=own) for _ in range(procs)]
    try:
        out = subprocess.run([sys.executable, __file__, PROBE, str(seconds)], capture_output=True, text=True,
                             check=True, start_new_session=own).stdout
        return [float(v) for v in out.split()]
    finally:
        for p in beside:
            p.kill()
            p.wait()


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == PROBE:
        print(" ".join(f"{h:.6f}" for h in probe(float(sys.argv[2]))))
        return
    if len(sys.argv) > 1 and sys.argv[1] == POLLERS:
        pollers(int(sys.argv[2]), float(sys.argv[3]), float(sys.argv[4]))
        return
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=30.0, help="each condition's length, s")
    ap.add_argument("--hogs", type=int, default=2)
    ap.add_argument("--procs", type=int, default=4)
    ap.add_argument("--threads", type=int, default=10)
    ap.add_argument("--steps", default="0.001,0.005,0.02", help="the threads' sleeps, s, comma-separated")
    ap.add_argument("--sessions", default="one,own",
                    help="one: everything in this session; own: each process in a session of its own; comma-separated")
    a = ap.parse_args()
    conditions = [(a.hogs, 0, 0.0)] + [(a.hogs, a.procs, float(s)) for s in a.steps.split(",")]
    conditions.append((0, a.procs, float(a.steps.split(",")[0])))
    print(f"{'session':>7} {'hogs':>4} {'threads':>8} {'sleep ms':>8} {'hops':>5} {'median ms':>9} {'p99 ms':>8} "
          f"{'max ms':>8} {'> 1 s':>5}  load")
    for (hogs, procs, step), sessions in itertools.product(conditions, a.sessions.split(",")):
        hops = sorted(condition(hogs, procs, a.threads, step, a.seconds, sessions == "own"))
        p99 = hops[min(len(hops) - 1, int(0.99 * len(hops)))]
        print(f"{sessions:>7} {hogs:>4} {procs * a.threads:>8} {step * 1e3:>8.0f} {len(hops):>5} "
              f"{statistics.median(hops) * 1e3:>9.2f} {p99 * 1e3:>8.1f} {hops[-1] * 1e3:>8.1f} "
              f"{sum(h > 1.0 for h in hops):>5}  {os.getloadavg()[0]:.1f}")

if __name__ == "__main__":
    main()
