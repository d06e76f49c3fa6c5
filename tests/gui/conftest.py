"""GUI test setup: a real Qt window offscreen (QT_QPA_PLATFORM=offscreen), QSettings and the rig config file in a
temporary directory (per test, or per module for the shared window; both restored afterwards), and one main window
on the simulated rig shared by a test module (opening the rig takes a few seconds: boards boot, the actuator homes).
Every test here is marked ``gui`` (tests/conftest.py)."""

from __future__ import annotations

import contextlib
import os

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

import pytest  # noqa: E402

from rigctl_gui.events import wait_for  # noqa: E402

#: the QSettings user-scope INI folders in force, innermost last (Qt has no getter for QSettings.setPath)
_SETTINGS_PATHS: list[str] = []


@contextlib.contextmanager
def private_home(home):
    """``$RIGCTL_CONFIG`` = ``home/rig.json`` and the QSettings user folder ``home/settings`` (never the user's)
    while the block runs; the previous environment and QSettings folder are restored afterwards."""
    from PySide6 import QtCore

    def set_path(path: str) -> None:
        QtCore.QSettings.setPath(QtCore.QSettings.IniFormat, QtCore.QSettings.UserScope, path)

    if not _SETTINGS_PATHS:  # Qt's default: the XDG config folder
        _SETTINGS_PATHS.append(QtCore.QStandardPaths.writableLocation(QtCore.QStandardPaths.GenericConfigLocation))
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("RIGCTL_CONFIG", str(home / "rig.json"))
        _SETTINGS_PATHS.append(str(home / "settings"))
        set_path(_SETTINGS_PATHS[-1])
        try:
            yield home
        finally:
            _SETTINGS_PATHS.pop()
            set_path(_SETTINGS_PATHS[-1])


@pytest.fixture
def gui_home(tmp_path_factory):
    """A private home for QSettings and the rig config for one test (:func:`private_home`)."""
    with private_home(tmp_path_factory.mktemp("gui_home")) as home:
        yield home


@pytest.fixture(autouse=True)
def _never_the_users_home(request, tmp_path_factory):
    """Every GUI test runs in a private home: its own (:func:`gui_home`), else its module's window's, else a fresh
    one."""
    if {"gui_home", "window"} & set(request.fixturenames):
        yield
        return
    with private_home(tmp_path_factory.mktemp("home")):
        yield


@pytest.fixture(scope="module")
def window_home(tmp_path_factory):
    """The private home (:func:`private_home`) of a module's shared :func:`window`."""
    with private_home(tmp_path_factory.mktemp("window_home")) as home:
        yield home


@pytest.fixture(scope="module")
def window(qapp, window_home):
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
