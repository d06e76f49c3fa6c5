"""One health model for both boards' links: connected / stalled / lost / reconnected / controller reset.

A :class:`LinkHealth` is fed what the host can see of a link at any moment (is the transport up, how many things
have arrived so far, the drum controller's heartbeat) and says in which state the link is, returning a
:class:`LinkEvent` at each change. It is pure (no threads, no clock of its own, no Qt): the GUI calls
:meth:`LinkHealth.observe` from its timer with ``time.monotonic()`` and shows, logs and draws what it returns; a
test feeds it made-up times.

States (:class:`LinkState`):

- ``NOT_CONNECTED``: no link object (the rig is not open);
- ``CONNECTED``: the transport is up and things arrive;
- ``STALLED``: the transport says it is up but nothing has arrived for ``stall_after_s`` (a taxel board that stopped
  streaming, a controller that stopped answering without the port going away);
- ``LOST``: the transport says it is down (a pulled cable, a failed poll);
- ``RECONNECTED``: things arrive again after ``STALLED``, ``LOST`` or ``CONTROLLER_RESET``; held for
  ``settle_s``, then ``CONNECTED``;
- ``CONTROLLER_RESET``: the drum controller's heartbeat (input register HEARTBEAT, +1 every 10 ms, wraps at 65536;
  docs/wire-protocol.md table 2.2) went back by more than a wrap explains: the board restarted (brown-out, watchdog,
  a reset on port open), so homing and the setpoints are gone; held for ``settle_s``, then ``CONNECTED``.

:func:`dropped_frames_severity` grades a count of dropped taxel frames against a protocol's ``max_dropped_frames``.
"""

from __future__ import annotations

import dataclasses
import enum

__all__ = ["LinkState", "LinkEvent", "LinkHealth", "dropped_frames_severity", "HEARTBEAT_HZ"]

#: the drum controller's heartbeat rate, counts per second (docs/wire-protocol.md table 2.2: +1 every 10 ms)
HEARTBEAT_HZ = 100.0
_HEARTBEAT_WRAP = 65536


class LinkState(enum.StrEnum):
    NOT_CONNECTED = "not connected"
    CONNECTED = "connected"
    STALLED = "stalled"
    LOST = "lost"
    RECONNECTED = "reconnected"
    CONTROLLER_RESET = "controller reset"

    @property
    def is_problem(self) -> bool:
        """True for the states an operator must see in red (stalled, lost, controller reset)."""
        return self in (LinkState.STALLED, LinkState.LOST, LinkState.CONTROLLER_RESET)


@dataclasses.dataclass(frozen=True)
class LinkEvent:
    """A change of a link's state: ``board`` (e.g. "taxel board"), the new ``state`` and the ``previous`` one,
    ``time_s`` (the caller's clock, s) and ``text``: one sentence for the operator."""

    board: str
    state: LinkState
    previous: LinkState
    time_s: float
    text: str


