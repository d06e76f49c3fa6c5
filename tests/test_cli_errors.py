"""The command line never destroys a file and never shows a traceback (issue 10, item 5).

Each test runs the real command (click's CliRunner in this process, or a subprocess where a rig or a second process
is involved) and checks the exit status, that the error is one line naming what is wrong and what to do, and that
no file was touched. Plus hypothesis fuzzing of the rig config schema.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings, strategies as st

from rigctl.cli import main

REPO = Path(__file__).resolve().parents[1]
RIGCTL: list[str] = []  # the command: this worker's preloaded rigctl (tests/conftest.py _preloaded_rigctl)
#: a fresh interpreter, where the command's own pid is judged (a sim's port folder names it; kill -9 must hit it)
OWN_PROCESS = [sys.executable, "-c", "from rigctl.cli import main; main()"]

PROTOCOL = """\
name = "cli_errors"
textures = ["A", "B"]
speeds_mm_s = [120]
forces_g = [500]
trials_per_condition = 4
duration_s = 0.4

[settle]
settle_time_ms = 50
"""


# ---------------------------------------------------------------------------------------------------------- helpers
def _digest(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _error_line(output: str, exit_code: int, actual_code: int, *words: str) -> str:
    """The one ``Error:`` line of a refused command; checks the exit status, no traceback, no numpy repr."""
    assert actual_code == exit_code, output
    assert "Traceback" not in output, output
    assert "np.float64(" not in output and "np.int64(" not in output and "np.str_(" not in output, output
    errors = [line for line in output.splitlines() if line.startswith("Error:")]
    assert len(errors) == 1, output
    for w in words:
        assert w in errors[0], errors[0]
    return errors[0]


def run(*args, env=None) -> tuple[int, str]:
    r = CliRunner().invoke(main, [str(a) for a in args], env=env)
    if r.exception is not None and not isinstance(r.exception, SystemExit):
        raise r.exception
    return r.exit_code, r.output


def refused(code: int, *args, words=(), env=None) -> str:
    rc, out = run(*args, env=env)
    return _error_line(out, code, rc, *words)


@pytest.fixture
def cfg_env(tmp_path, monkeypatch):
    """Never the user's rig config (and no window if `rigctl gui` were to start)."""
    monkeypatch.setenv("RIGCTL_CONFIG", str(tmp_path / "no-rig.json"))
    monkeypatch.setenv("QT_QPA_PLATFORM", "offscreen")
    return tmp_path / "no-rig.json"


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """A small simulated session (8 trials), its encoded file, the protocol and a CSV recording."""
    from rigctl.acquisition.protocol import load_protocol
    from rigctl.encoding.pipeline import encode_session
    from rigctl.simulation.dataset import generate_dataset

    d = tmp_path_factory.mktemp("cli_errors")
    proto = d / "p.toml"
    proto.write_text(PROTOCOL)
    session = d / "session.h5"
    generate_dataset(load_protocol(proto), session, seed=1, workers=0, progress=False)
    encoded = d / "session.encoded.h5"
    encode_session(session, encoded, progress=False)
    hw = d / "hw.toml"  # one trial per plate for the runs on the boards
    hw.write_text(PROTOCOL.replace("trials_per_condition = 4", "trials_per_condition = 1"))
    csv = d / "felt.csv"
    csv.write_text("\n".join(",".join(str(100 + i + j) for j in range(4)) for i in range(50)) + "\n")
    return {"dir": d, "protocol": proto, "hw_protocol": hw, "session": session, "encoded": encoded, "csv": csv}


@pytest.fixture
def unwritable(tmp_path) -> Path:
    """A folder that does not take a new file (a read-only folder; as root, /sys)."""
    d = tmp_path / "ro"
    d.mkdir()
    d.chmod(0o500)
    for cand in (d, Path("/sys")):
        try:
            fd, name = tempfile.mkstemp(dir=cand)
        except OSError:
            yield cand
            break
        os.close(fd)
        os.unlink(name)
    else:
        pytest.skip("no folder here refuses a new file")
    d.chmod(0o700)


