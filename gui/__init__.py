"""The rigctl desktop app (PySide6 + pyqtgraph): a thin face over the :mod:`rigctl` library.

Every rig-, encoding- and analysis-related operation is imported from ``rigctl``; the modules here only lay out
widgets, move work into worker threads (:mod:`rigctl_gui.workers`) and pull results at the GUI's own pace with QTimers.

Modules, one per panel: :mod:`rigctl_gui.app` (QApplication, main window, ``--screenshot``), :mod:`rigctl_gui.connect_dialog`,
:mod:`rigctl_gui.control_panel`, :mod:`rigctl_gui.live_view`, :mod:`rigctl_gui.protocol_tab`, :mod:`rigctl_gui.analysis_tab`,
:mod:`rigctl_gui.calibration_tab`, :mod:`rigctl_gui.classify_view`, :mod:`rigctl_gui.handheld_tab`,
:mod:`rigctl_gui.status_bar`, :mod:`rigctl_gui.workers`;
and shared by them: :mod:`rigctl_gui.dialogs` (every dialog non-modal, Esc is STOP), :mod:`rigctl_gui.messages` (the
event log, the exception guard, plain-text errors), :mod:`rigctl_gui.widgets` (fixed-width side panels).
"""

from __future__ import annotations

__all__ = ["main"]


def main(argv=None) -> int:
    """Start the app (see :func:`rigctl_gui.app.main`)."""
    from rigctl_gui.app import main as _main

    return _main(argv)
