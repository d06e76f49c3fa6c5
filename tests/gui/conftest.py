"""GUI test setup: a real Qt window offscreen (QT_QPA_PLATFORM=offscreen), QSettings and the rig config file in a
temporary directory (per test, or per module for the shared window; both restored afterwards), and one main window
on the simulated rig shared by a test module (opening the rig takes a few seconds: boards boot, the actuator homes).
Every test here is marked ``gui`` (tests/conftest.py). :func:`x_server`: a private X server with a window manager,
for the tests that need real X (test_gui_x11.py): Xvfb on a free display number (``-displayfd``: parallel test
workers never collide) with openbox, so windows get real frames, focus and placement; needs the Debian packages
xvfb, openbox and xdotool (scripts/test.sh installs them)."""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import time
from collections.abc import Callable, Iterator

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

import pytest  # noqa: E402

from rigctl_gui.events import wait_for  # noqa: E402

from ..conftest import skip_or_fail  # noqa: E402

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
    if {"gui_home", "window", "inprocess_window"} & set(request.fixturenames):
        yield
        return
    with private_home(tmp_path_factory.mktemp("home")):
        yield


@pytest.fixture(scope="module")
def window_home(tmp_path_factory):
    """The private home (:func:`private_home`) of a module's shared :func:`window`."""
    with private_home(tmp_path_factory.mktemp("window_home")) as home:
        yield home


def holds_within(app, check: Callable[[], None], timeout_s: float = 10.0) -> None:
    """Process ``app``'s events until ``check()`` raises no AssertionError (:func:`rigctl_gui.events.wait_for`), at
    most ``timeout_s`` of wall time; if it never held, call it once more and let its AssertionError out. A layout
    settles in events of its own (a tab shown for the first time, a text set, a strip shown): a check of it judges
    the settled layout, and the bound only ends a hang (a fixed 0.3 s wait before such checks failed beside two CPU
    hogs in loaded CI runs, and passed on its rerun)."""

    def holds() -> bool:
        try:
            check()
        except AssertionError:
            return False
        return True

    if not wait_for(app, holds, timeout_s):
        check()


#: the dead man's limit of the shared test windows, s: the GUI tests share a loaded machine, where the GUI thread can
#: be starved for half a second; a test that is not about the dead man's switch must not see the drum stopped by it
#: (test_gui_responsive.py sets the app's own 0.5 s on its window where it checks the switch)
TEST_DEADMAN_S = 5.0


@pytest.fixture(autouse=True, scope="session")
def _test_deadman_limit():
    """Every main window of the GUI tests gets :data:`TEST_DEADMAN_S` as its dead man's limit."""
    from rigctl_gui.app import MainWindow

    MainWindow.deadman_s = TEST_DEADMAN_S
    yield


#: after this long (s) a shown main window has done its delayed fits to the screen (MainWindow.showEvent's timers)
FITTED_AFTER_SHOW_S = 1.6


def _main_window(qapp, kind: str):
    """The main window connected to a fresh rig of ``kind``, shown at 1400x900; closed (rig stopped) afterwards."""
    from rigctl_gui.app import MainWindow, configure_pyqtgraph
    from rigctl_gui.workers import RigSource

    configure_pyqtgraph()
    w = MainWindow(RigSource(kind))
    w.resize(1400, 900)
    w.show()
    shown = time.monotonic()
    wait_for(qapp, lambda: w.handle is not None or "not connected" in w.source_label.text(), 30)
    assert w.handle is not None, w.banner.text
    # the window's own fits to its screen (MainWindow.showEvent: 0.3 and 1.5 s after it is first shown) are over
    # before a test sizes it (one fired in a test that had just resized it: the window shrank under it)
    wait_for(qapp, lambda: False, max(0.0, FITTED_AFTER_SHOW_S - (time.monotonic() - shown)))
    yield w
    w.close()
    # delete the Qt objects now, while the QApplication lives (a GC pass at interpreter exit would segfault)
    w.deleteLater()
    qapp.processEvents()
    import gc

    del w
    gc.collect()
    qapp.processEvents()


@pytest.fixture(scope="module")
def window(qapp, window_home):
    """The main window connected to a fresh simulated rig on ptys (module-scoped); closed (rig stopped) afterwards."""
    yield from _main_window(qapp, "sim")


@pytest.fixture(scope="module")
def inprocess_window(qapp, window_home):
    """The main window connected to the in-process rig (module-scoped): the GUI's flows on a simulated clock, a trial
    in a fraction of its time; closed afterwards."""
    yield from _main_window(qapp, "inprocess")


#: a short protocol of the GUI tests (:func:`gui_protocol`): two textures, ``n`` trials each, 0.3 s trials
GUI_PROTOCOL = """
name = "gui_test"
description = "GUI test: two textures, short trials"
textures = ["A", "L"]
speeds_mm_s = [100]
forces_g = [300]
trials_per_condition = {n}
duration_s = 0.3
order = "blocked"

[settle]
force_timeout_s = 10
speed_timeout_s = 5
speed_tolerance_mm_s = 3
"""


def gui_protocol(tmp_path, n: int) -> str:
    """:data:`GUI_PROTOCOL` with ``n`` trials a texture, written under ``tmp_path``; its path."""
    p = tmp_path / f"gui_test_{n}.toml"
    p.write_text(GUI_PROTOCOL.format(n=n))
    return str(p)


def run_queue_wait_s() -> float:
    """The calling thread's time spent runnable but waiting for a CPU so far, s (Linux schedstat: the machine's
    load, not the thread's own work nor a wait it is blocked in); 0 where the kernel does not tell."""
    try:
        with open("/proc/thread-self/schedstat") as f:
            return int(f.read().split()[1]) / 1e9
    except (OSError, IndexError, ValueError):
        return 0.0


TOOLS = ("Xvfb", "openbox", "xdotool")


def missing_tools() -> list[str]:
    return [t for t in TOOLS if shutil.which(t) is None]


@contextlib.contextmanager
def x_server(width: int, height: int) -> Iterator[dict]:
    """Start Xvfb (one ``width`` x ``height`` x 24 screen) and openbox; yield the environment to run a client in
    (``DISPLAY``, ``QT_QPA_PLATFORM=xcb``); kill both afterwards. Skips the test when a tool is missing (fails under
    ``CI=true``)."""
    miss = missing_tools()
    if miss:
        skip_or_fail(f"{', '.join(miss)} not installed (scripts/test.sh installs them)")
    r, wfd = os.pipe()
    xvfb = subprocess.Popen(["Xvfb", "-displayfd", str(wfd), "-screen", "0", f"{width}x{height}x24", "-nolisten",
                             "tcp"], pass_fds=(wfd,), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    os.close(wfd)
    wm = None
    try:
        with os.fdopen(r) as f:
            number = f.readline().strip()
        if not number:
            raise RuntimeError("Xvfb did not report its display number")
        env = dict(os.environ, DISPLAY=f":{number}", QT_QPA_PLATFORM="xcb")
        env.pop("WAYLAND_DISPLAY", None)
        wm = subprocess.Popen(["openbox", "--sm-disable"], env=env, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:  # openbox is up once its own (WM check) window exists
            probe = subprocess.run(["xdotool", "search", "--maxdepth", "1", "--class", "openbox"], env=env,
                                   capture_output=True, text=True)
            if probe.returncode == 0 or wm.poll() is not None:
                break
            time.sleep(0.2)
        time.sleep(0.5)
        yield env
    finally:
        for p in (wm, xvfb):
            if p is not None and p.poll() is None:
                p.terminate()
                try:
                    p.wait(5)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait(5)