# ---------------------------------------------------------------------------------------------------------- item 1
def test_encode_refuses_its_input_as_output(data, tmp_path):
    """`rigctl encode X.h5 --out X.h5 --overwrite` replaced the recording and exited 0; also through another name."""
    x = tmp_path / "x.h5"
    x.write_bytes(data["session"].read_bytes())
    before = _digest(x)
    refused(2, "encode", x, "--out", x, "--overwrite", "--quiet", words=("--out", "one of the input files"))
    alias = tmp_path / "alias.h5"
    alias.symlink_to(x)
    refused(2, "encode", x, "--out", alias, "--overwrite", "--quiet", words=("one of the input files", str(x)))
    assert _digest(x) == before
    rc, out = run("info", x)
    assert rc == 0 and "not a rigctl session file" not in out


def _writing_commands(data, out: Path) -> dict[str, list]:
    """Every command that writes a file, with ``out`` as its output."""
    return {
        "acquire": ["acquire", data["protocol"], "--out", out],
        "sim dataset": ["sim", "dataset", data["protocol"], "--out", out, "--quiet"],
        "import": ["import", data["csv"], "--out", out, "--rate", 100, "--texture", "felt"],
        "import-fabricslide": ["import-fabricslide", data["dir"], "--out", out, "--quiet"],
        "encode": ["encode", data["session"], "--out", out, "--quiet"],
        "analyze --csv": ["analyze", data["encoded"], "--csv", out],
        "analyze --plot": ["analyze", data["encoded"], "--plot", out.with_suffix(".png")],
        "analyze --confusion": ["analyze", data["encoded"], "--confusion", out.with_suffix(".png")],
        "analyze --save-model": ["analyze", data["encoded"], "--save-model", out],
        "gui --screenshot": ["gui", "--screenshot", out.with_suffix(".png"), "--quit-after", 1],
    }


COMMANDS = ["acquire", "sim dataset", "import", "import-fabricslide", "encode", "analyze --csv", "analyze --plot",
            "analyze --confusion", "analyze --save-model", "gui --screenshot"]


@pytest.mark.parametrize("command", COMMANDS)
def test_an_existing_output_is_kept_without_overwrite(command, data, tmp_path, cfg_env):
    args = _writing_commands(data, tmp_path / "precious.h5")[command]
    target = Path(next(a for a in args if isinstance(a, Path) and a.name.startswith("precious")))
    target.write_bytes(b"a user's file")
    refused(2, *args, words=("exists", "--overwrite", str(target)))
    assert target.read_bytes() == b"a user's file"


@pytest.mark.parametrize("command", ["acquire", "sim dataset", "import", "import-fabricslide", "encode",
                                     "analyze --csv", "gui --screenshot"])
def test_an_unwritable_output_folder_is_refused_up_front(command, data, unwritable, cfg_env):
    args = _writing_commands(data, unwritable / "out.h5")[command]
    refused(2, *args, words=("cannot write in", str(unwritable), "choose another folder"))


def test_analyze_checks_its_outputs_before_the_analysis_runs(data, tmp_path, monkeypatch):
    """`--plot x.h5` was refused by matplotlib only after the whole analysis ran."""
    from rigctl.analysis import tasks

    def no_analysis(*a, **k):
        raise AssertionError("the analysis ran before the outputs were checked")

    monkeypatch.setattr(tasks, "run_cv", no_analysis)
    monkeypatch.setattr(tasks, "run_extrapolation", no_analysis)
    enc = data["encoded"]
    refused(2, "analyze", enc, "--plot", tmp_path / "x.h5", words=("--plot", "unsupported format .h5", ".png"))
    refused(2, "analyze", enc, "--csv", enc, "--overwrite", words=("--csv", "one of the input files"))
    refused(2, "analyze", enc, "--plot", tmp_path / "a.png", "--confusion", tmp_path / "a.png",
            words=("both name", "a.png"))
    refused(2, "analyze", enc, "--plot", tmp_path / "no" / "a.png", words=("does not exist",))
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_analyze_overwrite_replaces_an_output(data, tmp_path):
    """--overwrite replaces analyze's own CSV (its header known), never a user's file of the same name."""
    csv = tmp_path / "curves.csv"
    args = ("analyze", data["encoded"], "--task", "textures", "--repeats", 1, "--per-texture", 4, "--pcs", "1-3",
            "--csv", csv, "--overwrite", "--no-progress")
    csv.write_text("old")
    refused(2, *args, words=("--csv", "a file of another program", "rigctl analyze CSV"))
    assert csv.read_text() == "old"
    csv.unlink()
    rc, out = run(*args)
    assert rc == 0, out
    first = csv.read_text()
    csv.write_text(first.replace("textures", "old-textures"))
    rc, out = run(*args)
    assert rc == 0, out
    assert csv.read_text() == first and "textures" in first
    assert [p.name for p in tmp_path.iterdir()] == ["curves.csv"]  # no temporary file left


