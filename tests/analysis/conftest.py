"""Shared fixtures of the analysis tests."""

from __future__ import annotations

import h5py
import numpy as np
import pytest


def _write_schema1(fs, path, n_taxels: int):
    """An unversioned (schema 1) encoded file, as the old pipeline wrote it, from a FeatureSet: features per variant
    and a trials table; ``n_taxels`` taxels x SA/RA spike trains per trial."""
    with h5py.File(path, "w") as f:
        for k, v in fs.features.items():
            f[f"features/{k}"] = v
        t = np.zeros(fs.n_trials, dtype=[("trial_id", "<i8"), ("texture", "S2"), ("speed_mm_s", "<f8"),
                                         ("force_g", "<f8")])
        t["trial_id"] = np.arange(fs.n_trials)
        t["texture"] = fs.texture.astype("S2")
        t["speed_mm_s"], t["force_g"] = fs.speed_mm_s, fs.force_g
        f["trials"] = t
        f.attrs["n_taxels"] = n_taxels
    return path


@pytest.fixture(scope="session")
def write_schema1():
    """``write_schema1(feature_set, path, n_taxels) -> path``: an unversioned encoded file of synthetic features."""
    return _write_schema1
