"""The boards' pins, read from the firmware's pin headers: ``mega_drum/drum_config.h`` (Arduino Mega 2560) and
``uno_taxel/uno_pins.h`` (Arduino Uno). docs/hardware/pins.md is generated from :func:`pins` (``python
scripts/hardware_docs.py``) and tests/test_hardware_docs.py holds it equal to the headers.

What a header declares, and how it is read (the macros the firmware's code uses, not prose):

- a pin: ``<STEM>_PORT`` / ``<STEM>_PIN`` / ``<STEM>_DDR`` defined as an I/O register (``PORTB``, ``PINE``,
  ``DDRH``, ...) and ``<STEM>_BIT`` its bit; a ``<STEM>_BIT`` without a register of its own uses its group's (the
  register of a stem with the same prefix up to the last ``_``: ``PIN_DRUM_DIR_BIT`` -> ``PIN_DRUM_STEP_PORT``);
- several pins of one register: ``<STEM>_SHIFT`` + ``<STEM>_MASK`` (consecutive bits), or named bits
  ``<STEM>_<NAME> n`` beside ``<STEM>_PORT``;
- direction: a pin with a ``DDR`` register is an output; one with a ``PIN`` register an input, and with ``PORT`` too
  an input with the internal pull-up; ``PORT`` alone is an input with its pull-up (DDR resets to input). A group's
  pin without registers of its own (``PIN_DRUM_DIR_BIT``) takes its group's ``PORT``/``DDR``.

A comment naming a pin as ``D11 = PB5`` or ``D8 (PB0)`` must agree with the macros (:func:`comment_pins` lists
them; the test checks every one is in the table), so a pin added in another style is noticed.

AVR port bit -> Arduino pin: the ``digital_pin_to_port_PGM`` / ``digital_pin_to_bit_mask_PGM`` tables of the
Arduino core's ``variants/mega`` and ``variants/standard`` ``pins_arduino.h`` (Debian's arduino-core-avr), copied
below and checked against those files when installed.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

__all__ = ["BOARD_HEADERS", "MEGA_PIN_PORTS", "UNO_PIN_PORTS", "Pin", "arduino_pin", "comment_pins", "parse_header",
           "pins"]

#: Arduino digital pin number -> AVR port letter + bit (index = pin number; A0 = 54 on the Mega, 14 on the Uno)
MEGA_PIN_PORTS = ("E0 E1 E4 E5 G5 E3 H3 H4 H5 H6 B4 B5 B6 B7 J1 J0 H1 H0 D3 D2 D1 D0 A0 A1 A2 A3 A4 A5 A6 A7 C7 C6 "
                  "C5 C4 C3 C2 C1 C0 D7 G2 G1 G0 L7 L6 L5 L4 L3 L2 L1 L0 B3 B2 B1 B0 F0 F1 F2 F3 F4 F5 F6 F7 K0 K1 "
                  "K2 K3 K4 K5 K6 K7").split()
UNO_PIN_PORTS = "D0 D1 D2 D3 D4 D5 D6 D7 B0 B1 B2 B3 B4 B5 C0 C1 C2 C3 C4 C5".split()
#: board -> (header under the firmware sources, pin table, first analog pin number)
BOARD_HEADERS = {
    "mega": ("mega_drum/drum_config.h", MEGA_PIN_PORTS, 54),
    "uno": ("uno_taxel/uno_pins.h", UNO_PIN_PORTS, 14),
}

_DEFINE = re.compile(r"^[ \t]*#define[ \t]+(\w+)[ \t]+(.*?)[ \t]*$", re.MULTILINE)
_COMMENT = re.compile(r"/\*(.*?)\*/", re.DOTALL)
_REGISTER = re.compile(r"^(PORT|PIN|DDR)([A-L])$")
_COMMENT_PIN = re.compile(r"\b([DA]\d{1,2})\s*(?:=|\()\s*P([A-L])([0-7])\b")


@dataclasses.dataclass(frozen=True)
class Pin:
    """One pin a board's firmware uses.

    Attributes
    ----------
    board : "mega" | "uno"
    arduino : the Arduino pin name (``D11``, ``A0``)
    avr : the AVR port bit (``PB5``)
    signal : the macro naming it (``PIN_DRUM_STEP``, ``UNO_SEL[0]`` for the first of a group)
    direction : "out" | "in" | "in, pull-up"
    what : the header's comment above it (first sentence)
    """

    board: str
    arduino: str
    avr: str
    signal: str
    direction: str
    what: str


def arduino_pin(board: str, port: str, bit: int) -> str:
    """The Arduino pin name of AVR port ``port`` (letter) bit ``bit`` on ``board`` ("mega" | "uno"). KeyError if
    the board has no such pin."""
    _, table, first_analog = BOARD_HEADERS[board]
    try:
        n = table.index(f"{port}{bit}")
    except ValueError:
        raise KeyError(f"the {board} has no Arduino pin on P{port}{bit}") from None
    return f"A{n - first_analog}" if n >= first_analog else f"D{n}"


def _comment_before(text: str, pos: int) -> str:
    last = None
    for m in _COMMENT.finditer(text, 0, pos):
        last = m
    if last is None:
        return ""
    words = " ".join(last.group(1).replace("*", " ").split())
    return words.split(". ")[0].strip(" .")


def _int(value: str) -> int | None:
    value = value.strip()
    return int(value, 0) if re.fullmatch(r"0x[0-9a-fA-F]+|\d+", value) else None


def _unconditional(text: str) -> str:
    """``text`` without its conditional blocks (``#if``/``#ifdef`` ... ``#endif``, e.g. a test build's pins), the
    include guard (``#ifndef X_H``) kept. Lines are blanked, not removed, so offsets stay."""
    out, depth = [], 0
    for line in text.splitlines(keepends=True):
        word = line.strip().split(maxsplit=1)[0] if line.strip() else ""
        if word in ("#if", "#ifdef") or (word == "#ifndef" and not line.strip().endswith("_H")):
            depth += 1
        elif word == "#endif" and depth:
            depth -= 1
            out.append("\n")
            continue
        out.append("\n" if depth else line)
    return "".join(out)


def parse_header(text: str, board: str) -> list[Pin]:
    """The pins a pin header declares (see the module docstring), in the header's order; pins inside a conditional
    block (``#ifdef RIGCTL_TEST_HOOKS``: a test image's, never flashed) are left out.

    Raises
    ------
    ValueError
        A pin on a port bit the board does not have, or a bit outside 0-7.
    """
    defines = {m.group(1): (m.group(2), m.start()) for m in _DEFINE.finditer(_unconditional(text))}
    registers: dict[str, dict[str, str]] = {}  # stem -> {"PORT": "B", ...}
    for name, (value, _) in defines.items():
        stem, _, kind = name.rpartition("_")
        reg = _REGISTER.match(value)
        if reg and kind in ("PORT", "PIN", "DDR"):
            registers.setdefault(stem, {})[reg.group(1)] = reg.group(2)

    def group_register(stem: str) -> tuple[str, dict[str, str]] | None:
        if stem in registers:
            return stem, registers[stem]
        prefix = stem.rpartition("_")[0]
        for other, regs in registers.items():
            if prefix and other.rpartition("_")[0] == prefix:
                return other, {k: v for k, v in regs.items() if k in ("PORT", "DDR")} or regs
        return None

    def direction(regs: dict[str, str]) -> str:
        if "DDR" in regs:
            return "out"
        if "PIN" in regs:
            return "in, pull-up" if "PORT" in regs else "in"
        return "in, pull-up"  # a PORT register without DDR: the pin stays an input (DDR's reset value), PORT its pull-up

    def make(stem: str, signal: str, regs: dict[str, str], bit: int, pos: int) -> Pin:
        if not 0 <= bit <= 7:
            raise ValueError(f"{signal}: bit {bit} is not 0-7")
        letters = set(regs.values())
        if len(letters) != 1:
            raise ValueError(f"{stem}: its registers name different ports ({', '.join(sorted(letters))})")
        port = letters.pop()
        return Pin(board, arduino_pin(board, port, bit), f"P{port}{bit}", signal, direction(regs),
                   _comment_before(text, pos))

    found: list[tuple[int, Pin]] = []
    for name, (value, pos) in defines.items():
        n = _int(value)
        stem, _, suffix = name.rpartition("_")
        if suffix == "BIT" and n is not None:
            hit = group_register(stem)
            if hit is None:
                raise ValueError(f"{name}: no {stem}_PORT/_PIN/_DDR (nor one of its group) says which port")
            found.append((pos, make(stem, stem, hit[1], n, pos)))
        elif suffix == "SHIFT" and n is not None and stem in registers and f"{stem}_MASK" in defines:
            mask = re.search(r"0x[0-9a-fA-F]+|\d+", defines[f"{stem}_MASK"][0])
            width = bin(int(mask.group(), 0)).count("1") if mask else 0
            for k in range(width):
                found.append((pos, make(stem, f"{stem}[{k}]", registers[stem], n + k, pos)))
        elif n is not None and stem in registers and suffix not in ("MASK", "SHIFT"):
            found.append((pos, make(stem, name, registers[stem], n, pos)))
    found.sort(key=lambda item: item[0])
    return [p for _, p in found]


def comment_pins(text: str) -> list[tuple[str, str]]:
    """Pins the header's comments name as ``D11 = PB5`` or ``D8 (PB0)``: ``[("D11", "PB5"), ...]``."""
    out = []
    for c in _COMMENT.finditer(text):
        out += [(m.group(1), f"P{m.group(2)}{m.group(3)}") for m in _COMMENT_PIN.finditer(c.group(1))]
    return out


def pins(src: Path | str | None = None) -> list[Pin]:
    """Every pin of both boards, from the pin headers of the firmware sources ``src`` (default the installed
    package's, :func:`rigctl.firmware.sources`): the Mega's first, each board in its header's order."""
    from rigctl import firmware

    src = Path(src) if src is not None else firmware.sources()
    out: list[Pin] = []
    for board, (header, _, _) in BOARD_HEADERS.items():
        out += parse_header((src / header).read_text(), board)
    return out