# ---------------------------------------------------------------------------------------------------------- item 2
def test_encode_scheduler_without_dask(data, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "dask", None)  # `import dask` fails as if it were not installed
    monkeypatch.setitem(sys.modules, "dask.distributed", None)
    refused(2, "encode", data["session"], "--out", tmp_path / "e.h5", "--scheduler", "local",
            words=("--scheduler", "Dask", "pip install"))
    assert not (tmp_path / "e.h5").exists()


def test_analyze_unknown_variant_and_too_many_pcs(data):
    refused(2, "analyze", data["encoded"], "--variants", "bogus", words=("--variants", "bogus", "original"))
    line = refused(2, "analyze", data["encoded"], "--pcs", "1-5000", words=("--pcs 1-5000", "the data allows 1-"))
    assert "allows 1-8 (8 trials" in line


def test_replay_of_an_empty_folder(tmp_path, cfg_env, data):
    empty = tmp_path / "empty"
    empty.mkdir()
    refused(1, "sim", "--replay", empty, words=(str(empty),))
    refused(1, "acquire", data["protocol"], "--out", tmp_path / "o.h5", "--replay", empty, words=(str(empty),))
    assert not (tmp_path / "o.h5").exists()


def test_numpy_values_read_as_plain_numbers(data):
    """A message built from numpy values (here the profiles of the file) names them as text."""
    import numpy as np

    from rigctl.cli.errors import plain_numbers

    line = refused(1, "analyze", data["encoded"], "--task", "realtime", "--train-profiles", "nope",
                   words=("nope", "has constant"))
    assert "np." not in line
    assert plain_numbers(f"{np.float64(1.5)!r} {[np.str_('A'), np.int64(3)]}") == "1.5 ['A', 3]"


def test_unexpected_errors_are_one_line_and_debug_shows_them(data, monkeypatch):
    """rigctl's own error types read as one line; anything else is an internal error with its place, and
    `rigctl --debug` lets it through with its traceback."""
    import rigctl.cli.info as info_cli
    from rigctl.storage.session import SessionError

    def broken(path, **kw):
        raise TypeError("boom")

    monkeypatch.setattr(info_cli, "session_summary", broken)
    line = refused(1, "info", data["session"], words=("internal error", "TypeError: boom", "--debug"))
    assert "test_cli_errors.py:" in line
    r = CliRunner().invoke(main, ["--debug", "info", str(data["session"])])
    assert isinstance(r.exception, TypeError)

    def damaged(path, **kw):
        raise SessionError(f"{path}: trial 3 is damaged\n(its taxels are missing)")

    monkeypatch.setattr(info_cli, "session_summary", damaged)
    line = refused(1, "info", data["session"], words=("trial 3 is damaged (its taxels are missing)",))
    assert "internal error" not in line


# ---------------------------------------------------------------------------------------------------------- item 3
def test_rig_config_is_checked_before_the_rig_opens(data, tmp_path, monkeypatch):
    out = tmp_path / "o.h5"
    proto = data["protocol"]
    monkeypatch.setenv("RIGCTL_CONFIG", str(tmp_path / "default.json"))
    refused(2, "acquire", proto, "--out", out, "--config", tmp_path / "missing.json",
            words=("--config", "missing.json", "does not exist"))
    cfg = tmp_path / "rig.json"
    for doc, words in (('{"loadcell": {"counts_per_g": 420', ("--config", "not valid JSON")),
                       ('{"loadcel": {"counts_per_g": 420}}', ("--config", '"loadcel"', "loadcell")),
                       ('{"loadcell": {"counts_per_g": "420"}}', ("loadcell.counts_per_g", "non-zero number")),
                       ('{"taxel_normalisation": {"taxel_min": [1], "taxel_max": [2], "n_trials": 1.5}}',
                        ("taxel_normalisation.n_trials", "integer"))):
        cfg.write_text(doc)
        refused(2, "acquire", proto, "--out", out, "--config", cfg, words=words)
    (tmp_path / "default.json").write_text("[]")  # the default file ($RIGCTL_CONFIG), not given on the line
    refused(1, "acquire", proto, "--out", out, words=("default.json", "JSON object", "--config"))
    assert not out.exists()


