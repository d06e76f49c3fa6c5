"""The documentation site builds with warnings as errors (``mkdocs build --strict``, mkdocs.yml): every page of
docs/ is in the navigation, every link and anchor between pages resolves, and every docstring of the API reference
parses (numpy style)."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

from .conftest import skip_or_fail

REPO = Path(__file__).resolve().parents[1]


def test_the_docs_build_strictly(tmp_path):
    if importlib.util.find_spec("mkdocs") is None or importlib.util.find_spec("mkdocstrings") is None:
        skip_or_fail('mkdocs / mkdocstrings are not installed (the "docs" extra, part of "test")')
    site = tmp_path / "site"
    out = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)],
                         capture_output=True, text=True, cwd=REPO, timeout=600,
                         env=dict(os.environ, NO_MKDOCS_2_WARNING="1"))
    assert out.returncode == 0, out.stderr[-4000:]
    # the guides, the existing reference pages and the API reference rendered from the docstrings
    for page in ("guides/first-recording", "guides/real-rig", "guides/reproducing-the-paper", "my-sensor",
                 "wire-protocol", "firmware"):
        assert (site / page / "index.html").is_file(), page
    api = (site / "api" / "core" / "index.html").read_text()
    assert "rigctl.core.sensor.SensorLayout" in api and "n_channels" in api
    assert ":class:" not in api  # the Sphinx roles of the docstrings are rendered, not shown verbatim
    assert "FirmwareBuildError" in (site / "api" / "firmware" / "index.html").read_text()
