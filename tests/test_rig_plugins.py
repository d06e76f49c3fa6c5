"""Rig backends as plugins (issue 38 part 6): rigctl's own rigs are entry points of the group ``rigctl.rigs``; an
out-of-tree package (tests/plugins/rigctl-csvboard: a taxel board sending CSV lines, installed with pip into a folder
of its own) is listed by ``rigctl rigs`` beside a broken plugin (one line, no traceback), records ``quick_check``
from a simulated board on a pty through ``rigctl acquire --rig``, and is opened and recorded through ``rigctl serve``
(loopback, a token) in a separate interpreter that finds it on ``PYTHONPATH``. The GUI's connect dialog opens it
too (tests/gui/test_gui_connect.py). The simulated drum is the in-process one (``drum=inprocess``): each recording
takes a few seconds."""

from __future__ import annotations

import itertools
import os
import socket
import subprocess
import sys
import threading
import time
import tty
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.cli import main
from rigctl.core.rig_plugins import BUILTIN_RIGS
from rigctl.storage.session import open_session

from . import loopback

TOKEN = "plugin-test-token-0123456789"
RIGCTL: list[str] = []  # this worker's preloaded rigctl (tests/conftest.py _preloaded_rigctl)


def test_the_builtin_rigs_are_entry_points():
    """The installed metadata holds rigctl's own rigs in the group (not only the fallback table)."""
    code = "from importlib.metadata import entry_points; print(entry_points(group='rigctl.rigs'))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    for name, target in BUILTIN_RIGS.items():
        assert f"name='{name}', value='{target}', group='rigctl.rigs'" in out, out


def test_the_guide_shows_the_plugin_as_it_is():
    """docs/guides/my-hardware.md's two files are tests/plugins/rigctl-csvboard's, byte for byte."""
    guide = (Path(__file__).resolve().parents[1] / "docs" / "guides" / "my-hardware.md").read_text()
    plugin = Path(__file__).resolve().parent / "plugins" / "rigctl-csvboard"
    for name in ("pyproject.toml", "rigctl_csvboard/__init__.py"):
        block = guide.split(f"\n# {name}\n", 1)[1].split("\n```", 1)[0] + "\n"
        assert block == (plugin / name).read_text(), name


def _rigs_listing(installed: Path) -> list[str]:
    r = CliRunner().invoke(main, ["rigs"])
    assert r.exit_code == 0 and "Traceback" not in r.output, r.output
    return r.output.splitlines()


def test_rigctl_rigs_lists_a_plugin_and_a_broken_one(installed_plugins):
    lines = _rigs_listing(installed_plugins)
    by_name = {line.split()[0]: line for line in lines}
    assert set(BUILTIN_RIGS) | {"csvboard", "broken"} == set(by_name), lines
    assert "rigctl-csvboard 0.1.0" in by_name["csvboard"] and "comma-separated ADC counts" in by_name["csvboard"]
    assert "BROKEN:" in by_name["broken"] and "rigctl_broken_missing" in by_name["broken"], by_name["broken"]
    assert all("BROKEN" not in by_name[n] for n in BUILTIN_RIGS)
    r = CliRunner().invoke(main, ["acquire", "quick_check", "--rig", "broken", "--out", "x.h5"])
    assert r.exit_code == 1 and "does not load: ModuleNotFoundError" in r.output and len(r.output.splitlines()) == 1


def _board(stop: threading.Event) -> str:
    """A simulated CSV board on a pty: 4 counts a line (``i % 900 + 10 * channel``), 200 lines a second (its rate:
    10 every 50 ms on its own clock; a board sending faster than its rate overflows the plugin's buffer, which then
    drops its oldest lines) until ``stop``; returns the port."""
    board, port_fd = os.openpty()
    tty.setraw(port_fd)

    def send() -> None:
        t0 = time.monotonic()
        for k, start in enumerate(itertools.count(0, 10)):
            if stop.is_set():
                break
            data = "".join(",".join(str(i % 900 + 10 * c) for c in range(4)) + "\n" for i in range(start, start + 10))
            out = data.encode()
            while out:  # a pty takes what its buffer holds: the rest written after (a real board's UART waits too)
                out = out[os.write(board, out):]
            time.sleep(max(0.0, t0 + 0.05 * (k + 1) - time.monotonic()))
        os.close(board)

    threading.Thread(target=send, daemon=True).start()
    return os.ttyname(port_fd)


def _check_session(path: Path, *, mode: str) -> np.ndarray:
    with open_session(path) as s:
        trials = s.completed_ids()
        layout = s.layout
        taxels = np.concatenate([np.asarray(s.trial(t).taxels, dtype=np.int64) for t in trials])
        rig = s.rig_config
    assert len(trials) == 6 and layout.n_channels == 4 and layout.sample_rate_hz == 200.0
    assert rig["mode"] == mode, rig
    assert len(taxels) == 6 * 2 * 200 and (np.diff(taxels, axis=1) == 10).all()  # every sample is the board's
    return taxels


