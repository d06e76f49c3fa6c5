"""The model boards' clock on a :class:`rigctl.core.shared_clock.SharedClock`: the simulated rig's physics thread
advances its milliseconds no further than the host grants (the clock's horizon), and, paced, no faster than the wall
clock (docs/architecture.md, "Time on a simulated rig").

Paced, millisecond k is simulated no earlier than ``t0 + k`` ms of wall time, as :func:`rigctl.simulation.virtual_uno.
paced_loop` does, but a world the host held back (a starved host) does not catch up the wall time it lost in a burst
(the host would see a second of simulated time go by in a few ms of its own): the pacing starts again from where the
world was let go. Unpaced, the world runs as fast as the CPU and the host's grants allow, in steps of at most
``tick_s`` of simulated time (the host's reads interleave with the stream as on a wire).

A paced world that streams a live sample source (``keep_wall``: a plugin's serial board, an LSL stream) keeps the wall
clock's time in the long run instead: the source's samples come on the wall clock, and a world that did not catch up
the time its host lost asked for them ever later (the my-hardware guide's board, beside two CPU hogs: its reader's 10 s
buffer ran full and dropped samples without a gap). It catches up in steps of at most :data:`CATCH_UP_STEP_MS`, as
fast as the host's grants allow (a host that still gets no CPU still holds it).
"""

from __future__ import annotations

import logging
import os
import select
import threading
import time
from collections.abc import Callable

from rigctl.core.shared_clock import SharedClock

log = logging.getLogger(__name__)

#: a paced world that fell this far behind the wall clock for want of CPU of its own does not catch up in a burst, s
MAX_CATCH_UP_S = 0.25
#: the longest wait of a world held back by the host before it looks at the horizon again, s (a grant wakes it)
HELD_WAIT_S = 0.005
#: the first wait of a world whose board is still taking in or answering a request (``board_busy``), s; each further
#: one twice the last, up to :data:`BUSY_WAIT_MAX_S`
BUSY_WAIT_S = 0.0005
#: the longest such wait, s: the world stands meanwhile, so a longer wait costs no simulated time, only wall time;
#: and a world that looks every 0.5 ms burns CPU the bytes' own way needs (a pty hands them on through a kernel worker
#: of ordinary priority, which the boards' raised threads, polling, kept from the CPU for seconds beside CPU hogs)
BUSY_WAIT_MAX_S = 0.005
#: the longest a board's request handling holds the world, s of wall time (a thread of the board that never gets
#: to it: the world goes on, and the host may see a late answer, as before the shared clock). 10 s: on a loaded
#: 2-core machine (a CI run at load 15-20) the virtual Mega's server thread went without CPU for more than the 2 s this
#: was, the world moved on under the waiting host, and its answer timeout (judged on the shared clock) ran out three
#: times: a DrumTimeout of a starved board, not of a silent one (test_drum_conformance[sim])
BUSY_MAX_S = 10.0
#: the longest step of a world catching up the wall clock (``keep_wall``), ms: the host's reads interleave with the
#: burst as on a wire
CATCH_UP_STEP_MS = 20


