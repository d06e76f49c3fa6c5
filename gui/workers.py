"""Worker threads of the app. The GUI never blocks on the rig, the encoder or an analysis: each runs here, in a plain
Python thread, and publishes into fixed-size buffers or a queue that the GUI drains from a QTimer at its own pace
(PyMoDAQ #564: a producer that emits Qt signals per sample floods the event loop and Stop stops responding).

Nothing here implements rig, encoding or analysis logic: it only calls :mod:`rigctl` in the right thread.
"""

from __future__ import annotations

import queue
import threading
import time
import traceback
from collections.abc import Callable
from typing import Any

import numpy as np

from rigctl.core.errors import describe_error
from rigctl.core.sensor import PAPER_SENSOR, SensorLayout

# the rig kinds are the library's (rigctl.rigs.KINDS, through the operator layer); the live encoder runs in the
# library too (rigctl.operations), the GUI only shows its spikes
from rigctl.operations import (
    LIVE_WINDOW_MAX_S as LIVE_WINDOW_MAX_S,
    LiveEncoder as LiveEncoder,
    RigControl,
    RigSource as RigSource,
    SpikeRing as SpikeRing,
    spike_capacity as spike_capacity,
)
from rigctl_gui.once import StartOnce


# ----------------------------------------------------------------------------------------------------------------
# Connection
# ----------------------------------------------------------------------------------------------------------------
class RigHandle:
    """The open rig as the GUI sees it: the operator layer's :class:`rigctl.operations.RigControl` and its parts.

    Attributes
    ----------
    control : rigctl.operations.RigControl
        What the panels call (setpoints, press -> settle -> run, commands, status, the rig config, the mounted
        plate) and listen to (its ``monitor``); the rig itself is the library's, never the GUI's.
    drum : rigctl.operations.DrumView (the controller read-only: every command goes through ``control``)
    taxels : rigctl.core.interfaces.TaxelSource (a TaxelStream)
    """

    def __init__(self, control: RigControl, source: RigSource | None = None):
        from rigctl.operations import live_ring

        self.control = control
        self.source = source or control.source
        self.drum = control.drum
        self.taxels = control.taxels
        live_ring(self.taxels)  # the live view reads it: a source that keeps one only on request (in-process) now does

    @property
    def is_simulated(self) -> bool:
        """True when the rig can place a calibration mass itself (simulated backends)."""
        return self.control.places_mass

    def close(self) -> None:
        self.control.close()


def open_rig(source: RigSource, *, config=None, host_config_path=None, prompt=None, seed: int = 0,
             home=True) -> RigHandle:
    """Open the rig described by ``source`` (:func:`rigctl.operations.open_control`); nothing moves (the Home action
    is the start). ``home``: a :class:`rigctl.operations.Home` (or True: a latched fault fails the opening; False:
    it stays latched for the operator).

    ``host_config_path`` is the rig config file (calibration; None = the library's default path); ``prompt`` the
    operator prompt for plate changes on hardware. Raises :class:`rigctl.acquisition.rig.RigError` (the library's
    message names the ports) or ``OSError``.
    """
    from rigctl.operations import Home, open_control

    policy = home if isinstance(home, (Home, str)) else Home.ALWAYS if home else Home.NEVER
    control = open_control(source, home=policy, config=config, seed=seed, host_config_path=host_config_path,
                           prompt=prompt)
    return RigHandle(control, source)


