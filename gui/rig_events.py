"""The GUI as a subscriber of the rig's monitor (:class:`rigctl.operations.RigMonitor`, owned by the open
:class:`rigctl.operations.RigControl`): the library polls the drum controller, feeds its watchdog and runs the dead
man's switch; the GUI only listens and proves it is alive.

:class:`RigEvents` hands the monitor's :class:`rigctl.operations.RigEvent` s (called in the monitor's thread) to the
GUI thread as a queued Qt signal, and beats the GUI's :class:`rigctl.operations.Heartbeat` from a QTimer on the GUI
thread every :data:`BEAT_MS`: when the GUI thread does not answer for the heartbeat's timeout (0.5 s) while the rig
moves, the library stops the rig, and the GUI shows why once it wakes (the ``deadman`` event waits in the queue).
"""

from __future__ import annotations

from collections.abc import Callable

from PySide6 import QtCore

from rigctl.operations import DEADMAN_TIMEOUT_S, Heartbeat, RigEvent, RigMonitor

__all__ = ["BEAT_MS", "RigEvents"]

#: how often the GUI thread beats its heartbeat, ms (a fifth of the dead man's limit)
BEAT_MS = 100


class RigEvents(QtCore.QObject):
    """Subscribes to ``monitor`` and re-emits its events as :attr:`happened` on the GUI thread; beats a heartbeat named
    ``name`` (limit ``timeout_s``) every :data:`BEAT_MS` from the GUI thread. :meth:`close` ends both (before the rig
    closes)."""

    happened = QtCore.Signal(object)  # a rigctl.operations.RigEvent, delivered on the GUI thread

    def __init__(self, monitor: RigMonitor, parent: QtCore.QObject | None = None, *, name: str = "GUI thread",
                 timeout_s: float = DEADMAN_TIMEOUT_S) -> None:
        super().__init__(parent)
        self.monitor = monitor
        self.heartbeat: Heartbeat | None = monitor.heartbeat(name, timeout_s)
        self.timer = QtCore.QTimer(self)
        self.timer.setTimerType(QtCore.Qt.TimerType.PreciseTimer)
        self.timer.timeout.connect(self.heartbeat.beat)
        self.timer.start(BEAT_MS)
        # emitted from the monitor's thread: Qt queues it to this object's (the GUI) thread
        self._unsubscribe: Callable[[], None] | None = monitor.subscribe(self._relay)

    def _relay(self, ev: RigEvent) -> None:
        if ev.kind != "status":  # the plots read the monitor's history at the frame clock: no signal per read
            self.happened.emit(ev)

    def close(self) -> None:
        """Unsubscribe and stop the heartbeat (the face goes away in order: nothing trips)."""
        self.timer.stop()
        if self._unsubscribe is not None:
            self._unsubscribe()
            self._unsubscribe = None
        if self.heartbeat is not None:
            self.heartbeat.close()
            self.heartbeat = None
