"""``rigctl firmware --flash PORT --dry-run`` prints the exact avrdude command and flashes nothing; usage errors
exit 2 with one line."""

from __future__ import annotations

import shlex

from click.testing import CliRunner

from rigctl import firmware as fw
from rigctl.cli import main


def _run(*args):
    return CliRunner().invoke(main, list(args))


def test_dry_run_prints_the_exact_avrdude_command_per_board():
    expected = {
        "mega": ["avrdude", "-p", "m2560", "-c", "wiring", "-P", "/dev/ttyACM7", "-b", "115200", "-D",
                 "-U", f"flash:w:{fw.build_dir() / 'mega_drum.hex'}:i"],
        "uno": ["avrdude", "-p", "m328p", "-c", "arduino", "-P", "/dev/ttyACM7", "-b", "115200",
                "-U", f"flash:w:{fw.build_dir() / 'uno_taxel.hex'}:i"],
    }
    for board, cmd in expected.items():
        res = _run("firmware", "--flash", "/dev/ttyACM7", "--board", board, "--dry-run")
        assert res.exit_code == 0, res.output
        assert shlex.split(res.output.splitlines()[0]) == cmd


def test_flash_needs_a_board_it_can_tell_and_options_need_flash():
    res = _run("firmware", "--flash", "/dev/ttyACM7", "--dry-run")  # no such USB port: the board cannot be guessed
    assert res.exit_code == 2 and "--board mega|uno" in res.output
    res = _run("firmware", "--dry-run")
    assert res.exit_code == 2 and "--flash PORT" in res.output
    res = _run("firmware", "--flash", "/dev/ttyACM7", "--board", "leonardo", "--dry-run")
    assert res.exit_code == 2


def test_the_uno_encoder_image_is_flashed_by_name():
    res = _run("firmware", "--flash", "/dev/ttyACM7", "--board", "uno", "--image", "uno_encoder", "--dry-run")
    assert res.exit_code == 0, res.output
    assert shlex.split(res.output.splitlines()[0])[-1] == f"flash:w:{fw.build_dir() / 'uno_encoder.hex'}:i"
    res = _run("firmware", "--flash", "/dev/ttyACM7", "--board", "mega", "--image", "uno_encoder", "--dry-run")
    assert res.exit_code == 2 and "not a mega image" in res.output
    res = _run("firmware", "--image", "uno_encoder")
    assert res.exit_code == 2 and "--flash PORT" in res.output
