"""GUI thread stalls: the longest time the GUI thread does not answer during each thing the GUI itself does, beside
two CPU hogs (issue 51 item 6: the library's dead man's switch stops a pressing or turning rig when the GUI thread is
silent for 0.5 s; nothing the GUI does may hold its thread 0.25 s or more).

The simulated rig runs in a process of its own (``rigctl sim``: the boards on ptys, as hardware outlives the face);
this process is the GUI (the real main window on the rig's two ports, offscreen or on ``$DISPLAY``). Two CPU hogs
(``while :; do :; done``, at nice 0 like the GUI) keep the machine's cores busy throughout. A QTimer on the GUI thread
ticks every 5 ms; for each action the longest gap between two ticks is its stall (wall: what the dead man's switch
sees) and, beside it, that gap less the time the GUI thread waited in the run queue for a CPU within it (its own
stall: work, a read or the GIL; the kernel's schedstat). The actions, each as an operator makes it:

0. ``idle``: nothing done for 3 s while the drum turns (the floor: what the machine's load alone does);
1. ``live``: the first showing of the Live view while the drum turns (80 mm/s, 300 g);
2. ``abort``: Abort of a running protocol (asked, answered "Abort the run"), until the run has ended;
3. ``analysis_tab``: the first showing of the Analysis tab;
4. ``open_session``: opening a session file there and drawing its first trial;
5. ``results``: running the analyses on it (a background process) and showing their results.

Also counted: whether the dead man's switch (0.5 s, the app's own) stopped the rig during the actions.

Usage: python benchmarks/bench_gui_stalls.py [--repeats 1] [--no-hogs] [--json] [--profile DIR]
(``--profile DIR``: a cProfile of the GUI thread per action, DIR/ACTION.prof)
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import json
import os
import subprocess
import sys
import tempfile
import threading
import time

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

#: --sample: where the stalls are spent (the GUI thread's stack sampled while a tick is late)
SAMPLE = False
#: the dead man's limit of the app (rigctl.operations.DEADMAN_TIMEOUT_S), and the issue's bound on a stall, s
TARGET_S = 0.25

PROTOCOL = """
name = "bench_stalls"
description = "GUI stall benchmark: two textures, short trials"
textures = ["A", "L"]
speeds_mm_s = [80]
forces_g = [300]
trials_per_condition = 100
duration_s = 0.5
order = "blocked"

[settle]
force_timeout_s = 20
speed_timeout_s = 10
speed_tolerance_mm_s = 3
"""

DATASET = """
name = "bench_stalls_data"
textures = ["A", "B", "C", "D"]
speeds_mm_s = [80]
forces_g = [500]
trials_per_condition = 4
duration_s = 0.5
"""


def run_queue_wait_s() -> float:
    """This thread's time runnable but waiting for a CPU so far, s (Linux schedstat); 0 where not told."""
    try:
        with open("/proc/thread-self/schedstat") as f:
            return int(f.read().split()[1]) / 1e9
    except (OSError, IndexError, ValueError):
        return 0.0


class Heartbeat:
    """A 5 ms QTimer on the GUI thread: per phase, the longest gap between two ticks (wall) and that gap less the GUI
    thread's run-queue wait within it (own)."""

    def __init__(self) -> None:
        from PySide6 import QtCore

        self.phase: str | None = None
        self.first = True  # the first window of the process (a profile of a later one is ACTION.again.prof)
        self.worst: dict[str, tuple[float, float]] = {}
        self._last: tuple[float, float] | None = None
        self.timer = QtCore.QTimer()
        self.timer.setTimerType(QtCore.Qt.TimerType.PreciseTimer)
        self.timer.timeout.connect(self._tick)
        self.timer.start(5)

    def _tick(self) -> None:
        now, waited = time.monotonic(), run_queue_wait_s()
        if self._last is not None and self.phase is not None:
            gap, own = now - self._last[0], now - self._last[0] - (waited - self._last[1])
            w = self.worst.get(self.phase, (0.0, 0.0))
            self.worst[self.phase] = (max(w[0], gap), max(w[1], own))
        self._last = (now, waited)

    def start_sampler(self) -> None:
        """A thread that, while a tick is late by more than 50 ms, samples the GUI thread's Python stack every
        10 ms (``--sample``: where a stall is spent, by phase)."""
        import collections
        import traceback

        self.samples: dict[str, collections.Counter] = {}
        gui = threading.main_thread().ident

        def loop():
            while True:
                time.sleep(0.01)
                last, phase = self._last, self.phase
                if last is None or phase is None or time.monotonic() - last[0] < 0.05:
                    continue
                frame = sys._current_frames().get(gui)
                if frame is None:
                    continue
                stack = traceback.extract_stack(frame)
                ours = [f"{os.path.basename(f.filename)}:{f.lineno} {f.name}" for f in stack
                        if "bench_gui_stalls" not in f.filename][-6:]
                self.samples.setdefault(phase, collections.Counter())[" < ".join(reversed(ours))] += 1

        threading.Thread(target=loop, name="stall-sampler", daemon=True).start()

    @contextlib.contextmanager
    def measure(self, phase: str, profile_dir: str | None = None):
        self.tick_now()
        self.phase = phase
        prof = cProfile.Profile() if profile_dir else None
        if prof is not None:
            prof.enable()
        try:
            yield
        finally:
            if prof is not None:
                prof.disable()
                prof.dump_stats(os.path.join(profile_dir, f"{phase}{'' if self.first else '.again'}.prof"))
            self.tick_now()
            self.phase = None

    def tick_now(self) -> None:
        self._tick()


