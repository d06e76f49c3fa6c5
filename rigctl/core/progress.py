"""Progress of long work as typed events: the one way every long-running function of rigctl reports how far it is.

:func:`rigctl.acquisition.runner.run_protocol`, :func:`rigctl.encoding.pipeline.encode_session`,
:func:`rigctl.simulation.dataset.generate_dataset`, the importers (:mod:`rigctl.storage.importers`,
:mod:`rigctl.storage.fabricslide`), the NWB export and the analyses (:mod:`rigctl.analysis.tasks`) take a
``progress`` callback and call it with a :class:`ProgressEvent` as work gets done. The library never draws a bar or
prints: the command line attaches tqdm (:mod:`rigctl.cli.progress`), the GUI its progress bars (``rigctl_gui``), a
test a list's ``append``.

Events of one stage come in order: ``done`` starts at 0 (the stage began, ``total`` known) and rises to ``total``
(the stage is over). A note with no count (``total`` None, e.g. "fitting force coefficients on 240 trials") is a
message of the stage, shown as text.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

__all__ = ["ProgressEvent", "ProgressCallback", "Stage", "as_callback", "note"]


@dataclass(frozen=True)
class ProgressEvent:
    """How far one stage of a long function is.

    Attributes
    ----------
    stage : str
        What is being done, in words ("reading trials", "encoding", "dataset ds.h5", "textures/groups", "trials").
    done : int
        Units finished in this stage (0 .. ``total``).
    total : int or None
        Units in the stage; None for a message that counts nothing.
    message : str
        Optional words for the operator (a note, the trial just recorded); "" when none.
    unit : str
        What is counted ("trial", "fit", "file").
    """

    stage: str
    done: int
    total: int | None
    message: str = ""
    unit: str = "trial"

    @property
    def fraction(self) -> float | None:
        """``done / total`` in [0, 1], or None for a message without a count."""
        if self.total is None:
            return None
        return min(1.0, self.done / self.total) if self.total > 0 else 1.0


#: what a ``progress`` argument takes: a callable receiving each event (its return value is ignored)
ProgressCallback = Callable[[ProgressEvent], object]


def _ignore(event: ProgressEvent) -> None:
    return None


def as_callback(progress: ProgressCallback | None | bool) -> ProgressCallback:
    """The callback a function reports to: ``progress`` itself, or one that ignores events for None / False.

    Raises
    ------
    TypeError
        For ``True`` or anything else not callable (the library draws no bars itself: pass a callback, e.g.
        ``rigctl.cli.progress.TqdmProgress()`` for tqdm bars on a terminal).
    """
    if progress is None or progress is False:
        return _ignore
    if not callable(progress):
        raise TypeError(f"progress must be a callable taking a ProgressEvent (or None), got {progress!r}; "
                        "for bars on a terminal pass rigctl.cli.progress.TqdmProgress()")
    return progress


class Stage:
    """Reports one stage to a callback: an event with ``done=0`` when made, one per :meth:`advance`.

    Parameters
    ----------
    progress : the ``progress`` argument of the calling function (callable, None or False).
    stage, total, unit : see :class:`ProgressEvent`.
    done : units already finished when the stage starts (a resumed run).
    """

    def __init__(self, progress: ProgressCallback | None | bool, stage: str, total: int, *, unit: str = "trial",
                 done: int = 0):
        self.callback = as_callback(progress)
        self.stage, self.total, self.unit, self.done = stage, int(total), unit, int(done)
        self.callback(ProgressEvent(stage, self.done, self.total, "", unit))

    def advance(self, n: int = 1, message: str = "") -> None:
        """``n`` more units finished (an event with the new ``done``)."""
        self.done += int(n)
        self.callback(ProgressEvent(self.stage, self.done, self.total, message, self.unit))

    def note(self, message: str) -> None:
        """A message within the stage (an event with ``total`` None)."""
        self.callback(ProgressEvent(self.stage, self.done, None, message, self.unit))


def note(progress: ProgressCallback | None | bool, stage: str, message: str) -> None:
    """Report a message that counts nothing (``total`` None) to ``progress``."""
    as_callback(progress)(ProgressEvent(stage, 0, None, message, ""))
