"""Exit codes the reviewers found inconsistent (issue 36 part 4): a bad ``--scheduler`` is a usage error (2, was an
internal error, 1); the loser of two writers of one output exits 2 for ``encode`` as for ``export nwb`` (encode said
1); ``import`` on a full disk does not suggest ``--resume``, which it does not have."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.cli import main
from rigctl.storage.session import SessionWriter, TrialData


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("exit") / "s.h5"
    rng = np.random.default_rng(0)
    plan = [dict(trial_id=i, texture="AB"[i % 2], speed_mm_s=80.0, force_g=500.0, duration_s=0.1) for i in range(4)]
    with SessionWriter.create(path, plan=plan, protocol_source="x", compression=None, durable=False) as w:
        w.write_trials((i, TrialData(taxels=rng.integers(0, 1024, (100, 18)), seq=np.arange(100))) for i in range(4))
    return path


@pytest.mark.parametrize("value", ["-1", "tcp://", "host:99999", "a b"])
@pytest.mark.parametrize("command", ["encode", "analyze"])
def test_a_bad_scheduler_is_a_usage_error(session, tmp_path, command, value):
    args = [command, str(session), "--scheduler", value]
    r = CliRunner().invoke(main, args + (["--out", str(tmp_path / "e.h5")] if command == "encode" else []))
    assert r.exit_code == 2 and "--scheduler" in r.stderr and "internal error" not in r.stderr, r.output


def test_good_scheduler_addresses_pass_the_check():
    from rigctl.cli.outputs import scheduler_address

    for value in ("local", "LOCAL", "tcp://127.0.0.1:8786", "tls://sched.lab:8786", "127.0.0.1:8786", "[::1]:8786"):
        assert scheduler_address(None, None, value)  # type: ignore[arg-type]


def test_the_second_writer_of_an_output_exits_2_for_encode_and_export(session, tmp_path, monkeypatch):
    """Both commands checked the output before any work; another writer takes it meanwhile (the race the review
    hit: held here for the length of the command). Both refuse it the same way."""
    import rigctl.cli.encode as encode_cli
    import rigctl.cli.export as export_cli
    from rigctl.storage import journal

    monkeypatch.setattr(encode_cli, "check_output", lambda path, **kw: Path(path))  # the race: checked before
    monkeypatch.setattr(export_cli, "check_output", lambda path, **kw: Path(path))
    codes = {}
    for name, out, args in (("encode", tmp_path / "o.enc.h5", ["--variant", "original"]),
                            ("export", tmp_path / "o.nwb", [])):
        lock = journal.WriterLock(out)  # the other writer
        try:
            cmd = ["encode", str(session)] if name == "encode" else ["export", "nwb", str(session)]
            r = CliRunner().invoke(main, cmd + ["--out", str(out), "--no-progress"] + args)
        finally:
            lock.release()
        codes[name] = r.exit_code
        assert "internal error" not in r.output and r.stderr.count("\n") <= 2, r.output
        assert not out.exists()
    assert codes == {"encode": 2, "export": 2}


def test_import_on_a_full_disk_does_not_suggest_resume(tmp_path, monkeypatch):
    from rigctl.storage import importers
    from rigctl.storage.session import SessionWriteError

    def full(self, items, **kw):
        raise SessionWriteError(f"no space left on device writing {self.path} (writing trials): nothing of it was "
                                "written; trials 0-1 are intact; free space and --resume", 28, [0, 1])

    monkeypatch.setattr(SessionWriter, "write_trials", full)
    with pytest.raises(SessionWriteError) as err:
        importers.write_session(tmp_path / "i.h5", [dict(trial_id=0, texture="A", speed_mm_s=1.0, force_g=1.0,
                                                         duration_s=0.1)], [], layout=_layout(),
                                textures=_textures())
    text = str(err.value)
    assert "--resume" not in text and "partial output was removed" in text and "run the import again" in text, text
    assert text.startswith("no space left on device") and err.value.intact == []
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # no empty import output left (issue 52)


def _layout():
    from rigctl.core.sensor import PAPER_SENSOR

    return PAPER_SENSOR


def _textures():
    from rigctl.core.textures import PAPER_TEXTURES

    return PAPER_TEXTURES
