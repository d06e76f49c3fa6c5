"""The rigctl desktop app (PySide6 + pyqtgraph): a thin face over the :mod:`rigctl` library.

Every rig-, encoding- and analysis-related operation is imported from ``rigctl``; the modules here only lay out
widgets, move work into worker threads (:mod:`gui.workers`) and pull results at the GUI's own pace with QTimers.

Modules, one per panel: :mod:`gui.app` (QApplication, main window, ``--screenshot``), :mod:`gui.connect_dialog`,
:mod:`gui.control_panel`, :mod:`gui.live_view`, :mod:`gui.protocol_tab`, :mod:`gui.analysis_tab`,
:mod:`gui.calibration_tab`, :mod:`gui.classify_view`, :mod:`gui.status_bar`, :mod:`gui.workers`.
"""

from __future__ import annotations

__all__ = ["main"]


def main(argv=None) -> int:
    """Start the app (see :func:`gui.app.main`)."""
    from gui.app import main as _main

    return _main(argv)
