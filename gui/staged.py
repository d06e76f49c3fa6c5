"""A widget built in steps: one step per pass of the Qt event loop, so the GUI thread answers in between (the
library's dead man's switch stops a pressing or turning rig when the GUI thread is silent 0.5 s; issue 51). The Live
view and the Analysis tab build their plots this way when first shown (:mod:`rigctl_gui.live_view`,
:mod:`rigctl_gui.analysis_tab`)."""

from __future__ import annotations

from collections.abc import Iterator

from PySide6 import QtCore

__all__ = ["StagedBuild", "StagedWidget"]


class StagedBuild(QtCore.QObject):
    """Runs ``steps`` (a generator that yields after each piece of work, e.g. a plot) one step per pass of the event
    loop (a 0 ms single-shot QTimer); :attr:`done` is emitted once it is exhausted, by the last step or by
    :meth:`finish` (which runs what is left at once: a caller that needs the whole widget)."""

    done = QtCore.Signal()

    def __init__(self, steps: Iterator[None], parent: QtCore.QObject | None = None) -> None:
        super().__init__(parent)
        self._steps: Iterator[None] | None = steps
        self._timer = QtCore.QTimer(self, singleShot=True, interval=0)
        self._timer.timeout.connect(self._step)
        self._timer.start()

    @property
    def running(self) -> bool:
        """Steps are left."""
        return self._steps is not None

    def _step(self) -> None:
        if self._steps is None:
            return
        try:
            next(self._steps)
        except StopIteration:
            self._steps = None
            self.done.emit()
        else:
            self._timer.start()

    def finish(self) -> None:
        """Run every step left now (nothing when done)."""
        steps, self._steps = self._steps, None
        if steps is not None:
            self._timer.stop()
            for _ in steps:
                pass
            self.done.emit()


class StagedWidget:
    """What a widget built in steps offers its callers (a mixin before the Qt base class: ``class LiveView(StagedWidget,
    QtWidgets.QWidget)``); the widget keeps its :class:`StagedBuild` in ``_staged`` (None when built at once)."""

    _staged: StagedBuild | None = None

    @property
    def building(self) -> bool:
        """A staged build (``staged=True``) is under way: the widget's parts are not all there yet."""
        return self._staged is not None and self._staged.running

    def finish_build(self) -> None:
        """Finish a staged build now (what needs the whole widget: attach, a window change, a caller)."""
        if self._staged is not None:
            self._staged.finish()
