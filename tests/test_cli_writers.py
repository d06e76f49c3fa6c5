"""Every option of the command line that writes a file is under the one replace rule (issue 52 item 1).

The writers are found from click's own parameter lists (the whole command tree, :func:`cli_commands`): a
``click.Path`` option declared ``writable=True`` writes a file (or, for a folder, files in it); every other path
parameter must read an existing path (``exists=True``) or be named in :data:`NOT_WRITERS` with the reason. Each writer
then gets four runs, with ``--overwrite`` where the command has it, pointed at

- a rigctl session file (another one than the run's input; a writer of sessions, :data:`SESSION_WRITERS`, replaces
  one with ``--overwrite`` by design, so it runs without it there and must say the file exists),
- another program's file (a user's notes),
- a device (a character device made here with /dev/null's numbers, so even a wrong replace harms nothing),
- the run's own input,

and each must be refused with one line (exit 2, no traceback), the file left byte for byte (the device a device),
and nothing left beside it. A new writer without a row in :data:`RUNS` fails :func:`test_every_writer_is_listed`.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import stat
import subprocess
from pathlib import Path

import click
import numpy as np
import pytest

from rigctl.storage.session import SessionWriter, TrialData

RIGCTL: list[str] = []  # the command: this worker's preloaded rigctl (tests/conftest.py _preloaded_rigctl)

#: path parameters that neither read an existing path (exists=True) nor write: why
NOT_WRITERS = {
    ("import", "files"): "inputs, checked by the command itself (a missing one named with what was found)",
    ("import-fabricslide", "directory"): "the FabricSlide folder read (optional: $RIGCTL_FABRICSLIDE)",
    ("sim inject", "port_dir"): "the folder of a running simulated rig, whose control socket it connects to (none "
                                "there: one line, exit 1; tests/simulation/test_sim_process.py)",
    ("serve", "data_dir"): "the folder of the sessions clients name: every name checked per request "
                           "(rigctl.storage.outputs.name_in_folder, check_output; tests/operations)",
}

#: (command words, parameter name) -> (suffix of the target, argv builder (paths: dict) -> list, the input the
#: output must not replace or None, with the reason). ``T`` in ``paths`` is the target.
RUNS = {
    (("acquire",), "out"): (".h5", lambda p: ["acquire", "quick_check", "--inprocess", "--out", p["T"],
                                              "--overwrite"], "config"),
    (("acquire",), "truth_log"): (".csv", lambda p: ["acquire", "quick_check", "--sim", "--out", p["new"],
                                                     "--config", p["config"], "--truth-log", p["T"]], "config"),
    (("analyze",), "plot"): (".png", lambda p: ["analyze", p["session"], "--plot", p["T"], "--overwrite"],
                             "session"),
    (("analyze",), "confusion"): (".png", lambda p: ["analyze", p["session"], "--confusion", p["T"],
                                                     "--overwrite"], "session"),
    (("analyze",), "csv_path"): (".csv", lambda p: ["analyze", p["session"], "--csv", p["T"], "--overwrite"],
                                 "session"),
    (("analyze",), "save_model"): (".skops", lambda p: ["analyze", p["session"], "--save-model", p["T"],
                                                        "--overwrite"], "session"),
    # the rig config is read and updated in place by design (its own input): the other three cases apply
    (("doctor",), "config_path"): (".json", lambda p: ["doctor", "--sim", "--save", "--config", p["T"]], None),
    (("calibrate", "loadcell"), "config_path"): (".json", lambda p: ["calibrate", "loadcell", "--mass-g", "200",
                                                                      "--inprocess", "--config", p["T"]], None),
    (("doctor",), "truth_log"): (".csv", lambda p: ["doctor", "--sim", "--config", p["config"], "--truth-log",
                                                    p["T"]], "config"),
    (("encode",), "out"): (".h5", lambda p: ["encode", p["session"], "--out", p["T"], "--overwrite"], "session"),
    # folder outputs (rigctl.storage.export_folder): a file at --out is never replaced by a folder
    (("export", "events"), "out"): ("", lambda p: ["export", "events", p["session"], "--out", p["T"], "--overwrite"],
                                    "session"),
    (("export", "trials"), "out"): ("", lambda p: ["export", "trials", p["session"], "--layout", "per-trial-csv",
                                                   "--out", p["T"], "--overwrite"], "session"),
    # the model is read only after the output is checked: a stand-in file is enough for the four refusals
    (("export", "nir"), "out"): (".nir", lambda p: ["export", "nir", p["model"], "--out", p["T"], "--overwrite"],
                                 "model"),
    (("export", "nwb"), "out"): (".nwb", lambda p: ["export", "nwb", p["session"], "--out", p["T"], "--overwrite"],
                                 "session"),
    (("gui",), "screenshot"): (".png", lambda p: ["gui", "--replay", p["session"], "--screenshot", p["T"],
                                                  "--quit-after", "1", "--overwrite"], "session"),
    (("import",), "out"): (".h5", lambda p: ["import", p["csv"], "--out", p["T"], "--rate", "1000", "--overwrite"],
                           "csv"),
    (("import-fabricslide",), "out"): (".h5", lambda p: ["import-fabricslide", p["folder"], "--out", p["T"],
                                                         "--overwrite"], "in_folder"),
    (("serve",), "queue_file"): (".json", lambda p: ["serve", "--port", "0", "--queue", p["T"]], "config"),
    (("sim",), "port_dir"): ("", lambda p: ["sim", "--port-dir", p["T_dir"]], None),
    (("sim",), "truth_log"): (".csv", lambda p: ["sim", "--truth-log", p["T"]], "config"),
    (("sim", "dataset"), "out"): (".h5", lambda p: ["sim", "dataset", p["protocol"], "--out", p["T"],
                                                    "--overwrite"], "protocol"),
}


#: the writers of sessions: ``--overwrite`` replaces a session (the rule: a rigctl output of the same kind)
SESSION_WRITERS = {(("acquire",), "out"), (("import",), "out"), (("import-fabricslide",), "out"),
                   (("sim", "dataset"), "out")}


def _session(path: Path) -> Path:
    rng = np.random.default_rng(0)
    plan = [dict(trial_id=i, texture="AB"[i % 2], speed_mm_s=40.0, force_g=500.0, duration_s=0.1) for i in range(2)]
    with SessionWriter.create(path, plan=plan, protocol_source="name = 't'") as w:
        for i in range(2):
            w.write_trial(i, TrialData(taxels=rng.integers(100, 900, (100, 18)), seq=np.arange(100),
                                       force_g=[500.0], force_time_s=[0.0], speed_mm_s=[40.0], speed_time_s=[0.0]))
    return path


def _writers(cli_commands) -> dict[tuple[tuple[str, ...], str], click.Parameter]:
    found = {}
    for words, cmd in cli_commands:
        for p in cmd.params:
            if isinstance(p.type, click.Path) and p.type.writable:
                found[(words, p.name)] = p
    return found


def test_every_writer_is_listed(cli_commands):
    """Every path parameter of every command reads (exists=True), writes (writable=True: a row of RUNS) or is
    named in NOT_WRITERS with why; RUNS names only real writers."""
    writers = _writers(cli_commands)
    assert set(writers) == set(RUNS), (sorted(set(writers) - set(RUNS)), sorted(set(RUNS) - set(writers)))
    for words, cmd in cli_commands:
        for p in cmd.params:
            if isinstance(p.type, click.Path) and not p.type.exists and not p.type.writable:
                assert (" ".join(words), p.name) in NOT_WRITERS, (words, p.name, "reads or writes? say which")
    assert len(writers) >= 15


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _state(path: Path):
    mode = os.lstat(path).st_mode
    if stat.S_ISCHR(mode) or stat.S_ISFIFO(mode):
        return ("device", stat.S_IFMT(mode))
    if stat.S_ISDIR(mode):
        return ("folder", sorted((e.name, _state(e)) for e in path.iterdir()))
    return ("file", _digest(path))


def _device(path: Path) -> Path:
    """A character device (1, 3: /dev/null's numbers) at ``path``, or a FIFO where mknod is not allowed."""
    try:
        os.mknod(path, stat.S_IFCHR | 0o666, os.makedev(1, 3))
    except OSError:
        os.mkfifo(path)
    return path


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    d = tmp_path_factory.mktemp("inputs")
    paths = {"session": _session(d / "input.h5"), "config": d / "rig.json", "csv": d / "rec.csv",
             "protocol": d / "p.toml", "folder": d / "fabricslide"}
    paths["config"].write_text("{}\n")
    paths["model"] = d / "model.skops"
    paths["model"].write_bytes(b"a stand-in for a model file: export nir refuses its output before reading it\n")
    paths["csv"].write_text("\n".join(",".join(["500"] * 18) for _ in range(200)) + "\n")
    paths["protocol"].write_text('name = "p"\ntextures = ["A"]\nspeeds_mm_s = [40]\nforces_g = [500]\n'
                                 'trials_per_condition = 1\nduration_s = 0.2\n')
    (paths["folder"] / "fabric").mkdir(parents=True)
    paths["in_folder"] = paths["folder"] / "fabric" / "notes.h5"
    paths["in_folder"].write_text("a file of the dataset's\n")
    paths["other_session"] = _session(d / "other.h5")
    return paths


CASES = ("a session", "a foreign file", "a device", "its own input")


def _target(case: str, suffix: str, where: Path, inputs: dict, own: str | None) -> Path | None:
    if case == "its own input":
        return None if own is None else inputs[own]
    t = where / f"target{suffix}"
    if case == "a session":
        shutil.copyfile(inputs["other_session"], t)
    elif case == "a foreign file":
        t.write_text("someone's notes: keep\n")
    else:
        _device(t)
    return t


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("writer", sorted(RUNS), ids=lambda w: "-".join(w[0]) + ":" + w[1])
def test_each_writer_refuses_to_replace(writer, case, inputs, tmp_path):
    suffix, argv, own = RUNS[writer]
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    if writer[1] == "port_dir":  # a folder option: the files it would replace are the port links' names
        if case == "its own input":
            pytest.skip("--port-dir reads nothing: the links are new names in the folder")
        for name in ("drum", "taxel"):
            _target(case, suffix, out_dir, inputs, own).rename(out_dir / name)
        target = out_dir
    else:
        target = _target(case, suffix, out_dir, inputs, own)
        if target is None:
            pytest.skip("the rig config is read and updated in place by design")
    before = {p: _state(p) for p in (target, *[v for v in inputs.values() if isinstance(v, Path)])}
    listing = sorted(os.listdir(out_dir)) + sorted(os.listdir(inputs["session"].parent))
    env = dict(os.environ, RIGCTL_CONFIG=str(tmp_path / "no-rig.json"), QT_QPA_PLATFORM="offscreen")
    paths = dict(inputs, T=target, T_dir=target, new=tmp_path / "new.h5")
    args = [str(a) for a in argv(paths)]
    if case == "a session" and writer in SESSION_WRITERS:
        args.remove("--overwrite")
    try:
        r = subprocess.run([*RIGCTL, *args], capture_output=True, text=True, timeout=120, env=env, cwd=tmp_path)
    except subprocess.TimeoutExpired:
        pytest.fail(f"{writer}: not refused within 120 s (it ran)")
    out = r.stdout + r.stderr
    assert r.returncode == 2, (writer, case, out)
    assert "Traceback" not in out, out
    errors = [line for line in out.splitlines() if line.startswith("Error:")]
    assert len(errors) == 1, out
    assert {p: _state(p) for p in before} == before, (writer, case, "changed", out)
    assert sorted(os.listdir(out_dir)) + sorted(os.listdir(inputs["session"].parent)) == listing, out
    assert not (tmp_path / "new.h5").exists()


#: the sidecars a writer makes beside its output (rigctl.storage.sidecars): a link at each must leave what it points
#: to as it was, the link itself kept (issue 77 item 3: 13 of 13 writers followed one)
SIDECARS = (".part", ".lock", ".creating", ".journal")
#: the writers run to the end with a link at each sidecar (their RUNS argv, --overwrite left out; import with a
#: texture so that it writes). The others write through the same code, tested with the library: analyze's four
#: outputs, gui --screenshot and model files (outputs.replacing), export events/trials (a folder made by mkdtemp,
#: no fixed name), import-fabricslide (importers.write_session, as import), serve's queue and token files
#: (sidecars.write_small_file): tests/storage/test_storage_sidecars.py; serve's runs: tests/operations/
#: test_serve_races.py
SIDECAR_RUNS = {(("acquire",), "out"): (), (("calibrate", "loadcell"), "config_path"): (),
                (("doctor",), "config_path"): (), (("encode",), "out"): (),
                (("export", "nwb"), "out"): (), (("import",), "out"): ("--texture", "A"),
                (("sim", "dataset"), "out"): ()}


@pytest.mark.parametrize("sidecar", SIDECARS)
@pytest.mark.parametrize("writer", sorted(SIDECAR_RUNS), ids=lambda w: "-".join(w[0]) + ":" + w[1])
def test_a_link_at_a_sidecar_is_never_followed(writer, sidecar, inputs, tmp_path):
    """``<out><sidecar>`` is a symlink to a session outside the output folder: the run either writes its output
    or refuses in one line, and the session the link points to is byte for byte as it was, the link still there.
    ``.journal`` only for the writers of sessions (the others have none)."""
    if sidecar == ".journal" and writer not in SESSION_WRITERS:
        pytest.skip("only session writers keep a journal")
    suffix, argv, _own = RUNS[writer]
    out_dir, victim_dir = tmp_path / "out", tmp_path / "elsewhere"
    out_dir.mkdir()
    victim_dir.mkdir()
    victim = shutil.copyfile(inputs["other_session"], victim_dir / "precious.h5")
    target = out_dir / f"target{suffix}"
    link = out_dir / (target.name + sidecar)
    link.symlink_to(victim)
    before = _digest(victim)
    env = dict(os.environ, RIGCTL_CONFIG=str(tmp_path / "no-rig.json"), QT_QPA_PLATFORM="offscreen")
    args = [str(a) for a in argv(dict(inputs, T=target, T_dir=target, new=tmp_path / "new.h5"))]
    args = [a for a in args if a != "--overwrite"] + list(SIDECAR_RUNS[writer])
    r = subprocess.run([*RIGCTL, *args], capture_output=True, text=True, timeout=300, env=env, cwd=tmp_path)
    out = r.stdout + r.stderr
    assert "Traceback" not in out and "internal error" not in out, out
    if r.returncode:  # refused: the sidecar named, left as it is
        assert "left as it is" in out, (writer, sidecar, out)
        assert len([line for line in out.splitlines() if line.startswith("Error:")]) == 1, out
    else:
        assert target.is_file() and not target.is_symlink(), out
    assert _digest(victim) == before, (writer, sidecar, "the file behind the link changed", out)
    assert link.is_symlink() and os.readlink(link) == str(victim), (writer, sidecar, "the link was replaced", out)
    assert sorted(os.listdir(victim_dir)) == ["precious.h5"]


def test_a_users_own_part_file_is_kept(inputs, tmp_path):
    """A file of the user's at ``<out>.part`` (not a link): refused in one line naming it, kept byte for byte."""
    out = tmp_path / "enc.h5"
    mine = tmp_path / "enc.h5.part"
    mine.write_text("my notes, named like this for my own reasons\n")
    r = subprocess.run([*RIGCTL, "encode", str(inputs["session"]), "--out", str(out)], capture_output=True,
                       text=True, timeout=300, cwd=tmp_path)
    assert r.returncode == 2, r.stdout + r.stderr
    errors = [line for line in (r.stdout + r.stderr).splitlines() if line.startswith("Error:")]
    assert len(errors) == 1 and "enc.h5.part exists" in errors[0] and "left as it is" in errors[0], errors
    assert mine.read_text() == "my notes, named like this for my own reasons\n" and not out.exists()