class LinkHealth:
    """The health of one board's link, from what the host observes.

    Parameters
    ----------
    board : str
        The board's name in messages ("drum controller", "taxel board").
    stall_after_s : float
        Nothing arrived for this long while the transport is up -> ``STALLED``, s.
    settle_s : float
        ``RECONNECTED`` and ``CONTROLLER_RESET`` turn into ``CONNECTED`` after this long with things arriving, s.
    """

    def __init__(self, board: str, *, stall_after_s: float = 1.0, settle_s: float = 5.0):
        if stall_after_s <= 0 or settle_s < 0:
            raise ValueError("stall_after_s must be > 0 and settle_s >= 0")
        self.board = board
        self.stall_after_s = float(stall_after_s)
        self.settle_s = float(settle_s)
        self.state = LinkState.NOT_CONNECTED
        self.since_s: float | None = None  # when the current state began (caller's clock)
        self._progress: int | None = None
        self._progress_t: float | None = None
        self._heartbeat: tuple[int, float] | None = None
        self.events = 0  # state changes so far

    def observe(self, now_s: float, *, connected: bool | None, progress: int = 0,
                heartbeat: int | None = None) -> LinkEvent | None:
        """Feed one observation and return the :class:`LinkEvent` if the state changed (else None).

        ``connected``: the transport's own word (None: no link object); ``progress``: a count that grows while
        things arrive (frames received, status reads answered); ``heartbeat``: the drum controller's HEARTBEAT
        register in the newest answer (None for a board without one)."""
        if connected is None:
            self._progress = self._progress_t = self._heartbeat = None
            return self._go(LinkState.NOT_CONNECTED, now_s)
        if self._progress is None or progress != self._progress:
            arrived = self._progress is not None and progress != self._progress
            self._progress, self._progress_t = int(progress), now_s
        else:
            arrived = False
        if not connected:
            self._heartbeat = None
            return self._go(LinkState.LOST, now_s)
        if heartbeat is not None and self._reset_seen(int(heartbeat), now_s):
            return self._go(LinkState.CONTROLLER_RESET, now_s)
        quiet_s = now_s - (self._progress_t if self._progress_t is not None else now_s)
        st = self.state
        if quiet_s >= self.stall_after_s:
            return self._go(LinkState.STALLED, now_s)
        if st in (LinkState.NOT_CONNECTED,):
            return self._go(LinkState.CONNECTED, now_s)
        if st in (LinkState.STALLED, LinkState.LOST):
            return self._go(LinkState.RECONNECTED, now_s) if arrived else None
        if st in (LinkState.RECONNECTED, LinkState.CONTROLLER_RESET):
            held = self.since_s is not None and now_s - self.since_s >= self.settle_s
            return self._go(LinkState.CONNECTED, now_s) if held else None
        return None

    def _reset_seen(self, heartbeat: int, now_s: float) -> bool:
        """True when ``heartbeat`` went back by more than a wrap explains since the last one seen."""
        last, self._heartbeat = self._heartbeat, (heartbeat, now_s)
        if last is None:
            return False
        prev, prev_t = last
        ahead = (heartbeat - prev) % _HEARTBEAT_WRAP  # counts advanced, assuming no reset
        expected = max(0.0, now_s - prev_t) * HEARTBEAT_HZ
        # a running controller advances ~expected counts; a restarted one restarts near 0, which reads as a huge
        # advance modulo the wrap (or as going back). Allow 3x the expected advance plus 1 s for a slow host.
        return heartbeat < prev and ahead > 3 * expected + HEARTBEAT_HZ

    def _go(self, state: LinkState, now_s: float) -> LinkEvent | None:
        previous = self.state
        if state == previous:
            return None
        self.state, self.since_s = state, now_s
        self.events += 1
        return LinkEvent(self.board, state, previous, now_s, self._text(state, previous))

    def _text(self, state: LinkState, previous: LinkState) -> str:
        b = self.board
        if state == LinkState.STALLED:
            return f"{b} stalled: nothing received for {self.stall_after_s:g} s although its port is open"
        if state == LinkState.LOST:
            return f"{b} link lost: trying to reconnect"
        if state == LinkState.RECONNECTED:
            return f"{b} reconnected (was {previous.value})"
        if state == LinkState.CONTROLLER_RESET:
            return (f"{b} reset: its heartbeat restarted (power, brown-out or watchdog reset); it has lost its "
                    "homing and setpoints")
        if state == LinkState.CONNECTED:
            return f"{b} connected"
        return f"{b} not connected"


def dropped_frames_severity(dropped: int, max_dropped_frames: int | None) -> str:
    """Grade ``dropped`` taxel frames of a trial against a protocol's ``max_dropped_frames``: ``"ok"`` (none),
    ``"warn"`` (some, within the threshold, or no threshold known: no trial is being judged) or ``"bad"`` (more than
    the threshold: the runner will not keep the trial; :mod:`rigctl.acquisition.runner`)."""
    if dropped <= 0:
        return "ok"
    if max_dropped_frames is None or dropped <= max_dropped_frames:
        return "warn"
    return "bad"
