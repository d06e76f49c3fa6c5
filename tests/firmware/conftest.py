"""Fixtures of the firmware tests: the built images and a HilRig (both firmwares under simavr)."""

from __future__ import annotations

import os
import shutil

import pytest

from rigctl.simulation import hil


def _need(tool: str) -> None:
    if shutil.which(tool) is None:
        msg = f"{tool} is not installed (scripts/test.sh installs the Debian toolchain)"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(msg)
        pytest.skip(msg)


@pytest.fixture(scope="session")
def fw_build():
    """Build both images, the harness and nothing else; returns the build directory."""
    for tool in ("make", "avr-gcc", "pkg-config"):
        _need(tool)
    return hil.build()


@pytest.fixture(scope="module")
def hil_rig(fw_build):
    """A running HilRig for one test module (live taxel rendering)."""
    with hil.HilRig() as rig:
        yield rig