# wall: a plugin board on a pty paced by the wall clock (~400 lines a second from a thread of this process)
@pytest.mark.realtime
def test_quick_check_from_a_pty_board_through_acquire(installed_plugins, tmp_path, monkeypatch):
    monkeypatch.setenv("RIGCTL_CONFIG", str(tmp_path / "rig.json"))
    stop = threading.Event()
    port = _board(stop)
    try:
        typo = CliRunner().invoke(main, ["acquire", "quick_check", "--rig", "csvboard", "--rig-option", f"prot={port}",
                                         "--out", str(tmp_path / "t.h5")])
        assert typo.exit_code == 1 and "has no option prot" in typo.output, typo.output
        r = CliRunner().invoke(main, ["acquire", "quick_check", "--rig", "csvboard", "--rig-option", f"port={port}",
                                      "--out", str(tmp_path / "s.h5"), "--quiet"])
    finally:
        stop.set()
    assert r.exit_code == 0 and "trials complete: 6/6" in r.output, r.output
    _check_session(tmp_path / "s.h5", mode="csvboard")
    with open_session(tmp_path / "s.h5") as s:  # the board's lines as they came, each once (it counts up by one)
        for t in s.completed_ids():
            x = np.asarray(s.trial(t).taxels, dtype=np.int64)[:, 0]
            assert (np.diff(x) % 900 == 1).all(), (t, np.flatnonzero(np.diff(x) % 900 != 1)[:5])


#: a protocol that keeps trials with dropped frames (the late plugin's test counts them)
LOSSY_PROTOCOL = """name = "lossy"
textures = ["A", "B"]
speeds_mm_s = [120]
forces_g = [500]
trials_per_condition = 1
duration_s = 1.0
max_dropped_frames = 100000
"""


def test_a_late_plugin_source_is_stored_as_dropped_frames_and_named_in_the_provenance(installed_plugins, tmp_path,
                                                                                    monkeypatch):
    """A SampleSource that has no sample yet returns fewer rows (issue 52: the guide's plugin repeated its last one,
    96 % of a recording, with 0 dropped frames shown): every period without a sample is a dropped frame, exactly the
    lines missing from the stored readings, shown by rigctl info; the plugin's distribution, version and describe()
    are in the session's rig_config and provenance."""
    import rigctl_csvboard

    from rigctl.storage.provenance import read_provenance

    monkeypatch.setenv("RIGCTL_CONFIG", str(tmp_path / "rig.json"))
    board = tmp_path / "board.csv"
    board.write_text("\n".join(",".join(str((i * 7) % 900 + 10 * c) for c in range(4)) for i in range(900)) + "\n")
    read, calls = rigctl_csvboard.CsvBoard.read, [0]

    def late(self, n):  # every 7th call the board is late: none of its samples (they are lost, a gap)
        calls[0] += 1
        rows = read(self, n)
        return rows[:0] if calls[0] % 7 == 0 else rows

    monkeypatch.setattr(rigctl_csvboard.CsvBoard, "read", late)
    proto = tmp_path / "lossy.toml"
    proto.write_text(LOSSY_PROTOCOL)
    r = CliRunner().invoke(main, ["acquire", str(proto), "--rig", "csvboard", "--rig-option", f"file={board}",
                                  "--rig-option", "drum=inprocess", "--out", str(tmp_path / "s.h5"), "--quiet"])
    assert r.exit_code == 0 and "trials complete: 2/2" in r.output, r.output
    total = 0
    with open_session(tmp_path / "s.h5") as s:
        counts = dict(zip(s.completed_ids(), s.trial_counts(s.completed_ids())))
        for t in s.completed_ids():
            x = np.asarray(s.trial(t).taxels, dtype=np.int64)[:, 0]
            lines = (np.diff(x) * 643) % 900  # 643 = 1/7 mod 900: the lines from one stored sample to the next
            assert (lines >= 1).all()  # never a repeated sample
            assert int((lines - 1).sum()) == counts[t]["dropped_frames"] > 0, (t, counts[t])
            total += counts[t]["dropped_frames"]
        plugin = s.rig_config["plugin"]
    assert plugin["distribution"] == "rigctl-csvboard" and plugin["version"] == "0.1.0"
    assert plugin["describe"] == {"board": "csvboard", "port": None, "lines": 900}
    assert read_provenance(tmp_path / "s.h5")["rig"]["plugin"] == plugin
    info = CliRunner().invoke(main, ["info", str(tmp_path / "s.h5")])
    assert f"{total} dropped frames" in info.output, info.output


