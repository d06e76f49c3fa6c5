"""Write tests/unit_seconds.json from a test run's $RIGCTL_TEST_CPU_LOG (tests/conftest.py: one line per test, node
id, wall s, CPU s, worker, start time): the wall seconds of each unit of work (``tests.conftest.unit_of``), which the test command's
scheduler hands out longest first.

    RIGCTL_TEST_CPU_LOG=/tmp/cpu.log bash scripts/test.sh && python scripts/unit_seconds.py /tmp/cpu.log
"""

from __future__ import annotations

import json
import sys
from collections import defaultdict
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print("usage: python scripts/unit_seconds.py CPU_LOG", file=sys.stderr)
        return 2
    sys.path.insert(0, str(REPO))
    from tests.conftest import UNIT_SECONDS, unit_of

    seconds: dict[str, float] = defaultdict(float)
    for line in Path(argv[0]).read_text().splitlines():
        nodeid, wall = line.split("\t")[:2]
        seconds[unit_of(nodeid)] += float(wall)
    ordered = dict(sorted(((u, round(s, 1)) for u, s in seconds.items()), key=lambda kv: -kv[1]))
    UNIT_SECONDS.write_text(json.dumps(ordered, indent=0) + "\n")
    print(f"{UNIT_SECONDS}: {len(ordered)} units, {sum(ordered.values()):.0f} s in all")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