JSON = st.recursive(st.none() | st.booleans() | st.integers(-10**6, 10**6) | st.floats(allow_nan=True)
                    | st.text(max_size=8),
                    lambda kids: st.lists(kids, max_size=4) | st.dictionaries(st.text(max_size=12), kids, max_size=4),
                    max_leaves=12)


def _rigconfig_schema() -> dict:
    from rigctl.acquisition.rigconfig import SCHEMA

    return SCHEMA


#: the rig config's blocks and their keys, from its one schema (a block added there, e.g. lsl, is fuzzed as a block:
#: its errors name "rig.json: lsl", not '"lsl"')
BLOCKS = {block: list(keys) for block, keys in _rigconfig_schema().items()}


def _near_valid():
    """Documents built from the schema's own keys with random values (most fail on one key, some are valid)."""

    def block(name):
        keys = st.sampled_from(BLOCKS[name] + ["bogus_key"])
        numbers = st.lists(st.floats(0, 1023), min_size=1, max_size=3)
        value = st.one_of(JSON, st.floats(0.1, 1e4), st.integers(0, 70000), numbers)
        return st.dictionaries(keys, value, max_size=6)

    return st.fixed_dictionaries({}, optional={"loadcell": block("loadcell"),
                                               "taxel_normalisation": block("taxel_normalisation")})


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(doc=st.one_of(JSON, _near_valid()))
def test_rig_config_fuzz_loads_or_names_the_key(doc, tmp_path):
    """Any JSON document either loads (and saves back unchanged) or raises RigConfigError naming the file and
    the key at fault; nothing else escapes."""
    from rigctl.acquisition.rigconfig import RigConfigError, load_rig_config, save_rig_config

    path = tmp_path / "rig.json"
    path.write_text(json.dumps(doc))
    try:
        loaded = load_rig_config(path)
    except RigConfigError as exc:
        msg = str(exc)
        assert msg.startswith(str(path)), msg
        if not isinstance(doc, dict):
            assert "JSON object" in msg, msg
            return

        def shown(key):
            return json.dumps(key)[:30]

        def names(key):
            if key not in BLOCKS:
                return shown(key) in msg
            if f"{path}: {key}" not in msg:
                return False
            if "unknown key" in msg or ("expected" in msg and "expected an object" not in msg):
                return any(f"{key}.{k}" in msg or shown(k) in msg for k in doc[key])
            return True

        assert any(names(k) for k in doc), msg
        return
    assert loaded == doc
    save_rig_config(loaded, path)
    assert load_rig_config(path) == doc


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(raw=st.binary(max_size=60) | st.text(max_size=60).map(str.encode))
def test_rig_config_fuzz_bytes(raw, tmp_path):
    """Arbitrary bytes in the file: a dict or RigConfigError, never another exception."""
    from rigctl.acquisition.rigconfig import RigConfigError, load_rig_config

    path = tmp_path / "rig.json"
    path.write_bytes(raw)
    try:
        assert isinstance(load_rig_config(path), dict)
    except RigConfigError as exc:
        assert str(exc).startswith(str(path))


# -------------------------------------------------------------------------------------------- item 3: port folders
def _start_sim(port_dir=None, env=None, command=OWN_PROCESS):
    args = [*command, "sim"] + (["--port-dir", str(port_dir)] if port_dir else [])
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    from rigctl.cli.sim import PORT_LINE

    ports = {}
    while len(ports) < 2:
        line = proc.stdout.readline()
        assert line, proc.stderr.read()
        m = PORT_LINE.match(line)
        if m:
            ports[m.group(1)] = m.group(2)
    return proc, ports


# wall: a `rigctl sim` of its own process (always paced to the wall clock: the rig other programs drive as hardware),
#   and SIGINT
@pytest.mark.realtime
def test_a_second_sim_does_not_take_over_a_running_ones_port_folder(tmp_path):
    d = tmp_path / "ports"
    first, ports = _start_sim(d)
    try:
        links = {name: os.readlink(d / name) for name in ("drum", "taxel")}
        # timeouts only bound a hang: a starved machine takes tens of seconds to start (imports) or stop a sim
        second = subprocess.run([*RIGCTL, "sim", "--port-dir", str(d)], capture_output=True, text=True, timeout=300)
        _error_line(second.stderr, 1, second.returncode, str(d), f"pid {first.pid}", "--port-dir")
        assert {name: os.readlink(d / name) for name in ("drum", "taxel")} == links  # untouched
        assert first.poll() is None
    finally:
        first.send_signal(signal.SIGINT)
        first.wait(timeout=300)
    assert not (d / "drum").exists() and not (d / "taxel").exists()
    third, _ = _start_sim(d, command=RIGCTL)  # the folder is free again once its owner is gone
    third.kill()
    third.wait(timeout=300)


