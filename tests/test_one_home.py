"""One home per concept (docs/architecture.md, rigctl.core): the encoding model's step rate and RA cutoff
(:mod:`rigctl.core.encoding_model`) and the one-line error format (:func:`rigctl.core.errors.describe_error`) are
written once; everything else names them. A source scan: cheap, and it names the file and line that copies one."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from rigctl.core.encoding_model import MODEL_RATE_HZ, MODEL_STEP_S, RA_CUTOFF_HZ
from rigctl.core.errors import describe_error, one_line

ROOT = Path(__file__).resolve().parents[1]

#: (what, pattern, folders it must not appear in, the files allowed to hold it)
COPIES = [
    ("the error format f'{type(exc).__name__}: {exc}' (use rigctl.core.errors.describe_error)",
     re.compile(r"__name__\}: \{"), ["rigctl", "gui"],
     {"rigctl/core/errors.py",
      "rigctl/cli/errors.py"}),  # the CLI's last line of defence: KeyError keys and numpy scalars read plainly
    ("the RA cutoff as a literal (use rigctl.core.encoding_model.RA_CUTOFF_HZ)",
     re.compile(r"cutoff\w*\b[^=\n]{0,12}=\s*20(\.0)?\b"), ["rigctl", "gui"], {"rigctl/core/encoding_model.py"}),
    ("the model's 1 kHz step as a literal (use rigctl.core.encoding_model.MODEL_RATE_HZ)",
     re.compile(r"\b(fs|fs_hz|model_rate_hz|max_rate_hz|model_fs)\b[^=\n]{0,12}=\s*1000(\.0)?\b|\"fs_hz\", 1000"),
     ["rigctl/encoding", "rigctl/storage", "rigctl/operations", "rigctl/analysis", "gui"],
     {"rigctl/core/encoding_model.py"}),
]


@pytest.mark.parametrize("what, pattern, folders, allowed", COPIES, ids=["error-format", "ra-cutoff", "model-rate"])
def test_written_once(what, pattern, folders, allowed):
    copies = []
    for folder in folders:
        for path in sorted((ROOT / folder).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            for n, line in enumerate(path.read_text().splitlines(), 1):
                if pattern.search(line) and rel not in allowed:
                    copies.append(f"{rel}:{n}: {line.strip()}")
    assert not copies, f"{what}:\n" + "\n".join(copies)


def test_the_patterns_find_copies():
    """Each pattern matches the copy it guards against (else the scan above proves nothing)."""
    samples = ['error = f"{type(exc).__name__}: {exc}"', "def f(x, cutoff_hz: float = 20.0):",
               "def f(x, fs: float = 1000.0):"]
    for (_, pattern, _, _), sample in zip(COPIES, samples):
        assert pattern.search(sample), sample


def test_the_constants_and_the_format():
    assert (MODEL_RATE_HZ, MODEL_STEP_S, RA_CUTOFF_HZ) == (1000.0, 0.001, 20.0)
    assert describe_error(ValueError("bad\n  value")) == "ValueError: bad value"
    assert describe_error(TimeoutError()) == "TimeoutError"
    assert describe_error(OSError("x" * 200), 20) == "OSError: " + "x" * 17 + "..."
    assert one_line("a\tb\n c") == "a b c" and one_line("abcdefgh", 5) == "ab..." and one_line("short", 5) == "short"
