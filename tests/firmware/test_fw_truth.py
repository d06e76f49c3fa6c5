"""``--truth-log`` (issue 39 item 7): the simulated rigs' ground truth as CSV on the clock ``--inject`` uses. Under
simavr: the Mega pressing 1000 g, ``host-silence`` injected: the log shows the true force below 100 g 1 s after the
watchdog latched (~10 s); on the simulated rig through ``rigctl doctor --sim --truth-log`` (~5 s)."""

from __future__ import annotations

import csv
import time

import numpy as np
import pytest
from click.testing import CliRunner

from rigctl.cli import main
from rigctl.core.faults import parse_fault
from rigctl.devices.drum import DrumClient
from rigctl.devices.wire import DrumState as S, HoldingRegister as HR
from rigctl.rigs import drum_answer_timeout_s
from rigctl.simulation import hil
from rigctl.simulation.truth import TRUTH_COLUMNS

from .conftest import home


def _read(path) -> np.ndarray:
    """The rows as (time_s, true_force_g, actuator_mm, drum_speed_mm_s); their wall_time_s checked to be the Unix time
    of the run (written as the physics went)."""
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    assert tuple(rows[0]) == TRUTH_COLUMNS and TRUTH_COLUMNS[0] == "wall_time_s"
    t = np.array(rows[1:], float)
    assert np.all(np.diff(t[:, 0]) >= 0) and abs(t[-1, 0] - time.time()) < 600, t[-1, 0]
    return t[:, 1:]


@pytest.mark.hil
def test_truth_log_under_simavr_shows_the_back_off_after_host_silence(fw_build, tmp_path):
    path = tmp_path / "t.csv"
    with hil.HilRig(live=False, with_uno=False, truth_log=path) as rig:
        with DrumClient(rig.drum_port, timeout_s=drum_answer_timeout_s("hil"), clock=rig.clock) as drum:
            drum.write_holding(HR.WATCHDOG_MS, 10000)
            home(drum)
            drum.set_force(1000)
            drum.press()
            drum.wait_state([S.FORCE_SETTLED], timeout_s=20)
            rig.truth_start()
            drum.write_holding(HR.WATCHDOG_MS, 300)
            rig.inject_faults([parse_fault("host-silence@0.2")])
            rig._wait_telemetry(rig.next_telemetry().t_s + 2.0, 10.0)
    t = _read(path)
    assert np.all(np.diff(t[:, 0]) <= 0.0105) and t[0, 0] < 0.02  # >= 100 Hz from the run's start
    assert t[0, 1] > 900  # pressing when the run started
    late = t[t[:, 0] >= 0.2 + 0.3 + 1.0]
    assert late.size and late[0, 1] < 100, f"true force {late[0, 1]:.0f} g 1 s after the watchdog"


def test_truth_log_of_the_simulated_rig_from_the_cli(tmp_path, monkeypatch):
    monkeypatch.setenv("RIGCTL_CONFIG", str(tmp_path / "rig.json"))
    path = tmp_path / "t.csv"
    # the noise-floor check holds the rig at rest for --rest-s (2 s of taxel capture): a run of known length (the
    # controller-faults check, one status read, was over in 30-110 ms of physics: 10-35 rows, as fast as the host was)
    result = CliRunner().invoke(main, ["doctor", "--sim", "--check", "noise-floor", "--no-save", "--rest-s", "2",
                                       "--truth-log", str(path)])
    assert result.exit_code == 0, result.output
    t = _read(path)
    # one row per physics step (3 ms paced; a starved physics thread takes longer steps): >= 100 rows a second
    assert len(t) > 10 and len(t) / (t[-1, 0] - t[0, 0]) >= 100 and np.all(np.abs(t[:, 1]) < 5)
    again = CliRunner().invoke(main, ["doctor", "--inprocess", "--truth-log", str(tmp_path / "u.csv")])
    assert again.exit_code == 2 and "--sim or --hil" in again.output
