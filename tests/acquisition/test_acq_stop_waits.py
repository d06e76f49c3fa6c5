"""A STOP ends the run's waits on the drum controller at once, not at their timeouts (in-process rig, simulated time).

A loaded CI run's GUI test saw 30 s of the rig's clock between the operator's STOP and the protocol tab's STOPPED:
the STOP came during the first trial's HOME, the controller went back to NOT_HOMED, and the run waited 30 s for an
IDLE that could no longer come. Each case here sends the STOP (the controller's, and the run's stop flag, as the
operations layer does) at the moment the wait under test has begun, seen through the drum client's own status reads,
and judges the rig's clock from the STOP to the run's end."""

from __future__ import annotations

import threading

import pytest

from rigctl.acquisition.rig import TrialAborted
from rigctl.core.drum import DrumWaitAborted
from rigctl.core.trial import PlannedTrial
from rigctl.devices.wire import DrumState
from rigctl.rigs import open_rig

#: the rig's clock from the STOP to the run's end, s, at most (a few status polls; the waits' timeouts are 10-30 s)
PROMPT_S = 1.0


@pytest.fixture
def rig(tmp_path):
    with open_rig("inprocess", seed=3, host_config_path=tmp_path / "rig.json") as r:
        yield r


def _stop_when(rig, state: DrumState) -> tuple[threading.Event, list[float]]:
    """The operator's STOP (the controller's STOP, then the run's stop flag) the first time the drum client reads
    ``state``; returns the flag and the rig's time of the STOP (filled in then)."""
    drum, stop, when = rig.drum, threading.Event(), []
    read = drum.read_status

    def read_and_stop():
        st = read()
        if st.state == state and not stop.is_set():
            drum.stop()
            stop.set()
            when.append(drum.clock.now())
        return st

    drum.read_status = read_and_stop
    return stop, when


def test_a_stop_during_the_first_trials_home_ends_the_press_at_once(rig):
    assert rig.drum.read_status().state == DrumState.NOT_HOMED  # opened without HOME: the first press homes
    stop, when = _stop_when(rig, DrumState.HOMING)
    with pytest.raises(TrialAborted):
        rig.press(300, stop_event=stop)
    assert when and rig.drum.clock.now() - when[0] < PROMPT_S


def test_a_stop_during_a_home_without_a_stop_flag_ends_it_at_once(rig):
    """The GUI's Home (rigctl.operations Control.home): no run, no stop flag; the controller back at NOT_HOMED ends
    the wait."""
    _, when = _stop_when(rig, DrumState.HOMING)
    rig.home_pending = True
    with pytest.raises(DrumWaitAborted, match="HOME stopped"):
        rig.home_if_pending()
    assert when and rig.drum.clock.now() - when[0] < PROMPT_S
    assert rig.drum.read_status().state == DrumState.NOT_HOMED


def test_a_stop_while_the_drum_spins_up_ends_the_trial_at_once(rig):
    """A sibling that held before the fix too (after a STOP the speed wait sees a steady 0 of 0 mm/s and the next
    abort check ends the trial): kept so that it stays so."""
    rig.press(300)  # homed and pressed; the trial's own press settles at once
    stop, when = _stop_when(rig, DrumState.RUNNING)
    with pytest.raises(TrialAborted):
        rig.record_trial(PlannedTrial(0, "A", 120.0, 300.0, 0.5), stop_event=stop)
    assert when and rig.drum.clock.now() - when[0] < PROMPT_S
