"""Property-based test (hypothesis) of every ``rigctl`` command: random values of its options (numbers negative,
zero, huge, non-finite, not numbers at all; choices, names and paths) on small real inputs. Whatever the values: no
traceback, exit status 0, 1 or 2 only, nothing left in the output folder when the command failed, no input changed.
:func:`test_every_command_is_driven` walks ``rigctl --help`` recursively and fails for a command no test here drives.

The commands run in this process (click's CliRunner: imports paid once) on an 8-trial session, its encoded file, a
CSV recording and a two-file FabricSlide folder. Where a command needs a rig (``acquire``, ``doctor``) the simulated
rig is the in-process one (the same controller logic and model on a simulated clock; the pty rig is the wire's
tests' business); ``gui`` runs without a display (its one-line refusal; the window has its own tests); ``firmware``
only prints (``--sources``, ``--flash PORT --dry-run``: building needs the AVR toolchain, flashing a board);
``sim``, which runs until Ctrl-C, runs in a child process that gets its Ctrl-C once the ports are up.
Deterministic (``derandomize``) and modest (``RIGCTL_PROPERTY_EXAMPLES``, default 5 per command) so that it runs in
seconds on an idle machine.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings, strategies as st

from rigctl.cli import main
from rigctl.storage.session import SessionWriter, TrialData

RIGCTL: list[str] = []  # the command: this worker's preloaded rigctl (tests/conftest.py _preloaded_rigctl)
N_EXAMPLES = int(os.environ.get("RIGCTL_PROPERTY_EXAMPLES", "5"))
PROPERTY = settings(max_examples=N_EXAMPLES, deadline=None, database=None, derandomize=True,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

#: any numeric text a user might type
NUMBER = st.one_of(st.integers(-10**13, 10**13).map(str), st.sampled_from(["0", "-1", "1", "2", "1e12", "-1e-9", "nan",
                                                                            "inf", "-inf", "1.5", "abc", ""]),
                   st.floats(allow_nan=True, allow_infinity=True).map(repr))
SMALL = st.one_of(st.integers(-3, 4).map(str), NUMBER)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    d = tmp_path_factory.mktemp("property_inputs")
    rng = np.random.default_rng(2)
    plan = [dict(trial_id=i, texture="AB"[i % 2], speed_mm_s=[40.0, 80.0][i // 2 % 2], force_g=500.0,
                 duration_s=0.1) for i in range(8)]
    session = d / "s.h5"
    with SessionWriter.create(session, plan=plan, protocol_source="name = 'p'") as w:
        for i in range(8):
            w.write_trial(i, TrialData(taxels=rng.integers(100, 900, (100, 18)), seq=np.arange(100),
                                       force_g=[500.0], force_time_s=[0.0], speed_mm_s=[40.0], speed_time_s=[0.0]))
    encoded = d / "s.enc.h5"
    r = CliRunner().invoke(main, ["encode", str(session), "--out", str(encoded), "--quiet"])
    assert r.exit_code == 0, r.output
    csv = d / "A__1.csv"
    np.savetxt(csv, rng.integers(0, 1024, (300, 9)), delimiter=",", fmt="%d")
    fabricslide = d / "fabricslide"  # the FabricSlide layout (rigctl.storage.fabricslide), two short recordings
    (fabricslide / "fabric").mkdir(parents=True)
    header = "timestamp, proximity1, proximity2, " + ", ".join(f"channel{k}" for k in range(1, 17))
    for name in ("Linen_F120_V50mmps_0.csv", "Canvas_F120_V-50mmps_0.csv"):
        rows = np.column_stack([4_000_000 + 28 * np.arange(200), np.zeros((200, 2), int),
                                rng.integers(2, 850, (200, 16))])
        np.savetxt(fabricslide / "fabric" / name, rows, delimiter=",", fmt="%d", header=header, comments="")
    protocol = d / "tiny.toml"
    protocol.write_text('name = "tiny"\ndescription = "One short trial."\ntextures = ["A"]\nspeeds_mm_s = [120]\n'
                        'forces_g = [250]\ntrials_per_condition = 1\ntravel_mm = 12\norder = "blocked"\n')
    return {"session": session, "encoded": encoded, "csv": csv, "fabricslide": fabricslide, "protocol": protocol}


def _digests(paths):
    files = [f for p in paths for f in (sorted(Path(p).rglob("*")) if Path(p).is_dir() else [Path(p)]) if f.is_file()]
    return {f: hashlib.sha256(f.read_bytes()).hexdigest() for f in files}


def _not_json(constant):
    raise AssertionError(f"not JSON: {constant}")


def _check(inputs, out_dir: Path, args: list[str]):
    before_inputs = _digests(inputs.values())
    before = set(os.listdir(out_dir))
    r = CliRunner().invoke(main, args)
    text = r.output
    assert r.exit_code in (0, 1, 2), (args, r.exit_code, text)
    assert "Traceback" not in text and "internal error" not in text, (args, text)
    assert r.exception is None or isinstance(r.exception, SystemExit), (args, repr(r.exception))
    if r.exit_code != 0:
        assert set(os.listdir(out_dir)) == before, (args, sorted(set(os.listdir(out_dir)) - before), text)
    elif "--json" in args and "--list" not in args:  # strict JSON (NaN is null), whatever the values
        json.loads(r.stdout, parse_constant=_not_json)
    assert _digests(inputs.values()) == before_inputs, args
    for name in set(os.listdir(out_dir)) - before:  # a success: clear it for the next example
        p = out_dir / name
        shutil.rmtree(p) if p.is_dir() else p.unlink()
    return r


def _opts(draw_pairs):
    args = []
    for opt, value in draw_pairs:
        if value is not None:
            args += [opt, value]
    return args


def _maybe(strategy):
    return st.one_of(st.none(), strategy)


@given(data=st.data())
@PROPERTY
def test_encode(inputs, tmp_path, data):
    opts = [(o, data.draw(_maybe(s), label=o)) for o, s in (
        ("--workers", SMALL), ("--batch", SMALL), ("--window-ms", NUMBER), ("--windows-unscaled", SMALL),
        ("--windows-scaled", st.one_of(SMALL, st.just("longest"))))]
    if dict(opts).get("--workers") is not None:
        opts.append(("--scheduler", "local"))
    _check(inputs, tmp_path, ["encode", str(inputs["session"]), "--out", str(tmp_path / "e.h5"), "--quiet",
                              "--variant", "original", *_opts(opts)])


@given(data=st.data())
@PROPERTY
def test_sim_dataset(inputs, tmp_path, data):
    opts = [(o, data.draw(_maybe(s), label=o)) for o, s in (
        ("--trials-per-condition", st.one_of(st.sampled_from(["1", "0", "-1", "1000000000", "100000"]), NUMBER)),
        ("--seed", NUMBER), ("--workers", st.sampled_from(["0", "-2", "100000", "x"])))]
    if dict(opts).get("--workers") is None:
        opts.append(("--workers", "0"))
    _check(inputs, tmp_path, ["sim", "dataset", "quick_check", "--out", str(tmp_path / "d.h5"), "--quiet",
                              *_opts(opts)])


@given(data=st.data())
@PROPERTY
def test_analyze(inputs, tmp_path, data):
    opts = [(o, data.draw(_maybe(s), label=o)) for o, s in (
        ("--repeats", SMALL), ("--per-texture", SMALL), ("--seed", NUMBER), ("--table-pcs", SMALL),
        ("--jobs", SMALL), ("--threads", SMALL), ("--channels", SMALL),
        ("--pcs", st.one_of(st.sampled_from(["1-2", "0-3", "3-1", "1-1000000000", "a-b", "-1"]), SMALL)))]
    json_flag = ["--json"] if data.draw(st.booleans(), label="--json") else []
    _check(inputs, tmp_path, ["analyze", str(inputs["encoded"]), "--task", "textures", "--variants", "original",
                              "--csv", str(tmp_path / "c.csv"), *json_flag, *_opts(opts)])


@given(data=st.data())
@PROPERTY
def test_import(inputs, tmp_path, data):
    opts = [(o, data.draw(_maybe(s), label=o)) for o, s in (
        ("--channels", SMALL), ("--resample", NUMBER), ("--volts-ref", NUMBER), ("--bits", SMALL),
        ("--layout", st.sampled_from(["3x3x1", "0x0x0", "3x3", "-1x2", "1e9x1e9x1", "x"])),
        ("--segment", st.sampled_from(["fixed:0.1", "fixed:-1", "fixed:1e12", "threshold:nan", "cycles:0", "bogus"])))]
    rate = data.draw(st.one_of(st.just("1000"), NUMBER), label="--rate")
    json_flag = ["--json"] if data.draw(st.booleans(), label="--json") else []
    _check(inputs, tmp_path, ["import", str(inputs["csv"]), "--out", str(tmp_path / "i.h5"), "--rate", rate,
                              "--texture", "A", "--quiet", *json_flag, *_opts(opts)])


@given(data=st.data())
@PROPERTY
def test_info_export_and_protocols(inputs, tmp_path, data):
    variants = data.draw(_maybe(st.sampled_from(["original", "nope", "original,force_scaled", ",", "speed_scaled"])))
    _check(inputs, tmp_path, ["export", "nwb", str(inputs["session"]), "--encoded", str(inputs["encoded"]),
                              "--out", str(tmp_path / "x.nwb"), "--no-progress",
                              *(["--variants", variants] if variants is not None else [])])
    variant = data.draw(_maybe(st.sampled_from(["original", "nope", "realtime_original", "", "speed_scaled"])),
                        label="export --variant")
    seed = data.draw(_maybe(st.sampled_from(["0", "-1", "nan", "1e30", "x"])), label="export --seed")
    _check(inputs, tmp_path, ["export", "events", str(inputs["encoded"]), "--out", str(tmp_path / "ev"),
                              "--no-progress", *(["--variant", variant] if variant is not None else []),
                              *(["--seed", seed] if seed is not None else [])])
    layouts = data.draw(st.lists(st.sampled_from(["per-trial-csv", "per-trial-npz", "bogus"]), max_size=2),
                        label="export trials --layout")
    encoded = ["--encoded", str(inputs["encoded"])] if data.draw(st.booleans(), label="--encoded") else []
    _check(inputs, tmp_path, ["export", "trials", str(inputs["session"]), *encoded, "--out", str(tmp_path / "tr"),
                              "--no-progress", *[a for lay in layouts for a in ("--layout", lay)]])
    _check(inputs, tmp_path, ["info", str(inputs["session"]), *(["--json"] if data.draw(st.booleans()) else [])])
    _check(inputs, tmp_path, ["protocols"])
    r = _check(inputs, tmp_path, ["rigs", *(["--json"] if data.draw(st.booleans(), label="rigs --json") else [])])
    assert r.exit_code == 0 and "inprocess" in r.output, r.output


@pytest.fixture(scope="module")
def model(inputs):
    """A model file of the 8-trial session (``analyze --save-model``'s pipeline, 2 PCs): ``export nir``'s input."""
    from rigctl.analysis.model import texture_pipeline, trials_of_session
    from rigctl.storage.model_file import save_model

    trials, texture = trials_of_session(inputs["session"])
    path = inputs["session"].with_name("m.skops")
    save_model(texture_pipeline("original", 2).fit(trials, texture), path)
    return path


@given(data=st.data())
@PROPERTY
def test_export_nir_and_safety_table(inputs, model, tmp_path, data):
    pcs = data.draw(_maybe(SMALL), label="export nir --pcs")
    source = data.draw(st.sampled_from([model, inputs["session"], inputs["csv"]]), label="export nir MODEL")
    out = data.draw(st.sampled_from(["m.nir", "m.txt", "sub/m.nir", ""]), label="export nir --out")
    _check({**inputs, "model": model}, tmp_path,
           ["export", "nir", str(source), "--out", str(tmp_path / out) if out else "",
            *(["--pcs", pcs] if pcs is not None else []),
            *(["--overwrite"] if data.draw(st.booleans(), label="--overwrite") else [])])
    r = _check(inputs, tmp_path, ["safety", "table"])
    assert r.exit_code == 0 and r.output.startswith("|"), r.output


@pytest.fixture
def inprocess_rig(monkeypatch, tmp_path_factory):
    """The simulated rig a command opens is the in-process one; the rig config lives in a folder of its own."""
    from rigctl.operations import RigSource

    flags = RigSource.from_flags.__func__

    def from_flags(cls, **kw):
        source = flags(cls, **kw)
        return cls("inprocess") if source.kind == "sim" else source

    monkeypatch.setattr(RigSource, "from_flags", classmethod(from_flags))
    config = tmp_path_factory.mktemp("rig_config") / "rig.json"
    monkeypatch.setenv("RIGCTL_CONFIG", str(config))
    return config


@given(data=st.data())
@PROPERTY
def test_acquire(inputs, tmp_path, inprocess_rig, data):
    opts = [(o, data.draw(_maybe(s), label=o)) for o, s in (
        ("--seed", NUMBER), ("--on-failure", st.sampled_from(["continue", "stop", "later"])),
        ("--plates", st.sampled_from(["prompt", "auto", "skip", "x"])))]
    flags = data.draw(st.lists(st.sampled_from(["--resume", "--overwrite", "--no-lsl"]), unique=True), label="flags")
    _check(inputs, tmp_path, ["acquire", str(inputs["protocol"]), "--out", str(tmp_path / "a.h5"), "--quiet",
                              *flags, *_opts(opts)])


@given(data=st.data())
@PROPERTY
def test_doctor(inputs, tmp_path, inprocess_rig, data):
    checks = data.draw(st.lists(st.sampled_from(["link", "noise-floor", "loadcell-zero", "uno-clock", "e-stop",
                                                 "hx711-rate", "nope"]), min_size=1, max_size=3), label="--check")
    opts = [(o, data.draw(_maybe(s), label=o)) for o, s in (("--rest-s", NUMBER), ("--seed", NUMBER))]
    flags = data.draw(st.lists(st.sampled_from(["--json", "--no-save", "--list"]), unique=True), label="flags")
    _check(inputs, tmp_path, ["doctor", *[a for c in checks for a in ("--check", c)], *flags, *_opts(opts)])


@given(data=st.data())
@PROPERTY
def test_calibrate_loadcell(inputs, tmp_path, inprocess_rig, data):
    opts = [(o, data.draw(_maybe(s), label=o)) for o, s in (
        ("--mass-g", st.one_of(NUMBER, st.just("200"))), ("--seed", NUMBER), ("--ack", st.sampled_from(["", " ", "x"])))]
    flags = data.draw(st.lists(st.sampled_from(["--sim", "--inprocess"]), unique=True), label="flags")
    _check(inputs, tmp_path, ["calibrate", "loadcell", *flags, *_opts(opts)])


@given(data=st.data())
@PROPERTY
def test_gui_without_a_display(inputs, tmp_path, monkeypatch, data):
    for name in ("DISPLAY", "WAYLAND_DISPLAY", "QT_QPA_PLATFORM"):
        monkeypatch.delenv(name, raising=False)
    opts = [(o, data.draw(_maybe(s), label=o)) for o, s in (
        ("--quit-after", NUMBER), ("--tab", st.sampled_from(["control", "analysis", "nope"])),
        ("--texture", st.sampled_from(["A", "P", "Z", ""])), ("--replay", st.just(str(inputs["session"]))),
        ("--screenshot", st.sampled_from([str(tmp_path / "w.png"), str(tmp_path / "w.txt")])))]
    flags = data.draw(st.lists(st.sampled_from(["--sim", "--run", "--overwrite"]), unique=True), label="flags")
    r = _check(inputs, tmp_path, ["gui", *flags, *_opts(opts)])
    assert r.exit_code in (1, 2), r.output  # never a window here: a usage error, or the display's one line


@given(data=st.data())
@PROPERTY
def test_firmware_prints_only(inputs, tmp_path, data):
    if data.draw(st.booleans(), label="--sources"):
        args = ["firmware", "--sources"]
    else:
        port = data.draw(st.sampled_from(["/dev/ttyACM0", str(tmp_path / "nope"), "", "COM3"]), label="--flash")
        board = data.draw(_maybe(st.sampled_from(["mega", "uno", "due"])), label="--board")
        args = ["firmware", "--flash", port, "--dry-run", *(["--board", board] if board else [])]
    _check(inputs, tmp_path, args)


@given(data=st.data())
@PROPERTY
def test_ports_udev_rules_and_fabricslide(inputs, tmp_path, data):
    _check(inputs, tmp_path, ["ports", *data.draw(st.lists(st.sampled_from(["--json", "--all"]), unique=True))])
    serials = [(o, data.draw(_maybe(st.text(min_size=0, max_size=12)), label=o))
               for o in ("--drum-serial", "--taxel-serial")]
    _check(inputs, tmp_path, ["udev-rules", *_opts(serials)])
    opts = [(o, data.draw(_maybe(s), label=o)) for o, s in (
        ("--trim", NUMBER), ("--pattern", st.sampled_from(["*.csv", "Linen*", "*.npy", "["])))]
    flags = data.draw(st.lists(st.sampled_from(["--no-board", "--json", "--overwrite"]), unique=True), label="flags")
    _check(inputs, tmp_path, ["import-fabricslide", str(inputs["fabricslide"]), "--out", str(tmp_path / "f.h5"),
                              "--quiet", *flags, *_opts(opts)])


@given(data=st.data())
@settings(PROPERTY, max_examples=min(N_EXAMPLES, 3))
def test_sim_runs_until_ctrl_c(inputs, tmp_path, data):
    """``rigctl sim`` in a child process: started with random options, stopped with Ctrl-C once its ports are up."""
    port_dir = tmp_path / f"ports-{data.draw(st.integers(0, 10**6), label='dir')}"
    opts = [(o, data.draw(_maybe(s), label=o)) for o, s in (
        ("--seed", NUMBER), ("--texture", st.sampled_from(["A", "P", "Z", "", "BeigeCotton"])),
        ("--replay", st.sampled_from([str(inputs["session"]), str(inputs["fabricslide"]), str(tmp_path / "no")])))]
    before_inputs = _digests(inputs.values())
    p = subprocess.Popen([*RIGCTL, "sim", "--port-dir", str(port_dir), *_opts(opts)], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        out = ""
        while "Ctrl-C stops" not in out and time.monotonic() < deadline:
            line = p.stdout.readline()
            if not line:
                break  # it ended (refused)
            out += line
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
        rest, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode in (0, 1, 2), (p.returncode, err)
    assert "Traceback" not in err and "internal error" not in err, err
    if "Ctrl-C stops" in out:
        assert p.returncode == 0 and "simulated rig stopped" in rest, (out, rest, err)
    assert not port_dir.exists() or not list(port_dir.iterdir()), list(port_dir.iterdir())  # its links removed
    assert _digests(inputs.values()) == before_inputs


@given(data=st.data())
@PROPERTY
def test_serve_refusals(inputs, tmp_path, monkeypatch, data):
    """``rigctl serve`` runs until stopped: driven here with what it must refuse before it opens a rig or binds (a
    non-loopback address without a token; --rig hardware without ports; --rig replay without a recording), with
    random numbers for its numeric options."""
    monkeypatch.delenv("RIGCTL_SERVE_TOKEN", raising=False)
    opts = [(o, data.draw(_maybe(NUMBER), label=o)) for o in ("--port", "--seed")]
    case = data.draw(st.sampled_from([["--host", "0.0.0.0"], ["--host", "192.168.1.7", "--rig", "inprocess"],
                                      ["--host", "example.org"], ["--rig", "hardware"],
                                      ["--rig", "hardware", "--drum-port", "/dev/null"], ["--rig", "replay"],
                                      ["--rig", "moon"], ["--rig", "handheld"],
                                      ["--rig", "inprocess", "--rig-option", "x=1"]]),
                     label="case")
    r = _check(inputs, tmp_path, ["serve", "--queue", str(tmp_path / "q.json"), *case, *_opts(opts)])
    assert r.exit_code == 2, (case, r.output)


@given(data=st.data())
@settings(PROPERTY, max_examples=min(N_EXAMPLES, 3))
def test_sim_operator(inputs, tmp_path, lsl, data):
    """``rigctl sim operator`` publishes in real time for --seconds: driven with what it refuses and a short run (at
    most 2 s of publishing), random seeds."""
    seconds = data.draw(st.sampled_from(["-1", "0", "nan", "inf", "abc", "1e9", "1", "2"]), label="seconds")
    seed = data.draw(_maybe(NUMBER), label="--seed")
    r = _check(inputs, tmp_path, ["sim", "operator", "--lsl", f"prop-{os.getpid()}", "--seconds", seconds,
                                  *_opts([("--seed", seed)])])
    if seconds in ("1", "2") and seed is None:
        assert r.exit_code == 0 and "tracker samples published" in r.output, r.output


@pytest.fixture(scope="module")
def sim_in_folder(tmp_path_factory):
    """A simulated rig's control socket in a port folder (the rig built, its clock not running: faults are armed and
    stay pending), as ``rigctl sim`` serves it; the folder."""
    from rigctl.simulation.rig import SimulatedRig
    from rigctl.simulation.sim_control import ControlServer

    folder = tmp_path_factory.mktemp("sim_inject") / "ports"
    rig = SimulatedRig(port_dir=folder)
    server = ControlServer(rig, folder, now_s=lambda: rig.model.time_s, active=lambda: sorted(rig.faults.active))
    yield folder
    server.close()
    rig.close()


FAULT_TEXT = st.one_of(
    st.builds(lambda name, value, at, dur: f"{name}{value}@{at}{dur}",
              st.sampled_from(["estop", "reset", "stall", "slip", "taxel-ohm", "host-silence", "nope", "", "ESTOP"]),
              st.sampled_from(["", "=20%", "=47000", "=x", "=-1"]), SMALL, st.one_of(st.just(""), SMALL.map("+{}".format))),
    st.text(max_size=12))


@given(data=st.data())
@PROPERTY
def test_sim_inject(inputs, tmp_path, sim_in_folder, data):
    """``rigctl sim inject``: random fault specs, to a running simulated rig's folder or to one where none runs."""
    from rigctl.core.faults import FaultSpecError, parse_fault

    specs = data.draw(st.lists(FAULT_TEXT, min_size=1, max_size=3), label="specs")
    folder = data.draw(st.sampled_from([sim_in_folder, tmp_path / "none"]), label="folder")
    r = _check(inputs, tmp_path, ["sim", "inject", "--port-dir", str(folder), *specs])
    try:
        for spec in specs:
            parse_fault(spec)
        valid = True
    except FaultSpecError:
        valid = False
    if not valid:
        assert r.exit_code == 2, r.output
    elif folder == sim_in_folder:
        assert r.exit_code == 0 and r.output.count("armed ") == len(specs), r.output
    else:
        assert r.exit_code == 1 and "no simulated rig running in" in r.output, r.output


#: the commands the tests above drive (``rigctl`` + these words)
DRIVEN = {("encode",), ("sim", "dataset"), ("analyze",), ("import",), ("export", "nwb"), ("export", "events"),
          ("export", "trials"), ("info",), ("protocols",),
          ("acquire",), ("doctor",), ("gui",), ("firmware",), ("ports",), ("udev-rules",), ("import-fabricslide",),
          ("sim",), ("serve",), ("sim", "operator"), ("rigs",), ("sim", "inject"), ("export", "nir"),
          ("safety", "table"), ("calibrate", "loadcell")}


def test_every_command_is_driven(cli_commands):
    """A new command needs its property test above (and an entry in DRIVEN)."""
    commands = {words for words, _ in cli_commands}
    assert commands == DRIVEN, (f"not driven: {sorted(commands - DRIVEN)}", f"gone: {sorted(DRIVEN - commands)}")
