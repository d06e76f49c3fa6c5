"""A newcomer's rough edges (issue 24): no display, Ctrl-C, strict JSON, broken pipes, honest bars and summaries,
the README's library snippet from an empty folder, whole protocol descriptions."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.cli import main
from rigctl.storage.session import SessionWriter, TrialData

ROOT = Path(__file__).resolve().parents[1]
RIGCTL: list[str] = []  # the command: this worker's preloaded rigctl (tests/conftest.py _preloaded_rigctl)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    path = tmp_path_factory.mktemp("newcomer") / "s.h5"
    rng = np.random.default_rng(0)
    plan = [dict(trial_id=i, texture="AB"[i % 2], speed_mm_s=40.0, force_g=500.0, duration_s=0.1)
            for i in range(400)]
    with SessionWriter.create(path, plan=plan, protocol_source="name = 'n'") as w:
        w.write_trials((i, TrialData(taxels=rng.integers(0, 1024, (100, 18)), seq=np.arange(100))) for i in range(4))
    return path


def _env(**kw):
    env = {k: v for k, v in os.environ.items() if k not in kw or kw[k] is not None}
    env.update({k: v for k, v in kw.items() if v is not None})
    return env


def test_gui_without_a_display_is_one_line(tmp_path):
    env = _env()
    for k in ("DISPLAY", "WAYLAND_DISPLAY", "QT_QPA_PLATFORM"):
        env.pop(k, None)
    r = subprocess.run([*RIGCTL, "gui", "--sim"], env=env, capture_output=True, text=True,
                       timeout=120, cwd=tmp_path)
    assert r.returncode == 1, (r.returncode, r.stderr)
    assert r.stderr.strip().splitlines() == [r.stderr.strip()] and "no display" in r.stderr


def test_json_is_strict_nan_becomes_null(session, tmp_path):
    path = tmp_path / "nan.h5"
    path.write_bytes(session.read_bytes())
    with h5py.File(path, "r+") as f:  # an imported recording: no force label
        plan = f["plan"][()]
        plan["force_g"][:] = np.nan
        f["plan"][...] = plan
    r = CliRunner().invoke(main, ["info", str(path), "--json"])
    assert r.exit_code == 0, r.output

    def refuse(constant):
        raise ValueError(f"not JSON: {constant}")

    d = json.loads(r.stdout, parse_constant=refuse)
    assert d["trials"][0]["force_g"] is None


def test_a_broken_pipe_is_quiet(session):
    p = subprocess.Popen([*RIGCTL, "info", str(session)], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE)
    p.stdout.close()  # `| head` that has read enough
    err = p.stderr.read().decode()
    p.wait(timeout=120)
    assert p.returncode in (0, 1) and err == "", err


def test_ctrl_c_during_sim_dataset_says_how_to_resume(tmp_path):
    out = tmp_path / "d.h5"
    # 1,200 trials: a few seconds at the generator's quiet rate (~430 trials/s at paper size; its workers fork and
    # render from the start), so the Ctrl-C lands while they render (240 trials were done within the second this
    # test then waited)
    p = subprocess.Popen([*RIGCTL, "sim", "dataset", "quick_check", "--out", str(out),
                          "--trials-per-condition", "200", "--workers", "2", "--quiet"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 300
    while not out.exists() and p.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.3)  # the workers are rendering
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=300)
    assert p.returncode == 1, f"the run ended {p.returncode} before the Ctrl-C, or ignored it: {err}"
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    assert "--resume" in err and err.strip().count("\n") == 0, err
    r = CliRunner().invoke(main, ["sim", "dataset", "quick_check", "--out", str(out), "--trials-per-condition", "200",
                                  "--resume", "--quiet", "--workers", "0"])
    assert r.exit_code == 0, r.output


def test_encode_bars_are_named_for_what_they_do(session, tmp_path):
    r = CliRunner().invoke(main, ["encode", str(session), "--out", str(tmp_path / "e.h5"), "--variant", "original",
                                  "--progress"])
    assert r.exit_code == 0, r.output
    stages = set(re.findall(r"(reading trials|range pass|encoding):", r.stderr))
    assert stages == {"reading trials", "encoding"}, r.stderr
    # not a terminal (CliRunner's stderr is a buffer): no bars unless asked, so logs get no bar updates
    r = CliRunner().invoke(main, ["encode", str(session), "--out", str(tmp_path / "f.h5"), "--variant", "original"])
    assert r.exit_code == 0, r.output
    assert not re.findall(r"(reading trials|range pass|encoding):", r.stderr), r.stderr


def test_acquire_draws_its_bar_only_on_a_terminal_or_when_asked(tmp_path):
    """acquire follows the other long commands' rule (issue 38): its trial bar is drawn on a terminal or with
    ``--progress``, not into a log (a CI log held 3,000 characters of bar redraws and no error line)."""
    protocol = tmp_path / "two.toml"  # two short trials: a bar with a step between its ends
    protocol.write_text('name = "two"\ntextures = ["A"]\nspeeds_mm_s = [120]\nforces_g = [250]\n'
                        'trials_per_condition = 2\nduration_s = 0.3\n')
    for extra, drawn in (([], False), (["--progress"], True)):
        out = tmp_path / f"q{len(extra)}{drawn}.h5"
        r = CliRunner().invoke(main, ["acquire", str(protocol), "--inprocess", "--out", str(out), *extra])
        assert r.exit_code == 0, r.output
        assert bool(re.search(r"two: +\d+%", r.stderr)) == drawn, (extra, r.stderr[-500:])


def test_encode_writes_enc_h5_by_default_and_outputs_keep_their_format(session, tmp_path):
    """One default suffix (``d.h5`` -> ``d.enc.h5``, as the docs write it) and an output's extension checked against
    the format written: ``--out x.csv`` for an HDF5 writer is one usage line, nothing written (issue 38)."""
    copy = tmp_path / "d.h5"
    shutil.copyfile(session, copy)
    r = CliRunner().invoke(main, ["encode", str(copy), "--variant", "original", "--quiet"])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "d.enc.h5").is_file() and not (tmp_path / "d.encoded.h5").exists()
    for args in (["encode", str(copy)], ["sim", "dataset", "quick_check"], ["acquire", "quick_check", "--inprocess"],
                 ["import", str(copy)]):
        r = CliRunner().invoke(main, [*args, "--out", str(tmp_path / "x.csv")])
        assert r.exit_code == 2 and "unsupported format .csv; use one of .h5, .hdf5" in r.output, (args, r.output)
        assert r.output.strip().count("\n") == 0 and not (tmp_path / "x.csv").exists()


def test_run_summary_of_nothing_recorded_says_so():
    from rigctl.acquisition.runner import RunSummary

    done = RunSummary(path=Path("q.h5"), planned=6, complete=6, recorded=0)
    text = "\n".join(done.lines())
    assert "samples: 0" not in text and "already complete" in text
    run = RunSummary(path=Path("q.h5"), planned=6, complete=6, recorded=6, samples=12000)
    assert "kept trials" not in "\n".join(run.lines())
    lossy = RunSummary(path=Path("q.h5"), planned=6, complete=6, recorded=6, samples=12000, lossy=2, dropped_frames=5)
    assert "(in 2 kept trials)" in "\n".join(lossy.lines())


def test_protocol_descriptions_are_whole_sentences():
    r = CliRunner().invoke(main, ["protocols"])
    assert r.exit_code == 0
    rows = dict(line.split(None, 1) for line in r.stdout.strip().splitlines())
    assert rows["quick_check"].rstrip().endswith("fastest speed.")
    assert all(text.rstrip().endswith(".") for text in rows.values()), rows


def test_shipped_protocols_and_snippets_name_no_checkout_path():
    for f in (ROOT / "rigctl" / "protocols").iterdir():
        assert "protocols/" not in f.read_text(), f


def test_the_readme_library_snippet_runs_from_an_empty_folder(tmp_path, monkeypatch):
    """The README's library snippet as the page's own marker sizes it (``small: open_rig("sim") =>
    open_rig("inprocess")``: what it proves is that its paths work outside a clone, not the rig's pace; quick_check
    on the real-time --sim rig is tests/acquisition/test_acq_cli.py's), run in an empty folder."""
    import runpy

    from .guides import blocks

    text = (ROOT / "README.md").read_text()
    library = text[:text.index("## Library")].count("\n") + 1  # the section's heading line
    block = next(b for b in blocks("README.md") if b.lang == "python" and b.line > library)
    (tmp_path / "snippet.py").write_text(block.as_run())
    monkeypatch.setenv("RIGCTL_CONFIG", str(tmp_path / "rig.json"))
    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.chdir(tmp_path)
    runpy.run_path(str(tmp_path / "snippet.py"), run_name="__main__")
    from rigctl.storage.session import open_session

    with open_session(tmp_path / "quick.h5") as s:
        assert len(s.completed_ids()) == len(s.plan) > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["quick.h5", "snippet.py"]  # nothing beside it


def test_sim_dataset_help_states_the_paper_datasets_size():
    """The help said ~3 GB for a dataset of ~4.4 GB: its figure is the size estimate's (which refuses a disk too
    small), in decimal GB."""
    from rigctl.acquisition.builtin import find_protocol
    from rigctl.acquisition.protocol import load_protocol
    from rigctl.cli.sim_dataset import dataset_size

    _, size = dataset_size(load_protocol(find_protocol("paper_dataset")))
    text = " ".join(CliRunner().invoke(main, ["sim", "dataset", "--help"]).output.split())
    assert f"~{size / 1e9:.1f} GB" in text, text


def _interrupt_on_call(n: int):
    """A stand-in that raises KeyboardInterrupt (Ctrl-C) on its n-th call and otherwise does nothing."""
    calls = []

    def stand_in(*args, **kwargs):
        calls.append(1)
        if len(calls) == n:
            raise KeyboardInterrupt

    return stand_in


@pytest.mark.parametrize("command", ["encode", "export"])
def test_ctrl_c_during_encode_or_export_is_one_line_and_leaves_nothing(session, tmp_path, monkeypatch, command):
    """Ctrl-C in the middle of the write (the encoded file's tables written; the NWB file's first taxel block):
    one line, exit 1, no partial output, the input unchanged. In this process: KeyboardInterrupt is what SIGINT
    raises in the main thread."""
    before = session.read_bytes()
    partial = []
    if command == "encode":
        import rigctl.encoding.pipeline as pipeline

        def interrupted_pass(*args, **kwargs):
            partial.extend(tmp_path.iterdir())  # the encoded file is being written
            raise KeyboardInterrupt

        monkeypatch.setattr(pipeline, "_encode_pass", interrupted_pass)
        args = ["encode", str(session), "--out", str(tmp_path / "e.h5"), "--quiet", "--variant", "original"]
    else:
        import rigctl.storage.nwb as nwb

        blocks = nwb._taxel_blocks

        def interrupted_blocks(*args, **kwargs):
            for block in blocks(*args, **kwargs):
                partial.extend(tmp_path.iterdir())  # the NWB file is being written
                raise KeyboardInterrupt
                yield block

        monkeypatch.setattr(nwb, "_taxel_blocks", interrupted_blocks)
        args = ["export", "nwb", str(session), "--out", str(tmp_path / "e.nwb"), "--no-progress"]
    r = CliRunner().invoke(main, args)
    assert r.exit_code == 1, r.output
    assert r.stderr.strip().splitlines() == ["Error: interrupted (Ctrl-C): no partial output was left; the inputs "
                                             "are unchanged"], r.stderr
    assert partial and list(tmp_path.iterdir()) == []
    assert session.read_bytes() == before


def test_ctrl_c_during_acquire_keeps_finished_trials_and_says_how_to_resume(tmp_path, monkeypatch):
    """On the in-process rig: Ctrl-C before the second of three trials; the first stays in the file, the summary
    says 'stopped early (resume with --resume)', exit 1, and --resume finishes the session."""
    import rigctl.acquisition.runner as runner
    from rigctl.operations import RigSource
    from rigctl.storage.session import open_session

    flags = RigSource.from_flags.__func__
    monkeypatch.setattr(RigSource, "from_flags", classmethod(lambda cls, **kw: cls("inprocess")))
    monkeypatch.setenv("RIGCTL_CONFIG", str(tmp_path / "rig.json"))
    assert flags(RigSource).kind == "sim"  # what the CLI would open: the in-process rig stands in for it
    protocol = tmp_path / "three.toml"
    protocol.write_text('name = "three"\ndescription = "Three short trials."\ntextures = ["A"]\n'
                        'speeds_mm_s = [120]\nforces_g = [250]\ntrials_per_condition = 3\ntravel_mm = 12\n')
    out = tmp_path / "a.h5"
    wait = runner._wait_while_paused
    stand_in = _interrupt_on_call(2)

    def wait_then_interrupt(*args, **kwargs):
        stand_in()
        return wait(*args, **kwargs)

    monkeypatch.setattr(runner, "_wait_while_paused", wait_then_interrupt)
    r = CliRunner().invoke(main, ["acquire", str(protocol), "--out", str(out), "--quiet"])
    assert r.exit_code == 1, r.output
    assert "stopped early (resume with --resume)" in r.output and "Traceback" not in r.output, r.output
    with open_session(out) as s:
        assert s.completed_ids() == [0]
    monkeypatch.setattr(runner, "_wait_while_paused", wait)
    r = CliRunner().invoke(main, ["acquire", str(protocol), "--out", str(out), "--quiet", "--resume"])
    assert r.exit_code == 0, r.output
    with open_session(out) as s:
        assert s.completed_ids() == [0, 1, 2]
