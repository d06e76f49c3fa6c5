"""GUI test setup: a real Qt window offscreen (QT_QPA_PLATFORM=offscreen), QSettings and the rig config file in a
temporary directory, and one main window on the simulated rig shared by a test module (opening the rig takes a few
seconds: boards boot, the actuator homes)."""

from __future__ import annotations

import os

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

import pytest  # noqa: E402

from rigctl_gui.events import wait_for  # noqa: E402


@pytest.fixture(scope="session")
def gui_home(tmp_path_factory):
    """A private home for QSettings and the rig config (never the user's)."""
    home = tmp_path_factory.mktemp("gui_home")
    os.environ["RIGCTL_CONFIG"] = str(home / "rig.json")
    from PySide6 import QtCore

    QtCore.QSettings.setPath(QtCore.QSettings.IniFormat, QtCore.QSettings.UserScope, str(home / "settings"))
    return home


@pytest.fixture(scope="module")
def window(qapp, gui_home):
    """The main window connected to a fresh simulated rig (module-scoped); closed (rig stopped) afterwards."""
    from rigctl_gui.app import MainWindow, configure_pyqtgraph
    from rigctl_gui.workers import RigSource

    configure_pyqtgraph()
    w = MainWindow(RigSource("sim"))
    w.resize(1400, 900)
    w.show()
    wait_for(qapp, lambda: w.handle is not None or "not connected" in w.source_label.text(), 30)
    assert w.handle is not None, w.banner.label.text()
    yield w
    w.close()
    # delete the Qt objects now, while the QApplication lives (a GC pass at interpreter exit would segfault)
    w.deleteLater()
    qapp.processEvents()
    import gc

    del w
    gc.collect()
    qapp.processEvents()
