"""`rigctl acquire protocols/quick_check.toml --hil`: the acquisition runner on both firmwares under simavr, and a
session file shaped like one from the Python simulated rig."""

from __future__ import annotations

import json
import subprocess
import sys

import h5py
import numpy as np
import pytest

from rigctl.simulation.hil import ARDUINO_DIR
from rigctl.storage.session import open_session

pytestmark = pytest.mark.hil

RIGCTL = [sys.executable, "-c", "from rigctl.cli import main; main()"]
PROTOCOL = ARDUINO_DIR.parent / "protocols" / "quick_check.toml"


def layout(path) -> dict[str, tuple]:
    """``{dataset path: (dtype, trailing shape)}`` of trial 0 plus the root's attributes and datasets."""
    out = {}
    with h5py.File(path, "r") as f:
        out["attrs"] = tuple(sorted(f.attrs))
        out["plan"] = (str(f["plan"].dtype),)
        for name, ds in f["trials"][sorted(f["trials"])[0]].items():
            out[name] = (str(ds.dtype), ds.shape[1:])
    return out


def acquire(out, *args):
    proc = subprocess.run([*RIGCTL, "acquire", str(PROTOCOL), "--out", str(out), "--quiet", *args],
                          capture_output=True, text=True, timeout=240, cwd=ARDUINO_DIR.parent)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return out


def test_quick_check_on_the_firmware_looks_like_the_simulated_rig(fw_build, tmp_path):
    hil = acquire(tmp_path / "hil.h5", "--hil")
    sim = acquire(tmp_path / "sim.h5", "--sim")
    s = open_session(hil)
    plan = s.plan
    assert len(plan) == 6 and sorted(s.completed_ids()) == list(range(6))
    assert json.loads(s.attrs["rig_config"])["mode"] == "hil" if isinstance(s.attrs["rig_config"], str) else True
    stds = {}
    for i in range(6):
        t = s.trial(i)
        n = int(round(float(plan["duration_s"][i]) * 1000))
        assert t.taxels.shape == (n, 18) and t.dropped_frames == 0 and t.crc_errors == 0
        assert np.all(np.diff(t.seq.astype(np.int64)) % 65536 == 1)
        assert abs(np.median(t.force_g) - 500) < 15 and abs(np.median(t.speed_mm_s) - 120) < 1
        letter = plan["texture"][i].decode() if isinstance(plan["texture"][i], bytes) else plan["texture"][i]
        stds.setdefault(letter, []).append(t.taxels.astype(float).std(axis=0).mean())
    # the taxel readings follow the mounted plate: smooth A is quieter than ridged B and waves L
    assert max(stds["A"]) < 0.5 * min(stds["B"] + stds["L"])
    assert layout(hil) == layout(sim)
