"""One trial of a session encoded on the fly (rigctl.operations.trial_spikes, what the GUI's analysis tab shows): the
session-wide per-taxel range, and the same spikes as the batch SA and RA encoders give for that trial."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl.acquisition.protocol import parse_protocol
from rigctl.encoding.izhikevich import encode_ra, encode_sa
from rigctl.operations import session_taxel_range, trial_spikes
from rigctl.simulation.dataset import generate_dataset
from rigctl.storage.session import open_session


def test_trial_spikes_match_the_batch_encoders_under_the_sessions_range(tmp_path):
    path = tmp_path / "s.h5"
    generate_dataset(parse_protocol('name = "t"\ntextures = ["A", "L"]\nspeeds_mm_s = [80]\nforces_g = [500]\n'
                                    'trials_per_condition = 2\nduration_s = 0.3\n'), path, workers=0, progress=False)
    rng = session_taxel_range(path)
    with open_session(path) as s:
        trials = [s.trial(t) for t in s.completed_ids()]
    lo = np.min([t.taxels.min(axis=0) for t in trials], axis=0)
    hi = np.max([t.taxels.max(axis=0) for t in trials], axis=0)
    np.testing.assert_array_equal(rng.minimum, lo)
    np.testing.assert_array_equal(rng.maximum, hi)
    got = trial_spikes(path, 2, taxel_range=rng)
    x = trials[2].taxels
    np.testing.assert_array_equal(got.readings, x)
    assert got.duration_s == pytest.approx(0.3) and len(got.sa) == len(got.ra) == x.shape[1] == 18
    sa, ra = encode_sa(x[None], normalise=rng), encode_ra(x[None], normalise=rng)
    for k in range(18):
        np.testing.assert_allclose(got.sa[k], sa.train(0, k))
        np.testing.assert_allclose(got.ra[k], ra.train(0, k))
    assert sum(len(a) for a in got.sa) > 0 and sum(len(a) for a in got.ra) > 0
    same = trial_spikes(path, 2)  # the range defaults to the session's
    assert all(np.array_equal(a, b) for a, b in zip(same.sa, got.sa))
    with pytest.raises(KeyError):
        trial_spikes(path, 99, taxel_range=rng)
