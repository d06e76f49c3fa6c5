"""The per-taxel normalisation is one type (rigctl.core.normalisation.TaxelRange): the calibration's result, stored
in the rig config, read back and handed to the encoder as it is, with no bridge between two classes."""

from __future__ import annotations

import numpy as np
import pytest

from rigctl.acquisition import calibration
from rigctl.core.normalisation import TaxelRange
from rigctl.encoding.normalise import TaxelRange as EncoderRange


def test_the_calibration_result_is_the_encoders_normaliser(tmp_path):
    rng = np.random.default_rng(0)
    caps = [rng.integers(100, 900, size=(50, 18)).astype(np.uint16) for _ in range(3)]
    norm = calibration.taxel_normalisation(caps, source="three captures")
    assert type(norm) is TaxelRange and EncoderRange is TaxelRange and calibration.TaxelNormalisation is TaxelRange
    allx = np.vstack(caps)
    assert np.array_equal(norm.taxel_min, allx.min(axis=0)) and np.array_equal(norm.taxel_max, allx.max(axis=0))
    assert norm.n_trials == 3 and norm.source == "three captures" and norm.calibrated_utc
    # the same object drives the encoder's affine map and the clipped 0-1 mapping
    offset, scale = norm.offset_scale()
    assert np.allclose((allx - offset) * scale, norm.normalise(allx, np.float64))
    assert norm.apply(allx).min() == 0.0 and norm.apply(allx).max() == 1.0
    assert norm.apply(np.full((1, 18), 5000)).max() == 1.0  # clipped

    cfg = tmp_path / "rig.json"
    calibration.store_taxel_normalisation(norm, cfg)
    host = calibration.load_rig_config(cfg)
    back = calibration.stored_taxel_range(host, 18)
    assert np.array_equal(back.minimum, norm.minimum) and back.source == norm.source
    assert calibration.stored_taxel_range(host, 9) is None  # made for another sensor


def test_update_accumulates_and_refuses_another_taxel_count():
    r = TaxelRange().update(np.array([[1, 5], [3, 2]])).update(np.array([[0, 9]]))
    assert r.minimum.tolist() == [0, 2] and r.maximum.tolist() == [3, 9] and r.n_samples == 3
    with pytest.raises(ValueError, match="3 taxels, expected 2"):
        r.update(np.zeros((1, 3)))
    with pytest.raises(RuntimeError):
        TaxelRange().offset_scale()
    flat = TaxelRange(np.array([4.0]), np.array([4.0]))
    assert flat.apply(np.array([[4.0], [7.0]])).tolist() == [[0.0], [0.0]]  # a taxel that never changed maps to 0
    old = TaxelRange.from_dict({"minimum": [1, 2], "maximum": [3, 4]})  # the encoder's older dict
    assert old.taxel_max.tolist() == [3.0, 4.0]
