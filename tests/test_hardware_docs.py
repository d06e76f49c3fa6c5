"""docs/hardware follows the firmware: the pin table and the wiring diagrams are what scripts/hardware_docs.py makes of
the pin headers today, every pin a header's comment names is in the table, and the Arduino pin mapping copied into
rigctl.firmware_pins is the Arduino core's."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest

from rigctl import firmware
from rigctl.firmware_pins import BOARD_HEADERS, comment_pins, parse_header, pins

REPO = Path(__file__).resolve().parents[1]
VARIANTS = Path("/usr/share/arduino/hardware/arduino/avr/variants")


def _script():
    spec = importlib.util.spec_from_file_location("hardware_docs", REPO / "scripts" / "hardware_docs.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_the_committed_pin_table_and_diagrams_are_the_headers_today():
    for name, text in _script().outputs().items():
        committed = (REPO / "docs" / "hardware" / name).read_text()
        assert committed == text, f"docs/hardware/{name} is out of date: run python scripts/hardware_docs.py"


def test_every_pin_a_header_comment_names_is_in_the_table():
    table = {(p.board, p.arduino, p.avr) for p in pins()}
    for board, (header, _, _) in BOARD_HEADERS.items():
        named = comment_pins((firmware.sources() / header).read_text())
        assert named, header
        missing = [(a, avr) for a, avr in named if (board, a, avr) not in table]
        assert not missing, f"{header} names {missing} in a comment but declares no such pin macro"


def test_the_table_follows_a_changed_header():
    """A pin moved in the header moves in the table; a comment contradicting the macros is noticed."""
    text = (firmware.sources() / BOARD_HEADERS["mega"][0]).read_text()
    moved = text.replace("#define PIN_HOME_BIT        4", "#define PIN_HOME_BIT        5")
    home = {p.signal: p for p in parse_header(moved, "mega")}["PIN_HOME"]
    assert (home.arduino, home.avr) == ("D8", "PH5")
    assert ("D7", "PH4") in comment_pins(moved)  # the stale comment still says D7: the test above would fail
    added = text + "\n/* e-stop D2 = PE4 */\n#define PIN_ESTOP_PIN PINE\n#define PIN_ESTOP_PORT PORTE\n" \
                   "#define PIN_ESTOP_BIT 4\n"
    estop = {p.signal: p for p in parse_header(added, "mega")}["PIN_ESTOP"]
    assert (estop.arduino, estop.avr, estop.direction) == ("D2", "PE4", "in, pull-up")
    test_only = added + "#ifdef RIGCTL_TEST_HOOKS\n#define PIN_TEST_HANG_PIN PINA\n#define PIN_TEST_HANG_BIT 0\n#endif\n"
    assert "PIN_TEST_HANG" not in {p.signal for p in parse_header(test_only, "mega")}  # a test image's pin
    assert "PIN_ESTOP" in {p.signal for p in parse_header(test_only, "mega")}


@pytest.mark.parametrize("board,variant", [("mega", "mega"), ("uno", "standard")])
def test_the_copied_pin_mapping_is_the_arduino_cores(board, variant):
    path = VARIANTS / variant / "pins_arduino.h"
    if not path.exists():
        pytest.skip(f"{path} missing (Debian's arduino-core-avr)")
    text = re.sub(r"/\*.*?\*/", "", path.read_text(), flags=re.DOTALL)

    def table(name):
        body = re.search(name + r"\[\]\s*=\s*\{(.*?)\};", text, re.DOTALL).group(1)
        return [x.strip() for x in re.sub(r"//.*", "", body).split(",") if x.strip()]

    ports = table("digital_pin_to_port_PGM")
    bits = [re.search(r"\d+", b).group() for b in table("digital_pin_to_bit_mask_PGM")]
    assert [f"{p[1]}{b}" for p, b in zip(ports, bits)] == list(BOARD_HEADERS[board][1])