# wall: a `rigctl sim` of its own process (always paced to the wall clock: the rig other programs drive as hardware),
#   killed
@pytest.mark.realtime
def test_a_killed_sims_temporary_folder_is_removed_by_the_next_one(tmp_path, monkeypatch):
    from rigctl.simulation.pty import PortDir

    killed, ports = _start_sim(env={**os.environ, "TMPDIR": str(tmp_path)})
    folder = Path(ports["drum"]).parent
    assert folder.parent == tmp_path and folder.name.startswith(f"rigctl-sim-{killed.pid}-")
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    live = PortDir()  # a live simulated rig's folder (this process)
    killed.kill()
    killed.wait(timeout=30)
    assert folder.is_dir() and live.path.is_dir()  # kill -9: nothing cleaned up
    nxt = PortDir()  # the next simulated rig to start
    try:
        assert not folder.exists()
        assert live.path.is_dir()  # the live one's is kept
    finally:
        nxt.release()
        live.release()
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------------------- item 2 and 4: hardware runs
def _hardware(args, *, drum_port=None, timeout=180):
    """`rigctl acquire ... --drum-port --taxel-port` on the simulated rig's ports as if they were the real boards
    (stdin not a terminal); ``drum_port`` replaces the drum's."""
    from rigctl.devices.wire import HoldingRegister
    from rigctl.rigs import WATCHDOG_MS
    from rigctl.simulation.rig import SimulatedRig

    with SimulatedRig(seed=1) as sim:
        # the simulated rig's own watchdog (5 s), not the hardware's 1 s: these tests judge the command line, and a
        # host process starved for 1 s on a saturated test machine latched WATCHDOG in every CI run
        sim.mega.set_holding_register(HoldingRegister.WATCHDOG_MS, WATCHDOG_MS["sim"])
        return subprocess.run([*RIGCTL, "acquire", *map(str, args), "--quiet", "--drum-port", drum_port or sim.drum_port,
                               "--taxel-port", sim.taxel_port], capture_output=True, text=True, timeout=timeout,
                              stdin=subprocess.DEVNULL)


# wall: a pty nobody serves: the answer timeouts are the wall clock's
@pytest.mark.realtime
def test_a_wrong_drum_port_is_one_line(data, tmp_path, monkeypatch):
    """A port that exists but answers nothing (a pty nobody serves): DrumTimeout traceback after three 'STOP attempt
    failed' lines before."""
    monkeypatch.setenv("RIGCTL_CONFIG", str(tmp_path / "rig.json"))
    master, slave = os.openpty()
    silent = os.ttyname(slave)
    try:
        run_ = _hardware([data["hw_protocol"], "--out", tmp_path / "o.h5", "--plates", "skip"], drum_port=silent)
    finally:
        os.close(master)
        os.close(slave)
    _error_line(run_.stderr, 1, run_.returncode, "no answer from the drum controller", silent,
                "--drum-port", "rigctl ports")
    assert "STOP attempt" not in run_.stderr and "retries, continue" not in run_.stderr
    assert not (tmp_path / "o.h5").exists()