def test_a_board_that_outran_its_buffer_names_what_it_let_go_as_a_gap(installed_plugins, monkeypatch):
    """The guide's board keeps :data:`BUFFER_S` of samples for a rigctl that fell behind; what it has to let go past
    that is told as periods with no sample (dropped frames) before the samples after the loss, never skipped silently
    (beside two CPU hogs the guide's quick check recorded 6-54 jumps in the board's count with 0 dropped frames)."""
    import rigctl_csvboard

    from rigctl.core.sensor import SensorLayout

    monkeypatch.setattr(rigctl_csvboard, "BUFFER_S", 0.5)  # 100 samples at 200 Hz
    board, port_fd = os.openpty()
    tty.setraw(port_fd)
    opened, written = threading.Event(), [0]

    def first_lines():  # what opening the port waits for (pyserial empties the port's input as it opens)
        while not opened.wait(0.2):
            os.write(board, b"0,10,20,30\n")
            written[0] += 1

    writer = threading.Thread(target=first_lines, daemon=True)
    writer.start()
    try:
        try:
            csv = rigctl_csvboard.CsvBoard(SensorLayout.for_channels(4, sample_rate_hz=200.0),
                                           port=os.ttyname(port_fd))
        finally:
            opened.set()
            writer.join()
        try:
            os.write(board, "".join(f"{i},{i + 10},{i + 20},{i + 30}\n" for i in range(1, 300)).encode())
            written[0] += 299
            deadline = time.monotonic() + 10.0  # (a hang, not a judgement of speed)
            while time.monotonic() < deadline and not (len(csv._buffer) == 100 and csv._buffer[-1][0] == 299):
                time.sleep(0.01)
            assert csv._buffer[-1][0] == 299, list(csv._buffer)
            rows, gap = [], 0
            for _ in range(80):  # rigctl asks for 7 periods at a time
                got = csv.read(7)
                assert got.shape[1] == 4 and len(got) <= 7
                if not rows:
                    gap += 7 - len(got)
                rows.extend(int(x) for x in got[:, 0])
        finally:
            csv.close()
    finally:
        os.close(board)
        os.close(port_fd)
    assert rows == list(range(200, 300)), rows  # the 100 the buffer held, in order, each once
    lost = written[0] - 100  # (the port's first lines, before it opened, were never the board's to keep)
    assert lost >= 200 and lost <= gap < lost + 7, (gap, written)  # a gap at least as long, before them


#: seconds an HTTP request to `rigctl serve` may take before the test calls it hung (not a judgement of speed)
HANG_S = 30.0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_quick_check_through_rigctl_serve(csvboard_plugin, tmp_path):
    import httpx

    board = tmp_path / "board.csv"
    board.write_text("\n".join(",".join(str((i * 7) % 900 + 10 * c) for c in range(4)) for i in range(400)) + "\n")
    port = _free_port()
    url, auth = f"http://127.0.0.1:{port}", {"Authorization": f"Bearer {TOKEN}"}
    env = {**os.environ, "PYTHONPATH": str(csvboard_plugin), "RIGCTL_SERVE_TOKEN": TOKEN,
           "RIGCTL_CONFIG": str(tmp_path / "rig.json"), "XDG_STATE_HOME": str(tmp_path / "state")}
    # this worker's preloaded rigctl: the command takes the plugin from its PYTHONPATH as a fresh interpreter would
    proc = subprocess.Popen([*RIGCTL, "serve", "--rig", "csvboard", "--rig-option",
                             f"file={board}", "--rig-option", "drum=inprocess", "--host", "127.0.0.1", "--port",
                             str(port), "--data-dir", str(tmp_path / "data")], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while True:
            assert proc.poll() is None, proc.communicate()[1]
            try:
                status = loopback.client().get(f"{url}/status", headers=auth, timeout=2)
                break
            except httpx.HTTPError:
                assert time.monotonic() < deadline, "rigctl serve did not answer"
                time.sleep(0.2)
        # HANG_S only bounds a hang: a server recording on a loaded machine may take seconds to answer
        assert status.status_code == 200 and loopback.client().get(f"{url}/status", timeout=HANG_S).status_code == 401
        run = loopback.client().post(f"{url}/runs", json={"protocol": "quick_check", "out": "s.h5"}, headers=auth,
                         timeout=HANG_S)
        assert run.status_code == 201, run.text
        rid = run.json()["id"]
        while (state := loopback.client().get(f"{url}/runs/{rid}", headers=auth, timeout=HANG_S).json()["state"]) in (
                "queued", "running"):
            assert time.monotonic() < deadline + 120, state
            time.sleep(0.2)
        assert state == "done", state
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=60)
    assert "csvboard rig (file=" in err and "Traceback" not in err, err
    _check_session(tmp_path / "data" / "s.h5", mode="csvboard")