class WorldLoop:
    """Runs ``step(n_ms)`` on the shared clock (module doc); :meth:`run` is the thread's body.

    Parameters
    ----------
    clock : the shared clock (its horizon bounds the world).
    now_ms : the world's time, ms (the model's; ``step(n)`` moves it on by ``n``).
    step : advances the world by ``n`` ms.
    paced : True: no faster than the wall clock; False: as fast as it may.
    tick_s : period of the steps while busy (``idle()`` False), s of wall time paced, of simulated time unpaced.
    idle, idle_tick_s : after a step for which ``idle()`` is True, the next comes ``idle_tick_s`` later (paced).
    wake_fd : read end of a pipe; a byte ends a wait (a command to act on, or a new grant while :attr:`held`).
    board_busy : whether a board's own threads outside this loop are still taking in or answering a request of the
        host (the virtual Mega's Modbus server and pty bridge: :meth:`rigctl.simulation.pty.PtyBridge.bytes_to_board`,
        ``bytes_from_board``). The firmware does that within about a millisecond of its own time, so the world does
        not move on meanwhile (at most :data:`BUSY_MAX_S` of wall time): a starved server thread is a paused board,
        not a late one.
    horizon : how far the world may run, s (default the clock's :attr:`SharedClock.horizon_s`; a rig whose host
        may be another process: the lower of that and the other process's grant, :mod:`rigctl.core.port_clock`).
    keep_wall : paced, catch up the wall time the host or the world itself lost (module doc: a live sample source).
    """

    def __init__(self, clock: SharedClock, now_ms: Callable[[], int], step: Callable[[int], object], *,
                 paced: bool = True, tick_s: float = 0.005, idle: Callable[[], bool] | None = None,
                 idle_tick_s: float | None = None, wake_fd: int | None = None,
                 board_busy: Callable[[], bool] | None = None, horizon: Callable[[], float] | None = None,
                 keep_wall: bool = False) -> None:
        self.clock = clock
        self.keep_wall = bool(keep_wall) and paced
        self._horizon_s = horizon if horizon is not None else (lambda: clock.horizon_s)
        self.now_ms = now_ms
        self.step = step
        self.paced = paced
        self.tick_ms = max(1, int(round(tick_s * 1000)))
        self.idle = idle
        self.idle_tick_ms = max(self.tick_ms, int(round((idle_tick_s or tick_s) * 1000)))
        self.wake_fd = wake_fd
        self.board_busy = board_busy
        #: the world waits for the host's grant (the host is starved, or the world unpaced is ahead)
        self.held = False
        #: wall seconds the world spent held back by the host
        self.held_s = 0.0

    def _wait(self, seconds: float) -> bool:
        """Wait up to ``seconds`` of wall time or until woken; True if woken."""
        if seconds <= 0.0:
            return False
        if self.wake_fd is None:
            time.sleep(seconds)
            return False
        if select.select([self.wake_fd], [], [], seconds)[0]:
            try:
                os.read(self.wake_fd, 4096)
            except BlockingIOError:
                pass
            return True
        return False

    def run(self, stop: threading.Event) -> None:
        monotonic, stopped, clock = time.monotonic, stop.is_set, self.clock
        done = self.now_ms()
        wall0, sim0 = monotonic(), done  # paced: ms sim0 + k no earlier than wall0 + k ms
        ahead = self.tick_ms
        woken = False
        busy, busy_since, busy_waits = self.board_busy, None, 0
        while not stopped():
            limit = int(self._horizon_s() * 1000.0 + 1e-9)
            if busy is not None and busy():  # the board is at a request: its time stands still meanwhile
                now = monotonic()
                busy_since = now if busy_since is None else busy_since
                if now - busy_since < BUSY_MAX_S:
                    limit = done
            else:
                busy_since, busy_waits = None, 0
            if self.paced:
                due = sim0 + int((monotonic() - wall0) * 1000.0)
            else:
                due = done + self.tick_ms
            target = min(due, limit)
            held = limit < due  # the host's grant (or a board at a request) holds the world short of its due time
            if self.keep_wall and target - done > CATCH_UP_STEP_MS:  # catching up the wall: a step at a time
                target, held = done + CATCH_UP_STEP_MS, False
            n = target - done
            if n > 0:
                try:
                    self.step(n)
                except Exception:  # keep the clock alive; the error is logged
                    log.exception("simulation step failed")
                done = target
                clock.moved()
                woken = False
                if self.idle is not None:
                    ahead = self.idle_tick_ms if self.idle() else self.tick_ms
            if held:  # held back by the host: wait for its grant
                self.held = True
                t0 = monotonic()
                if busy_since is not None:
                    time.sleep(min(BUSY_WAIT_MAX_S, BUSY_WAIT_S * 2.0 ** min(16, busy_waits)))
                    busy_waits += 1
                elif int(self._horizon_s() * 1000.0 + 1e-9) <= done:
                    self._wait(HELD_WAIT_S)
                self.held = False
                self.held_s += monotonic() - t0
                if self.paced and not self.keep_wall:  # the pacing starts again from here: no burst for the time
                    wall0, sim0 = monotonic(), done  # the host lost
                continue
            if not self.paced:
                continue
            behind_s = (due - done) / 1000.0
            if behind_s > MAX_CATCH_UP_S and not self.keep_wall:  # the world itself starved: no burst either
                wall0, sim0 = monotonic(), done
            wait = wall0 + (done - sim0 + (1 if woken else ahead)) / 1000.0 - monotonic()
            if self._wait(wait):
                woken = True