def test_plate_policy_unattended_hardware_run(data, tmp_path, monkeypatch):
    """Without a terminal the plate prompt made every trial fail with EOFError: now refused up front, and
    --plates auto runs the protocol, announcing each plate."""
    monkeypatch.setenv("RIGCTL_CONFIG", str(tmp_path / "rig.json"))
    out = tmp_path / "hw.h5"
    ptys = [os.openpty() for _ in range(2)]  # refused up front: two ports nobody serves are never opened
    try:
        no_tty = subprocess.run([*RIGCTL, "acquire", str(data["hw_protocol"]), "--out", str(out), "--quiet",
                                 "--drum-port", os.ttyname(ptys[0][1]), "--taxel-port", os.ttyname(ptys[1][1])],
                                capture_output=True, text=True, timeout=180, stdin=subprocess.DEVNULL)
    finally:
        for fd in (fd for pair in ptys for fd in pair):
            os.close(fd)
    _error_line(no_tty.stderr, 2, no_tty.returncode, "stdin is not a terminal", "--plates auto", "--plates skip")
    assert not out.exists()
    auto = _hardware([data["hw_protocol"], "--out", out, "--plates", "auto"])
    assert auto.returncode == 0, auto.stderr
    assert "trials complete: 2/2" in auto.stdout
    changes = [line for line in auto.stderr.splitlines() if "plate change (--plates auto, not waiting)" in line]
    assert [c.split("plate ")[-1].split()[0] for c in changes] == ["A", "B"], auto.stderr


def test_plate_prompt_callables():
    from rigctl.cli.acquire import plate_prompt
    from rigctl.cli.outputs import UsageProblem
    from rigctl.core.textures import PAPER_TEXTURES
    from rigctl.devices.backend import OperatorMounter

    with pytest.raises(UsageProblem, match="stdin is not a terminal"):
        plate_prompt("prompt", hardware=True, stdin_is_tty=False)
    assert plate_prompt("prompt", hardware=True, stdin_is_tty=True) is None  # the terminal prompt
    assert plate_prompt("prompt", hardware=False, stdin_is_tty=False) is None  # simulated: mounts itself
    said = []
    auto = plate_prompt("auto", hardware=True, stdin_is_tty=False, echo=said.append)
    OperatorMounter(auto).mount("g", PAPER_TEXTURES)  # what the hardware backend does at a plate change
    assert len(said) == 1 and "Mount texture plate G on the drum" in said[0] and "confirm" not in said[0]
    skip = plate_prompt("skip", hardware=True, stdin_is_tty=False)
    OperatorMounter(skip).mount("A", PAPER_TEXTURES)  # returns without input() (pytest's stdin would raise)


@pytest.mark.parametrize("args, suggestion", [
    (["aquire"], "'acquire'"), (["exprot"], "'export'"), (["export", "nbw"], "'nwb'"), (["sim", "datset"], "'dataset'"),
    (["xyzzy"], None),
])
def test_a_mistyped_command_names_the_nearest_one(args, suggestion):
    """A mistyped command is one usage line (exit 2) that names the nearest command, at every level (issue 79 item 7:
    ``rigctl aquire`` said only "No such command"); a name like no command's gets no guess."""
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 2 and "Traceback" not in r.output, r.output
    lines = [line for line in r.output.splitlines() if line.strip()]
    assert len(lines) == 1 and f"No such command {args[-1]!r}" in lines[0], r.output
    if suggestion:
        assert lines[0].split("did you mean ")[1].startswith(suggestion), r.output
    else:
        assert "did you mean" not in lines[0], r.output


def test_a_group_without_its_command_shows_its_help():
    """``rigctl export`` alone prints the group's help as click lays it out (it was squeezed into one error line)."""
    r = CliRunner().invoke(main, ["export"], prog_name="rigctl")
    assert r.exit_code == 2, r.output
    assert r.output.startswith("Usage: rigctl export") and "Commands:" in r.output and "Error" not in r.output
    assert {"events", "nwb", "trials"} <= {line.split()[0] for line in r.output.split("Commands:")[1].splitlines()
                                           if line.strip()}


def test_the_shell_completes_protocol_names_and_files():
    """Issue 79 item 7: ``rigctl acquire <TAB>`` completed nothing; it now offers the built-in protocols' names (with
    their summaries, for zsh and fish) and the shell's own file completion, for acquire and sim dataset alike."""
    from click.shell_completion import ShellComplete

    for words in (["acquire"], ["sim", "dataset"]):
        items = ShellComplete(main, {}, "rigctl", "_RIGCTL_COMPLETE").get_completions(words, "qu")
        assert [(i.type, i.value) for i in items] == [("plain", "quick_check"), ("file", "qu")], items
        assert items[0].help  # its summary line, which zsh and fish show beside the name
    everything = ShellComplete(main, {}, "rigctl", "_RIGCTL_COMPLETE").get_completions(["acquire"], "")
    assert {"quick_check", "paper_dataset", "realtime_profiles"} <= {i.value for i in everything if i.type == "plain"}