# wall: a sensor plugin's CSV board paced by the wall clock (a live sample source)
@pytest.mark.realtime
def test_a_sensor_plugin_on_the_simulated_drum_in_real_time(installed_plugins, tmp_path):
    """The default drum of a sensor-only plugin: the simulated rig on ptys, in real time (one 0.5 s trial)."""
    from rigctl.core import PlannedTrial
    from rigctl.rigs import open_rig

    board = tmp_path / "board.csv"
    board.write_text("\n".join(",".join(str((i * 7) % 900 + 10 * c) for c in range(4)) for i in range(400)) + "\n")
    with open_rig("csvboard", file=str(board), host_config_path=tmp_path / "rig.json") as rig:
        assert rig.mode == "csvboard" and rig.describe()["taxel_port"]  # the simulated Uno's pty
        rig.mount_texture("A")
        data = rig.record_trial(PlannedTrial(0, "A", 100.0, 300.0, 0.5))
    taxels = np.asarray(data.taxels, dtype=np.int64)
    assert taxels.shape == (100, 4) and (np.diff(taxels, axis=1) == 10).all()


def test_a_request_reads_its_options_and_refuses_bad_ones():
    from rigctl.core.rig_plugins import RigOptionError, RigRequest

    req = RigRequest("board", {"rate_hz": "250.5", "channels": "0x10", "on": "yes", "off": "0", "bad": "x"})
    assert (req.number("rate_hz"), req.integer("channels"), req.flag("on"), req.flag("off")) == (250.5, 16, True, False)
    assert req.text("port", "/dev/ttyUSB0") == "/dev/ttyUSB0" and req.flag("absent") is False
    for call, words in ((lambda: req.text("port"), "needs option port"), (lambda: req.number("bad"), "not a number"),
                        (lambda: req.integer("rate_hz"), "not an integer"), (lambda: req.flag("bad"), "true or false"),
                        (lambda: req.check_known(("rate_hz", "channels")), "no option bad, off, on")):
        with pytest.raises(RigOptionError, match=words):
            call()


def test_rigctls_own_rigs_without_the_group_in_the_metadata(monkeypatch):
    """An editable install made before the group existed (its metadata lacks it) still opens rigctl's own rigs."""
    import importlib.metadata

    from rigctl.core import rig_plugins

    monkeypatch.setattr(importlib.metadata, "entry_points", lambda **kw: [])
    rig_plugins.rig_entries.cache_clear()
    try:
        assert rig_plugins.rig_names() == tuple(BUILTIN_RIGS)
        assert callable(rig_plugins.load_rig_factory("inprocess"))
        with pytest.raises(rig_plugins.RigPluginError, match="unknown rig kind 'csvboard'; installed: sim, replay"):
            rig_plugins.load_rig_factory("csvboard")
    finally:
        rig_plugins.rig_entries.cache_clear()


def test_a_board_repeating_every_fifth_reading_is_counted_not_complete(installed_plugins, tmp_path, monkeypatch):
    """Issue 77 item 4: a plugin board that repeats every 5th reading (2,396 of 12,000 rows held) read "6/6 complete,
    0 dropped" from acquire and info. The repeated samples (identical on every taxel to the one before) are counted
    per trial at acquisition, whatever the source, named in the run's summary and by rigctl info."""
    monkeypatch.setenv("RIGCTL_CONFIG", str(tmp_path / "rig.json"))
    lines = [",".join(str((i * 7) % 900 + 10 * c) for c in range(4)) for i in range(900)]
    held = [lines[i - 1] if i % 5 == 4 else line for i, line in enumerate(lines)]  # every 5th: the one before again
    board = tmp_path / "board.csv"
    board.write_text("\n".join(held) + "\n")
    proto = tmp_path / "p.toml"
    proto.write_text(LOSSY_PROTOCOL)
    r = CliRunner().invoke(main, ["acquire", str(proto), "--rig", "csvboard", "--rig-option", f"file={board}",
                                  "--rig-option", "drum=inprocess", "--out", str(tmp_path / "s.h5"), "--quiet"])
    assert r.exit_code == 0 and "trials complete: 2/2" in r.output, r.output
    with open_session(tmp_path / "s.h5") as s:
        truth = sum(int(np.all(np.diff(np.asarray(s.trial(t).taxels, np.int64), axis=0) == 0, axis=1).sum())
                    for t in s.completed_ids())
        samples = sum(s.trial(t).n_samples for t in s.completed_ids())
    assert 0.15 * samples < truth < 0.25 * samples, (truth, samples)
    assert f"repeated samples: {truth} (in 2 trials)" in r.output, r.output
    info = CliRunner().invoke(main, ["info", str(tmp_path / "s.h5")])
    assert f"{truth} repeated samples (identical on every taxel to the one before) in 2 trials" in info.output, \
        info.output