def spin(qapp, cond, timeout_s: float) -> bool:
    """Run the event loop until ``cond()`` or ``timeout_s`` (the GUI tests' :func:`rigctl_gui.events.wait_for`)."""
    from rigctl_gui.events import wait_for

    return wait_for(qapp, cond, timeout_s)


def raise_priority(pid: int, nice: int = -10) -> None:
    """Every thread of process ``pid`` at ``nice`` (where allowed): the simulated rig stands for hardware with
    processors of its own, which the PC's CPU hogs never starve; the hogs compete with the GUI only."""
    try:
        for tid in os.listdir(f"/proc/{pid}/task"):
            os.setpriority(os.PRIO_PROCESS, int(tid), nice)
    except (OSError, PermissionError):
        pass


def weigh_session(nice: int | None) -> int | None:
    """Set this session's autogroup nice (Linux: the weight of the session's processes against other sessions'),
    where allowed; returns the previous value (None: not changed)."""
    if nice is None:
        return None
    try:
        with open("/proc/self/autogroup") as f:
            before = int(f.read().rsplit("nice", 1)[1])
        with open("/proc/self/autogroup", "w") as f:
            f.write(str(nice))
        return before
    except (OSError, ValueError, IndexError):
        return None


def start_hogs(n: int) -> list[subprocess.Popen]:
    return [subprocess.Popen(["bash", "-c", "while :; do :; done"]) for _ in range(n)]


def run(repeats: int, hogs: int, profile_dir: str | None, screenshot_dir: str | None, rig: str = "inprocess") -> dict:
    from PySide6 import QtWidgets

    from rigctl.cli.sim import start_sim_process
    from rigctl.core.drum import DrumState

    qapp = QtWidgets.QApplication.instance() or QtWidgets.QApplication([sys.argv[0]])
    results: dict[str, list[tuple[float, float]]] = {}
    deadman: list[str] = []
    with tempfile.TemporaryDirectory(prefix="rigctl-bench-stalls-") as tmp:
        os.environ["RIGCTL_CONFIG"] = os.path.join(tmp, "rig.json")
        os.environ["XDG_CONFIG_HOME"] = os.path.join(tmp, "config")
        os.environ["XDG_STATE_HOME"] = os.path.join(tmp, "state")
        from PySide6 import QtCore

        QtCore.QSettings.setPath(QtCore.QSettings.Format.IniFormat, QtCore.QSettings.Scope.UserScope,
                                 os.path.join(tmp, "settings"))
        from rigctl.acquisition.protocol import parse_protocol
        from rigctl.simulation.dataset import generate_dataset

        dataset = os.path.join(tmp, "dataset.h5")
        generate_dataset(parse_protocol(DATASET), dataset, workers=0, progress=False)
        proto = os.path.join(tmp, "bench.toml")
        with open(proto, "w") as f:
            f.write(PROTOCOL)
        for rep in range(repeats):
            if rig == "sim":
                sim, ports = start_sim_process(os.path.join(tmp, f"ports{rep}"), texture="G")
                raise_priority(sim.pid)
            else:
                sim, ports = None, None
            hog_procs: list[subprocess.Popen] = []
            try:
                # a fresh interpreter's state for each repeat is not possible in one process: the first repeat is
                # the one of a fresh app (its first Live view, first Analysis tab); later repeats a fresh window
                for name, worst in _one_window(qapp, ports, proto, dataset, hogs, hog_procs, profile_dir,
                                               screenshot_dir if rep == 0 else None, deadman, DrumState,
                                               first=rep == 0).items():
                    results.setdefault(name, []).append(worst)
            finally:
                for p in hog_procs:
                    p.kill()
                    p.wait()
                if sim is not None:
                    sim.terminate()
                    try:
                        sim.wait(30)
                    except subprocess.TimeoutExpired:
                        sim.kill()
    return {"actions": {k: {"wall_s": [round(w, 3) for w, _ in v], "own_s": [round(o, 3) for _, o in v]}
                        for k, v in results.items()},
            "deadman_trips": deadman, "hogs": hogs, "rig": rig, "repeats": repeats, "cores": os.cpu_count(),
            "load_average": [round(x, 2) for x in os.getloadavg()]}