# ----------------------------------------------------------------------------------------------------------------
# Drum commands (the status poll, the watchdog feed and the dead man's switch are the library's:
# rigctl.operations.RigMonitor, which the GUI subscribes to through rigctl_gui.rig_events)
# ----------------------------------------------------------------------------------------------------------------
class CommandExecutor:
    """Runs drum commands one at a time in a worker thread; results land in :attr:`results` for the GUI to drain.

    Each result is ``(name, ok, message)``. :meth:`emergency_stop` does not queue behind other commands: it calls the
    rig owner's ``stop`` (:meth:`rigctl.operations.RigControl.stop`) on a fresh thread at once (the client's lock
    serialises it with any request in flight). The commands are the owner's methods: the GUI holds no drum client.
    """

    def __init__(self, control: RigControl):
        self.control = control
        self.results: queue.SimpleQueue = queue.SimpleQueue()
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._loop, name="drum-commands", daemon=True)
        self._thread.start()

    def submit(self, name: str, fn: Callable, *args) -> None:
        self._queue.put((name, fn, args))

    def emergency_stop(self) -> threading.Thread:
        t = threading.Thread(target=self._call, args=("STOP", self.control.stop, ()), name="drum-stop", daemon=True)
        t.start()
        return t

    def close(self) -> None:
        self._queue.put(None)

    def _loop(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            self._call(*item)

    def _call(self, name, fn, args) -> None:
        try:
            fn(*args)
        except Exception as exc:  # noqa: BLE001 - reported to the operator, the app carries on
            self.results.put((name, False, f"{name} failed: {exc}"))
        else:
            self.results.put((name, True, f"{name} done"))


# ----------------------------------------------------------------------------------------------------------------
# Live taxels + streaming encoder
# ----------------------------------------------------------------------------------------------------------------
#: frames that arrive after a silence longer than this (host time, s) start a new segment of the live traces
GAP_S = 0.5


class TraceBuffer:
    """The last ``seconds`` of taxel readings, decimated by ``decimate``, in fixed-size arrays.

    The GUI thread calls :meth:`pull` each refresh: it reads the frames that arrived since the last call from the
    taxel stream's ring buffer (:meth:`rigctl.devices.ring.RingBuffer.read_since`, cheap copies of a few dozen
    frames) so a frame reaches the screen without waiting for any worker. Times are stream time (frame number in the
    ring / ``layout.sample_rate_hz``, s); readings are ``(n, layout.n_channels)`` (``layout``: the stream's sensor,
    default the paper's 3x3x2 at 1 kHz). ``since``: the ring's frame count to read on from (the first :meth:`pull`
    takes what the ring still holds of the frames since then); default the ring's count now (live only, no history).
    """

    def __init__(self, ring, *, seconds: float = 10.0, decimate: int = 4, layout: SensorLayout | None = None,
                 since: int | None = None):
        self.ring = ring
        self.layout = layout or PAPER_SENSOR
        self.rate_hz = self.layout.sample_rate_hz
        self.decimate = max(1, int(decimate))
        n = max(1, int(seconds * self.rate_hz / self.decimate))
        self._x = np.zeros((n, self.layout.n_channels), dtype=np.uint16)
        self._t = np.zeros(n)
        self._n = 0
        self.cursor = ring.total if since is None else int(since)
        self.n_samples = 0
        self.current = np.zeros(self.layout.n_channels, dtype=np.uint16)
        self.newest_host_time_s = float("nan")
        #: outages seen: (stream time of the first frame after it, s; its length in host time, s), newest last
        self.gaps: list[tuple[float, float]] = []
        self._gap_at = np.zeros(0)  # the gaps' stream times and the shift each adds to the times after it
        self._gap_shift = np.zeros(1)

    def pull(self) -> int:
        """Take the new frames from the ring; returns how many arrived."""
        self.cursor, samples, _seq, host_t = self.ring.read_since(self.cursor)
        n = len(samples)
        if n == 0:
            return 0
        idx = np.arange(self.cursor - n, self.cursor)  # absolute frame numbers of the stream
        quiet = float(host_t[0]) - self.newest_host_time_s  # NaN before the first frame
        if quiet > GAP_S:  # no frame arrived for that long: an outage, drawn as a gap in the traces
            self.gaps.append((idx[0] / self.rate_hz, quiet))
            del self.gaps[:-64]
            # the frames lost in it have no number in the ring: its width on a time axis is the host's clock
            self._gap_at = np.append(self._gap_at, idx[0] / self.rate_hz)[-64:]
            extra = max(quiet - 1.0 / self.rate_hz, 0.0)
            self._gap_shift = np.append(self._gap_shift, self._gap_shift[-1] + extra)[-65:]
        pick = idx % self.decimate == 0
        sub, sub_t = samples[pick], idx[pick] / self.rate_hz
        cap = len(self._x)
        if len(sub) > cap:
            sub, sub_t = sub[-cap:], sub_t[-cap:]
        k = len(sub)
        pos = (self._n + np.arange(k)) % cap
        self._x[pos] = sub
        self._t[pos] = sub_t
        self._n += k
        self.n_samples += n
        self.current = samples[-1]
        self.newest_host_time_s = float(host_t[-1])
        return n

    def display_time(self, t: np.ndarray) -> np.ndarray:
        """Stream times ``t`` (s; frame number / rate, as :meth:`view` and the live encoder's spikes have them) on
        a time axis where every outage takes its real width (the host's clock across it): ``t`` plus the length of
        the outages before it. Returns a new float64 array of ``t``'s shape."""
        t = np.asarray(t, dtype=np.float64)
        if not len(self._gap_at):
            return t.copy()
        k = np.searchsorted(self._gap_at, t, side="right") + len(self._gap_shift) - len(self._gap_at) - 1
        return t + self._gap_shift[k]

    def view(self, last: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(t (n,) s, readings (n, n_channels) uint16)``, oldest first: everything held, or only the newest
        ``last`` samples (a live view copies just its window, not the whole buffer, each frame)."""
        cap = len(self._x)
        n = min(self._n, cap) if last is None else min(self._n, cap, max(int(last), 0))
        end = self._n % cap if self._n > cap else self._n
        start = end - n
        if start >= 0:
            return self._t[start:end], self._x[start:end]
        return np.concatenate([self._t[start:], self._t[:end]]), np.concatenate([self._x[start:], self._x[:end]])


# ----------------------------------------------------------------------------------------------------------------
# Generic background job (encoding, analysis, protocol runs)
# ----------------------------------------------------------------------------------------------------------------
class Job(threading.Thread):
    """Runs ``fn(job)`` in a thread. ``fn`` may call :meth:`progress` and check :attr:`cancel` (a threading.Event).

    The GUI polls :attr:`done`, :attr:`fraction`, :attr:`message`, :attr:`result` and :attr:`error`.
    """

    #: what a caller attaches to know which request the job answers (the analysis tab's trial view: ``tid``,
    #: ``path``; the classification view: ``planned``)
    tid: int
    path: str
    planned: Any

    def __init__(self, fn: Callable[["Job"], Any], name: str = "job"):
        super().__init__(name=name, daemon=True)
        self.fn = fn
        self.cancel = threading.Event()
        self.fraction = 0.0
        self.message = ""
        self.result: Any = None
        self.error: str | None = None
        self.traceback: str | None = None
        self.done = False
        self.events: queue.SimpleQueue = queue.SimpleQueue()

    def progress(self, fraction: float | None = None, message: str | None = None) -> None:
        if fraction is not None:
            self.fraction = float(fraction)
        if message is not None:
            self.message = message

    def run(self) -> None:
        try:
            self.result = self.fn(self)
        except BaseException as exc:  # noqa: BLE001 - reported in the GUI
            self.error = describe_error(exc)
            self.traceback = traceback.format_exc()
        finally:
            self.done = True


# ----------------------------------------------------------------------------------------------------------------
# Background process (encoding, analyses): cancellable for real, never holds the GUI's GIL
# ----------------------------------------------------------------------------------------------------------------
class _ForwardProgress:
    """The ``progress`` callback in the child process: sends the library's
    :class:`rigctl.core.progress.ProgressEvent` s to the parent, at most one per stage every ``min_interval_s``
    (the first and last of a stage and every message always go)."""

    def __init__(self, q, min_interval_s: float = 0.1):
        self.q, self.min_interval_s = q, min_interval_s
        self._last: dict[str, float] = {}

    def __call__(self, event) -> None:
        now = time.monotonic()
        last = self._last.get(event.stage)
        edge = event.total is None or event.message or event.done in (0, event.total)
        if edge or last is None or now - last >= self.min_interval_s:
            self._last[event.stage] = now
            self.q.put(("progress", event))


def _process_main(target: str, kwargs: dict, q) -> None:
    import importlib
    import inspect

    try:
        module, attr = target.split(":")
        fn = getattr(importlib.import_module(module), attr)
        if q is None:  # the fork server's warm-up (:func:`start_job_server`): nothing to answer
            fn(**kwargs)
            return
        if "progress" in inspect.signature(fn).parameters:
            kwargs = {**kwargs, "progress": _ForwardProgress(q)}
        result = fn(**kwargs)
    except BaseException as exc:  # noqa: BLE001 - sent to the GUI
        if q is not None:
            q.put(("error", describe_error(exc), traceback.format_exc()))
    else:
        if q is not None:
            q.put(("result", result))


#: what every job of the analysis tab imports (the library's encoding and analyses, scikit-learn, scipy, numba,
#: h5py: ~1.5-2 s of CPU), loaded once into the fork server that starts the jobs (:func:`job_context`), and numba's
#: CPU target set up there once (:mod:`rigctl_gui.job_numba`)
JOB_PRELOAD = ("rigctl_gui.analysis_jobs", "rigctl.operations", "rigctl.encoding.pipeline", "rigctl.analysis.tasks",
               "rigctl.analysis.classify", "rigctl.analysis.model", "rigctl.encoding.estimators",
               "rigctl_gui.job_numba")


def job_context():
    """The ``multiprocessing`` context the jobs start in: ``forkserver``, with :data:`JOB_PRELOAD` imported into the
    server when it starts, so each job is a fork of a process that has the analysis stack loaded rather than a fresh
    interpreter importing it again (``spawn``). The server is a plain process started from a fresh interpreter, not a
    fork of the GUI: no Qt, no threads of the app in the jobs. It lives as long as the app and is stopped with it.
    Starting it takes seconds (the imports): :func:`start_job_server` starts it in the background when the app builds
    its Analysis tab (:func:`rigctl_gui.app.start_job_server_with_analysis`), and :class:`ProcessJob` starts its
    process from a thread of its own, never the GUI thread."""
    import multiprocessing as mp

    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload(list(JOB_PRELOAD))  # used when the server starts; no effect once it runs
    return ctx


def _warm_up() -> None:
    """Start the fork server and wait until it has imported :data:`JOB_PRELOAD`: a job that does nothing is forked
    from it and waited for (the answer to a fork request comes only once the server has loaded its preload)."""
    ctx = job_context()
    proc = ctx.Process(target=_process_main, args=("os:getpid", {}, None), daemon=True)
    proc.start()
    proc.join()


_job_server = StartOnce(_warm_up, "job-server-start")


def start_job_server() -> threading.Thread:
    """Start the analysis jobs' fork server (:func:`job_context`) in a background thread, at once, so the first
    Encode / Run analyses / Train finds it loaded; returns the thread (started once per process). The GUI thread never
    waits on it: a job started earlier waits in its own launch thread."""
    return _job_server.start()


def job_server_state() -> str | None:
    """The analysis jobs' fork server as :func:`start_job_server` left it in this process: None (never started),
    ``"starting"`` (importing :data:`JOB_PRELOAD`) or ``"ready"``."""
    started = _job_server.thread
    if started is None:
        return None
    return "starting" if started.is_alive() else "ready"


class ProcessJob:
    """Runs ``module:function(**kwargs)`` in a separate process (forked from :func:`job_context`'s server), so heavy
    encoding and analyses neither freeze the GUI nor compete for its GIL, and :meth:`cancel` really stops them
    (terminate).

    Nothing here blocks the calling (GUI) thread: :meth:`start` hands the process start to a launch thread (the first
    start waits there until the fork server has loaded the analysis stack, seconds), :meth:`poll` only drains a queue
    and :meth:`cancel` terminates without waiting for the process to end.

    Progress: a function that takes a ``progress`` argument gets a callback that sends the library's
    :class:`rigctl.core.progress.ProgressEvent` s to this process; :meth:`poll` turns the newest into
    :attr:`fraction` and :attr:`message` (:attr:`events` keeps every one received). The interface mirrors
    :class:`Job` (``done``, ``fraction``, ``message``, ``result``, ``error``).
    """

    def __init__(self, target: str, **kwargs):
        self.target, self.kwargs = target, kwargs
        self.q: Any = None  # the child's queue and process: made in the launch thread (the queue's lock may start
        self.proc: Any = None  # multiprocessing's resource tracker, a process of its own)
        self.done = False
        self.cancelled = False
        self.fraction = 0.0
        self.message = "starting a worker process..."
        self.result: Any = None
        self.error: str | None = None
        self.traceback: str | None = None
        self.events: list = []  # the ProgressEvents received, in order
        self._counted_stage: str | None = None  # the stage of the newest counted event
        self.started = threading.Event()  # set once the process runs (or could not be started)
        self._launch_error: str | None = None
        self._lock = threading.Lock()  # the launch thread's start vs cancel

    def start(self) -> "ProcessJob":
        """Start the process from a launch thread; returns at once."""
        threading.Thread(target=self._launch, name="job-launch", daemon=True).start()
        return self

    def _launch(self) -> None:
        with self._lock:
            if not self.cancelled:
                try:
                    ctx = job_context()
                    self.q = ctx.Queue()
                    self.proc = ctx.Process(target=_process_main, args=(self.target, self.kwargs, self.q),
                                            daemon=True)
                    self.proc.start()
                except BaseException as exc:  # noqa: BLE001 - shown by poll()
                    self._launch_error = f"could not start the worker process: {describe_error(exc)}"
        self.started.set()

    def cancel(self) -> None:
        """Stop the job: its process is terminated (reaped in the background); returns at once."""
        if self.done:
            return
        with self._lock:  # a launch in progress finishes first (the process exists then), a later one never starts
            self.cancelled = True
            started = self.proc is not None and self.proc._popen is not None
        if started:
            self.proc.terminate()
            threading.Thread(target=self.proc.join, args=(5,), name="job-reap", daemon=True).start()
        self.done = True
        self.error = "cancelled"

    def poll(self) -> None:
        """Drain the child's messages (call from the GUI timer; never blocks)."""
        if self.done:
            return
        if not self.started.is_set():
            return  # still launching
        if self._launch_error is not None:
            self.done, self.error = True, self._launch_error
            return
        alive = self.proc.is_alive()  # before draining: a result sent just before exiting is still read
        while True:
            try:
                item = self.q.get_nowait()
            except queue.Empty:
                break
            if item[0] == "progress":
                self._on_progress(item[1])
            elif item[0] == "result":
                self.result = item[1]
                self.done = True
            elif item[0] == "error":
                self.error, self.traceback = item[1], item[2]
                self.done = True
        if not self.done and not alive and self.proc.exitcode is not None:
            self.done = True
            self.error = self.error or f"worker process exited with code {self.proc.exitcode}"
        if self.done and not alive:
            self.proc.join(0)  # reap it (it has exited); a process still exiting is reaped by multiprocessing later

    def _on_progress(self, event) -> None:
        self.events.append(event)
        if event.total is None:
            self.message = event.message
            if event.stage != self._counted_stage:  # a stage that counts nothing (fitting force coefficients):
                self.fraction = 0.0  # busy, not the previous stage's 100 %
            return
        self._counted_stage = event.stage
        self.fraction = event.fraction
        self.message = f"{event.stage}: {event.done}/{event.total}" + (f" ({event.message})" if event.message else "")
