"""The drum controller's C sources under cppcheck's MISRA C:2012 addon (issue 80 item 5; docs/firmware.md, "MISRA
C:2012"): no finding of cppcheck's own, and every MISRA rule it reports is a deviation recorded in docs/firmware.md
with its reason (and every recorded deviation still occurs): a new kind of violation fails the suite."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SOURCES = ("controller.c", "force_pi.c", "steprate.c", "modbus_slave.c")
FINDING = re.compile(r"^(?P<file>[^:\s]+):(?P<line>\d+):\d+: (?P<severity>\w+): (?P<text>.*) \[(?P<id>[\w.-]+)\]$")


def _cppcheck() -> str:
    found = shutil.which("cppcheck")
    if found is None:
        if os.environ.get("CI") == "true":
            pytest.fail("cppcheck is not installed (scripts/test.sh installs Debian's)")
        pytest.skip("cppcheck is not installed (Debian: apt install cppcheck)")
    return found


def _deviations() -> dict[str, int]:
    """docs/firmware.md's MISRA table: rule -> the findings it records."""
    text = (REPO / "docs" / "firmware.md").read_text()
    table = text.split("### MISRA C:2012", 1)[1].split("\n#", 1)[0]
    rows = [line.split("|")[1:-1] for line in table.splitlines() if re.match(r"^\| \d+\.\d+ \|", line)]
    return {r[0].strip(): int(r[2]) for r in rows}


def test_the_controller_has_no_misra_rule_beyond_its_recorded_deviations(tmp_path):
    src = REPO / "arduino" / "mega_drum"
    r = subprocess.run([_cppcheck(), "--addon=misra", "--std=c11", "--enable=warning,style,portability", "-q",
                        f"--cppcheck-build-dir={tmp_path}", f"-I{REPO / 'arduino' / 'common'}",
                        *(str(src / f) for f in SOURCES)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    findings = [m.groupdict() for m in map(FINDING.match, r.stderr.splitlines()) if m]
    assert findings, r.stderr[-2000:]  # the addon ran (this code has recorded deviations)
    own = [f"{f['file']}:{f['line']}: {f['text']} [{f['id']}]" for f in findings
           if not f["id"].startswith("misra-c2012-")]
    assert not own, "cppcheck's own findings:\n" + "\n".join(own)
    counts: dict[str, int] = {}
    for f in findings:
        rule = f["id"].removeprefix("misra-c2012-")
        counts[rule] = counts.get(rule, 0) + 1
    recorded = _deviations()
    new = {rule: n for rule, n in counts.items() if rule not in recorded}
    assert not new, f"MISRA rules not recorded as deviations in docs/firmware.md: {new}"
    stale = sorted(set(recorded) - set(counts))
    assert not stale, f"docs/firmware.md records deviations of rules that no longer occur: {stale}"
