"""Issue 55 item 5: a Mega image without a build id (``make BUILD_ID=``: what the Arduino IDE builds, and what a plain
make built before the Makefile computed the id) runs under simavr and is refused at open with one line."""

from __future__ import annotations

import shutil
import subprocess

import pytest

from rigctl import firmware
from rigctl.rigs import open_rig
from rigctl.simulation import hil

pytestmark = pytest.mark.hil


def test_a_mega_image_without_a_build_id_is_refused_at_open(fw_build, tmp_path, monkeypatch):
    from rigctl.acquisition.rig import FirmwareMismatch

    # the build folder copied with its times (only the id's objects rebuild), then both images made without an id
    out = tmp_path / "build"
    subprocess.run(["cp", "-a", str(fw_build), str(out)], check=True)
    proc = subprocess.run(["make", "-s", "-C", str(firmware.sources()), f"BUILD={out}", "BUILD_ID=", "mega", "uno"],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "mega_drum build 0" in proc.stdout
    monkeypatch.setattr(hil.firmware, "build", lambda src=None, out_=None, **kw: out)
    monkeypatch.setattr(hil.firmware, "build_dir", lambda src=None: out)
    with pytest.raises(FirmwareMismatch) as exc:
        open_rig("hil", seed=1, host_config_path=tmp_path / "rig.json")
    line = str(exc.value)
    assert "\n" not in line and "the Mega runs firmware" in line and "build 0" in line, line
    assert f"mega firmware {'.'.join(map(str, firmware.source_versions()['mega']))} build {firmware.build_id()}" in line
    assert "rigctl firmware --flash PORT --board mega" in line
    shutil.rmtree(out)