def _one_window(qapp, ports, proto, dataset, hogs, hog_procs, profile_dir, screenshot_dir, deadman, DrumState, *,
                first: bool = True):
    from rigctl_gui.app import MainWindow, configure_pyqtgraph
    from rigctl_gui.workers import RigSource

    configure_pyqtgraph()
    MainWindow.deadman_s = 0.5  # the app's own limit
    w = MainWindow(RigSource("serial", drum_port=ports["drum"], taxel_port=ports["taxel"]) if ports is not None
                   else RigSource("inprocess"))
    w.resize(1280, 800)
    w.show()
    if not spin(qapp, lambda: w.handle is not None or "not connected" in w.source_label.text(), 60) \
            or w.handle is None:
        raise SystemExit(f"could not connect to the simulated rig: {w.banner.text}")
    beat = Heartbeat()
    beat.first = first
    if SAMPLE:
        beat.start_sampler()
    spin(qapp, lambda: False, 2.0)
    hog_procs.extend(start_hogs(hogs))
    spin(qapp, lambda: False, 1.0)

    def state():
        st = w.poller.latest if w.poller is not None else None
        return None if st is None else DrumState(int(st.state))

    seen = [w.poller.deadman if w.poller is not None else None]

    def tripped(action):  # a new stop by the dead man's switch since the last action
        now = w.poller.deadman if w.poller is not None else None
        if now and now != seen[0]:
            deadman.append(f"{action}: {now}")
        seen[0] = now

    try:
        # 1. the first Live view while the drum turns
        w.tabs.setCurrentWidget(w.control)
        w.control.speed.setValue(80.0)
        w.control.force.setValue(300.0)
        for _ in range(3):  # (a command the loaded machine's Modbus link lost is sent again)
            w.control.command("run")
            if spin(qapp, lambda: state() == DrumState.RUNNING, 30):
                break
        else:
            raise SystemExit(f"the drum did not start: {w.poller.latest}; {w.control.message.text()}; dead man's "
                             f"switch: {w.poller.deadman}")
        spin(qapp, lambda: False, 1.0)
        with beat.measure("idle", profile_dir):  # the floor: nothing done, the drum turning, the hogs beside
            spin(qapp, lambda: False, 3.0)
        tripped("idle")
        with beat.measure("live", profile_dir):
            w.tabs.setCurrentIndex(w._live_index)
            spin(qapp, lambda: False, 3.0)
        tripped("live")
        w.control.command("stop")
        spin(qapp, lambda: state() == DrumState.IDLE, 30)
        # 2. Abort of a running protocol
        tab = w.protocol
        w.tabs.setCurrentWidget(tab)
        tab.load(proto)
        tab.out_edit.setText(os.path.join(os.path.dirname(proto), f"run{time.monotonic_ns()}.h5"))
        tab.resume_box.setChecked(False)
        tab.start()
        def recording():
            if tab.prompt_frame.isVisible():  # "Mount texture plate X": the simulated rig's plate is mounted
                tab.prompt_ok.click()
            return len(tab._done_ids) >= 2 and tab._current is not None

        if not spin(qapp, recording, 180):
            raise SystemExit(f"the protocol did not record: {tab.status.text()}")
        with beat.measure("abort", profile_dir):
            box = tab.ask_abort()  # the Abort button: asks first
            if box is None:
                raise SystemExit(f"the run ended before Abort: {tab.status.text()}")
            next(b for b in box.buttons() if b.text() == "Abort the run").click()
            spin(qapp, lambda: tab.job is None, 60)
            spin(qapp, lambda: False, 1.0)
        tripped("abort")
        # 3-5. the Analysis tab, a session, the results
        with beat.measure("analysis_tab", profile_dir):
            w.tabs.setCurrentIndex(w._analysis_index)
            spin(qapp, lambda: False, 1.0)
        an = w.analysis
        with beat.measure("open_session", profile_dir):
            an.open(dataset)
            an.trials.selectRow(1)
            spin(qapp, lambda: an._trial_job is None and "SA" in an.status.text(), 120)
            spin(qapp, lambda: False, 0.5)
        an.do_extra.setChecked(False)
        an.repeats.setValue(2)
        an.n_pcs.setValue(6)
        with beat.measure("results", profile_dir):
            an.run_analyses()
            spin(qapp, lambda: an.job is None, 600)
            spin(qapp, lambda: False, 1.0)
        if an.results is None:
            raise SystemExit(f"no analysis results: {an.status.text()}")
        if screenshot_dir:
            w.grab().save(os.path.join(screenshot_dir, "stalls_end.png"))
        if SAMPLE:
            for phase, counter in beat.samples.items():
                print(f"== {phase}: the GUI thread's stack while a tick was late (10 ms samples)", file=sys.stderr)
                for stack, n in counter.most_common(8):
                    print(f"  {n:4d}  {stack}", file=sys.stderr)
        return dict(beat.worst)
    finally:
        beat.timer.stop()
        w._close_confirmed = True
        w.close()
        w.deleteLater()
        qapp.processEvents()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=1, help="fresh windows in turn (the first is a fresh app)")
    ap.add_argument("--hogs", type=int, default=2, help="CPU hogs beside the GUI (default 2)")
    ap.add_argument("--session-nice", type=int, default=-10,
                    help="the scheduling weight of this session's group against other sessions' programs (Linux "
                         "autogroup nice, where allowed; default -10): on a machine other people keep busy, the GUI, "
                         "its rig and the two hogs then share the cores among themselves as on a machine of their "
                         "own (inside the group the GUI and the hogs are both at nice 0)")
    ap.add_argument("--rig", choices=("inprocess", "sim"), default="inprocess",
                    help="the rig the window opens: the in-process simulated rig (default; its boards are threads of "
                         "this process, on a simulated clock: they also compete with the GUI thread for the GIL) or "
                         "`rigctl sim` in a process of its own on ptys (on this machine, beside two hogs, its host "
                         "watchdog expired before the drum turned, also without a GUI)")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--profile", default=None, metavar="DIR", help="cProfile of each action into DIR/ACTION.prof")
    ap.add_argument("--screenshot", default=None, metavar="DIR", help="a PNG of the window at the end into DIR")
    ap.add_argument("--sample", action="store_true",
                    help="print the GUI thread's Python stack sampled while a tick is late (stderr), by action")
    args = ap.parse_args()
    global SAMPLE
    SAMPLE = args.sample
    if args.profile:
        os.makedirs(args.profile, exist_ok=True)
    load0 = os.getloadavg()
    group = weigh_session(args.session_nice)
    try:
        r = run(args.repeats, args.hogs, args.profile, args.screenshot, args.rig)
    finally:
        weigh_session(group)
    r["load_average_before"] = [round(x, 2) for x in load0]
    r["session_nice"] = args.session_nice
    if args.json:
        print(json.dumps(r, indent=2))
        return
    print(f"GUI thread's longest stall per action beside {r['hogs']} CPU hogs ({r['cores']} cores, load average "
          f"before {' '.join(map(str, r['load_average_before']))}, after {' '.join(map(str, r['load_average']))}); "
          f"target < {TARGET_S} s")
    for name, v in r["actions"].items():
        worst = max(v["wall_s"])
        print(f"  {name:14s} wall {', '.join(f'{x:.3f}' for x in v['wall_s'])} s   own {', '.join(f'{x:.3f}' for x in v['own_s'])} s"
              f"   {'ok' if worst < TARGET_S else 'OVER'}")
    print(f"  dead man's switch trips: {len(r['deadman_trips'])}" + "".join(f"\n    {t}" for t in r["deadman_trips"]))


if __name__ == "__main__":
    threading.current_thread().name = "GUI thread"
    main()
