"""The one wire specification (docs/wire-protocol.md) against both implementations: the Python constants
(rigctl/devices/wire.py) and the firmware header (arduino/common/rigctl_wire.h), row by row.

The spec's tables are parsed from the markdown (each follows a ``<!-- table: NAME -->`` marker); the header's
``#define`` lines are parsed and evaluated here, so this test needs no compiler.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from rigctl.devices import wire

REPO = Path(__file__).resolve().parents[1]
SPEC = REPO / "docs" / "wire-protocol.md"
HEADER = REPO / "arduino" / "common" / "rigctl_wire.h"


# ------------------------------------------------------------------------------------------------ parsing
def spec_tables(text: str) -> dict[str, list[dict[str, str]]]:
    """``{table name: [row as {column: cell}]}`` for every ``<!-- table: NAME -->`` markdown table."""
    tables = {}
    for m in re.finditer(r"<!--\s*table:\s*([\w-]+)\s*-->\s*\n((?:\|.*\n?)+)", text):
        lines = [ln.strip() for ln in m.group(2).strip().splitlines()]
        cells = [[c.strip() for c in ln.strip("|").split("|")] for ln in lines]
        header, rows = cells[0], [r for r in cells[1:] if not set("".join(r)) <= set("-: ")]
        tables[m.group(1)] = [dict(zip(header, r)) for r in rows]
    return tables


def spec_int(cell: str) -> int:
    cell = cell.strip().strip("`")
    return int(cell, 16) if cell.lower().startswith("0x") else int(cell.replace(",", ""))


def header_defines(text: str) -> dict[str, object]:
    """Evaluate the header's object-like ``#define`` macros (integers, chars, strings, shifts, references)."""
    raw = {}
    for m in re.finditer(r"^\s*#define\s+(\w+)\s+(.+?)\s*(?:/\*.*)?$", text, re.M):
        raw[m.group(1)] = m.group(2)
    values: dict[str, object] = {}

    def ev(name: str):
        if name in values:
            return values[name]
        expr = raw[name]
        if expr.startswith('"'):
            values[name] = expr.strip('"')
            return values[name]
        expr = re.sub(r"'(.)'", lambda m: str(ord(m.group(1))), expr)
        expr = re.sub(r"\b(0x[0-9A-Fa-f]+|\d+)(?:UL|ul|U|u|L|l)\b", r"\1", expr)
        expr = re.sub(r"\b[A-Z_][A-Z0-9_]*\b", lambda m: str(ev(m.group(0))) if m.group(0) in raw else m.group(0),
                      expr)
        values[name] = eval(expr, {"__builtins__": {}}, {})  # noqa: S307 (integer expressions of our header)
        return values[name]

    for name in raw:
        if name.endswith("_H"):
            continue
        ev(name)
    return values


@pytest.fixture(scope="module")
def tables():
    return spec_tables(SPEC.read_text())


@pytest.fixture(scope="module")
def spec_text():
    return SPEC.read_text()


@pytest.fixture(scope="module")
def h():
    return header_defines(HEADER.read_text())


def test_spec_has_every_table(tables):
    assert set(tables) == {"frame", "flags", "uno-commands", "encoder-commands", "spike-frame", "spike-flags",
                           "counts-frame", "holding", "input", "commands", "states", "command-states", "faults",
                           "reset-cause", "status-flags"}
    assert all(len(rows) >= 3 for rows in tables.values())


# ------------------------------------------------------------------------------------------------ taxel stream
def test_frame_layout(tables, spec_text, h):
    rows = {r["field"]: r for r in tables["frame"]}
    assert list(rows) == ["sync", "seq", "flags", "samples", "crc"]
    py = {"sync": wire.OFFSET_SYNC, "seq": wire.OFFSET_SEQ, "flags": wire.OFFSET_FLAGS,
          "samples": wire.OFFSET_SAMPLES, "crc": wire.OFFSET_CRC}
    end = 0
    for name, r in rows.items():
        off, size = spec_int(r["offset"]), spec_int(r["size"])
        assert off == end, f"{name} does not follow the previous field"
        end = off + size
        assert py[name] == off
        assert wire.FRAME_DTYPE.fields[name][1] == off and wire.FRAME_DTYPE.fields[name][0].itemsize == size
        assert h[f"RIGCTL_FRAME_{name.upper()}_OFFSET"] == off
        assert h[f"RIGCTL_FRAME_{name.upper()}_SIZE"] == size
    size = int(re.search(r"Frame size:\s*(\d+)\s*bytes", spec_text).group(1))
    assert end == size == wire.FRAME_SIZE == h["RIGCTL_FRAME_SIZE"] == wire.FRAME_DTYPE.itemsize
    # sync bytes, sample count, CRC coverage
    sync = [int(x, 16) for x in re.findall(r"0x([0-9A-Fa-f]{2})", rows["sync"]["meaning"])]
    assert bytes(sync) == wire.SYNC == bytes([h["RIGCTL_FRAME_SYNC0"], h["RIGCTL_FRAME_SYNC1"]])
    n = int(re.search(r"\[(\d+)\]", rows["samples"]["type"]).group(1))
    assert n == wire.N_TAXELS == h["RIGCTL_N_TAXELS"]
    a, b = map(int, re.search(r"bytes (\d+)\.\.(\d+)", rows["crc"]["meaning"]).groups())
    assert a == wire.CRC_START == h["RIGCTL_FRAME_CRC_START"] and b == wire.OFFSET_CRC - 1
    assert "0xA001" in rows["crc"]["meaning"] and "0xFFFF" in rows["crc"]["meaning"]
    assert wire.crc16(b"123456789") == 0x4B37


def test_stream_link_and_identity(spec_text, h):
    assert "**1,000,000 baud**" in spec_text and wire.TAXEL_BAUD == h["RIGCTL_TAXEL_BAUD"] == 1_000_000
    assert "**1 kHz**" in spec_text and wire.SAMPLE_RATE_HZ == h["RIGCTL_SAMPLE_RATE_HZ"] == 1000
    assert "10-bit" in spec_text and wire.ADC_BITS == h["RIGCTL_ADC_BITS"] == 10
    assert wire.ADC_MAX == h["RIGCTL_ADC_MAX"] == 1023
    major, minor = map(int, re.search(r"Uno identity: firmware version (\d+)\.(\d+)", spec_text).groups())
    assert wire.UNO_FIRMWARE_VERSION == (major, minor) == (h["RIGCTL_UNO_FW_MAJOR"], h["RIGCTL_UNO_FW_MINOR"])
    banner = re.search(r"ready banner\s*\n?\s*`(#RIGCTL-UNO READY[^`]*)`", spec_text).group(1)
    ident = re.search(r"reply `(#RIGCTL-UNO fw=[^`]*)`", spec_text).group(1)
    fw = f"{major}.{minor}"
    assert h["RIGCTL_UNO_BANNER"] == banner.replace("<major>.<minor>", fw)
    assert h["RIGCTL_UNO_IDENTITY"] == ident.replace("<major>.<minor>", fw)
    assert h["RIGCTL_UNO_BANNER"].startswith(wire.UNO_BANNER_PREFIX)
    assert h["RIGCTL_UNO_IDENTITY"].startswith(wire.UNO_IDENTITY_PREFIX)


@pytest.mark.parametrize("table, flag, prefix", [("flags", wire.FrameFlag, "RIGCTL_FLAG_"),
                                                 ("spike-flags", wire.SpikeFlag, "RIGCTL_SPIKE_FLAG_")])
def test_flags(tables, h, table, flag, prefix):
    rows = tables[table]
    assert {r["name"] for r in rows} == {f.name for f in flag}
    for r in rows:
        bit = spec_int(r["bit"])
        assert flag[r["name"]] == 1 << bit
        assert h[f"{prefix}{r['name']}_BIT"] == bit and h[f"{prefix}{r['name']}"] == 1 << bit


def test_uno_commands(tables, h):
    rows = tables["uno-commands"]
    assert {r["command"] for r in rows} == {c.name for c in wire.UnoCommand}
    for r in rows:
        byte = r["byte"].strip("`")
        assert len(byte) == 1
        assert wire.UnoCommand[r["command"]].value == byte.encode()
        assert h[f"RIGCTL_UNO_CMD_{r['command']}"] == ord(byte)


# ------------------------------------------------------------------------------------------------ encoder image
def test_encoder_commands(tables, h):
    rows = tables["encoder-commands"]
    assert {r["command"] for r in rows} == {c.name for c in wire.EncoderCommand}
    payload = {"CALIBRATE": wire.ENC_CALIBRATE_PAYLOAD, "ENCODE": 2, "SPEED": 4, "FINISH": 2}
    for r in rows:
        byte = r["byte"].strip("`")
        assert len(byte) == 1 and wire.EncoderCommand[r["command"]].value == byte.encode()
        assert h[f"RIGCTL_ENC_CMD_{r['command']}"] == ord(byte)
        if r["command"] in payload:
            assert h[f"RIGCTL_ENC_{r['command']}_PAYLOAD"] == payload[r["command"]]
    # the encoder's commands and the streamer's share one byte space
    assert not {c.value for c in wire.EncoderCommand} & {c.value for c in wire.UnoCommand}
    assert h["RIGCTL_ENC_N_TAXELS"] == wire.ENC_N_TAXELS and h["RIGCTL_ENC_N_WINDOWS"] == wire.ENC_N_WINDOWS
    # the ring ENCODE starts from (common/sa_ring.h), as the host and the banner know it
    ring = (Path(wire.__file__).parents[1] / "arduino" / "common" / "sa_ring.h").read_text()
    sizes = {m[0]: int(m[1]) for m in re.findall(r"#define (SA_RING_SAMPLES|SA_RING_SPARE) (\d+)u", ring)}
    assert sizes["SA_RING_SAMPLES"] == wire.ENC_RING_SAMPLES
    assert wire.ENC_RING_SAMPLES - sizes["SA_RING_SPARE"] == wire.ENC_RING_MAX_BACK
    assert f"ring={wire.ENC_RING_SAMPLES}" in wire.UNO_ENCODER_FIELD


@pytest.mark.parametrize("table, prefix, sync, size", [("spike-frame", "SPIKE", wire.SPIKE_SYNC, wire.SPIKE_FRAME_SIZE),
                                                       ("counts-frame", "COUNTS", wire.COUNTS_SYNC,
                                                        wire.COUNTS_FRAME_SIZE)])
def test_encoder_frames(tables, h, table, prefix, sync, size):
    rows = {r["field"]: r for r in tables[table]}
    end = 0
    for name, r in rows.items():
        off, n = spec_int(r["offset"]), spec_int(r["size"])
        assert off == end, f"{name} does not follow the previous field"
        end = off + n
        if name not in ("sync", "masks", "counts") and f"RIGCTL_{prefix}_{name.upper()}_OFFSET" in h:
            assert h[f"RIGCTL_{prefix}_{name.upper()}_OFFSET"] == off
    assert end == size == h[f"RIGCTL_{prefix}_FRAME_SIZE"]
    assert rows["crc"]["offset"] == str(h[f"RIGCTL_{prefix}_CRC_OFFSET"]) == str(size - 2)
    assert f"`0x{sync[0]:02X} 0x{sync[1]:02X}`" == rows["sync"]["meaning"]
    assert (h[f"RIGCTL_{prefix}_SYNC0"], h[f"RIGCTL_{prefix}_SYNC1"]) == (sync[0], sync[1])
    assert h[f"RIGCTL_{prefix}_CRC_START"] == 2 and f"over bytes 2..{size - 3}" in rows["crc"]["meaning"]
    if table == "spike-frame":
        assert spec_int(rows["masks"]["size"]) == 2 * wire.SPIKE_MASKS == 2 * h["RIGCTL_SPIKE_MASKS"]
        assert h["RIGCTL_SPIKE_MASKS_OFFSET"] == spec_int(rows["masks"]["offset"])
    else:
        assert spec_int(rows["counts"]["size"]) == 2 * wire.ENC_N_TAXELS * wire.ENC_N_WINDOWS
        assert h["RIGCTL_COUNTS_COUNTS_OFFSET"] == spec_int(rows["counts"]["offset"])


# ------------------------------------------------------------------------------------------------ Modbus
def test_modbus_link(spec_text, h):
    assert f"**{wire.DRUM_BAUD} baud 8N1**" in spec_text and wire.DRUM_BAUD == h["RIGCTL_DRUM_BAUD"]
    # exact at 16 MHz: the UART divides the clock by 16 x (UBRR + 1) (8 x with U2X), with no remainder
    assert 16_000_000 % (16 * wire.DRUM_BAUD) == 0 and wire.DRUM_BAUD > 19200  # t3.5 = 1.75 ms above 19200
    assert "**device id 1**" in spec_text and wire.DRUM_DEVICE_ID == h["RIGCTL_DRUM_DEVICE_ID"] == 1
    for fc, name in ((3, "READ_HOLDING"), (4, "READ_INPUT"), (6, "WRITE_SINGLE"), (16, "WRITE_MULTIPLE")):
        assert f"{fc:02d} (" in spec_text and h[f"RIGCTL_MB_FC_{name}"] == fc
    for code, name in ((1, "ILLEGAL_FUNCTION"), (2, "ILLEGAL_ADDRESS"), (3, "ILLEGAL_VALUE")):
        assert f"{code:02d} {name.lower().replace('_', ' ')}" in spec_text.replace("data ", "")
        assert h[f"RIGCTL_MB_EX_{name}"] == code
    t35 = float(re.search(r"t3\.5 silence \(([\d.]+) ms", spec_text).group(1))
    assert h["RIGCTL_MB_T35_US"] == round(t35 * 1000)
    # the host's RTU client (pymodbus) keeps the same t3.5 at the link's rate, and no inter-byte timeout above 19200
    from pymodbus.client import ModbusSerialClient

    client = ModbusSerialClient("/dev/null", baudrate=wire.DRUM_BAUD)
    assert client.silent_interval == t35 / 1000 and client.inter_byte_timeout == 0
    version = int(re.search(r"FIRMWARE_VERSION = (\d+)", spec_text).group(1))
    assert version == h["RIGCTL_MEGA_FIRMWARE_VERSION"] == (wire.MEGA_FIRMWARE_VERSION[0] << 8) | \
        wire.MEGA_FIRMWARE_VERSION[1]


def test_holding_registers(tables, h):
    rows = tables["holding"]
    assert [r["name"] for r in rows] == [r.name for r in sorted(wire.HoldingRegister)]
    span = max(spec_int(r["address"]) for r in rows) + 1  # reserved addresses inside it read 0 (spec 2)
    assert span == wire.N_HOLDING == h["RIGCTL_N_HOLDING"]
    assert wire.RESERVED_HOLDING == set(range(span)) - {spec_int(r["address"]) for r in rows}
    for r in rows:
        name, addr = r["name"], spec_int(r["address"])
        lo, hi = map(spec_int, r["range"].split("-"))
        default = spec_int(r["default"])
        assert r["type"] == "uint16"
        assert wire.HoldingRegister[name] == addr == h[f"RIGCTL_HREG_{name}"]
        assert wire.HOLDING_RANGE[wire.HoldingRegister[name]] == (lo, hi, default)
        assert (h[f"RIGCTL_HREG_{name}_MIN"], h[f"RIGCTL_HREG_{name}_MAX"], h[f"RIGCTL_HREG_{name}_DEF"]) == \
            (lo, hi, default)
        assert lo <= default <= hi
    # SPEED_LIMIT_0P1MMS is "the highest speed accepted in any speed register": the other 0.1 mm/s registers
    speed_regs = {r["name"] for r in rows if r["name"].endswith("_0P1MMS")} - {"SPEED_LIMIT_0P1MMS"}
    assert {reg.name for reg in wire.SPEED_REGISTERS} == speed_regs


def test_speed_profiles(tables, h):
    meaning = next(r["meaning"] for r in tables["holding"] if r["name"] == "SPEED_PROFILE")
    for value, name in re.findall(r"(\d+) = (\w+)", meaning):
        assert wire.SpeedProfile[name] == int(value) == h[f"RIGCTL_PROFILE_{name}"]


def test_input_registers(tables, h):
    rows = tables["input"]
    assert [r["name"] for r in rows] == [r.name for r in sorted(wire.InputRegister)]
    span = max(spec_int(r["address"]) for r in rows) + 1
    assert span == wire.N_INPUT == h["RIGCTL_N_INPUT"]
    assert wire.RESERVED_INPUT == set(range(span)) - {spec_int(r["address"]) for r in rows}
    for r in rows:
        assert wire.InputRegister[r["name"]] == spec_int(r["address"]) == h[f"RIGCTL_IREG_{r['name']}"]
    signed = {wire.InputRegister[r["name"]] for r in rows if r["type"] == "int16"}
    assert signed == set(wire.SIGNED_INPUT_REGISTERS)
    assert {r["type"] for r in rows} <= {"int16", "uint16"}


def test_build_id_registers(spec_text):
    """Spec 2.2: the 48-bit build id in BUILD_ID_0 .. _2, most significant word first (the spec's example), all zero
    = a build without one; as wide as the id rigctl's builds give the firmware."""
    from rigctl import firmware

    m = re.search(r"`([0-9a-f]{12})` reads 0x([0-9A-F]{4}), 0x([0-9A-F]{4}), 0x([0-9A-F]{4})", spec_text)
    assert m, "spec 2.2 gives an example of the build id's words"
    words = tuple(int(w, 16) for w in m.groups()[1:])
    assert wire.build_id_words(m.group(1)) == words and wire.build_id_from_words(words) == m.group(1)
    assert wire.build_id_words(None) == (0, 0, 0) and wire.build_id_from_words([0, 0, 0]) is None
    assert wire.build_id_from_words(wire.build_id_words("abc")) == "000000000abc"
    for bad in ("", "0123456789abc", "xyz", "12 4"):
        with pytest.raises(ValueError):
            wire.build_id_words(bad)
    assert [int(r) for r in wire.BUILD_ID_REGISTERS] == [wire.InputRegister[f"BUILD_ID_{i}"] for i in range(3)]
    assert wire.BUILD_ID_HEX_DIGITS == firmware.BUILD_ID_DIGITS == len(firmware.build_id())


@pytest.mark.parametrize("table,enum,prefix", [
    ("commands", wire.Command, "RIGCTL_CMD_"),
    ("states", wire.DrumState, "RIGCTL_STATE_"),
])
def test_codes(tables, h, table, enum, prefix):
    rows = tables[table]
    assert {r["name"] for r in rows} == {m.name for m in enum}
    for r in rows:
        code = spec_int(r["code"])
        assert enum[r["name"]] == code == h[prefix + r["name"]]
    # the COMMAND register's range covers exactly the command codes
    if table == "commands":
        assert wire.HOLDING_RANGE[wire.HoldingRegister.COMMAND][:2] == (0, max(spec_int(r["code"]) for r in rows))


def test_faults(tables, spec_text, h):
    rows = tables["faults"]
    assert {r["name"] for r in rows} == {f.name for f in wire.Fault}
    for r in rows:
        bit = spec_int(r["bit"])
        assert wire.Fault[r["name"]] == 1 << bit
        assert h[f"RIGCTL_FAULT_{r['name']}_BIT"] == bit and h[f"RIGCTL_FAULT_{r['name']}"] == 1 << bit
    timeout = int(re.search(r"no reading for (\d+) ms", spec_text).group(1))
    assert h["RIGCTL_LOADCELL_TIMEOUT_MS"] == timeout
    travel, home_ms = map(int, re.search(r"HOME gives up after (\d+) mm of travel towards home or (\d+) ms",
                                         spec_text).groups())
    assert (h["RIGCTL_HOME_MAX_TRAVEL_MM"], h["RIGCTL_HOME_TIMEOUT_MS"]) == (travel, home_ms) == \
        (wire.HOME_MAX_TRAVEL_MM, wire.HOME_TIMEOUT_MS)
    leave, rise = map(int, re.search(r"did not open within (\d+) um of leaving home \(HOME_LEAVE_UM, creeping\), or the "
                                     r"load cell's untared force rose more than (\d+) g", spec_text).groups())
    proof = int(re.search(r"within the leaving travel plus (\d+) mm, HOME_PROOF_MM", spec_text).group(1))
    assert (h["RIGCTL_HOME_LEAVE_UM"], h["RIGCTL_HOME_PROOF_MM"], h["RIGCTL_DIRECTION_RISE_G"]) == (leave, proof, rise) \
        == (wire.HOME_LEAVE_UM, wire.HOME_PROOF_MM, wire.DIRECTION_RISE_G)


def test_the_press_direction_watch_constants(spec_text, h):
    """Spec 2.11's press direction watch: the same readings, lag, steps, force and proof in the text, the header and
    wire.py (the model controller and the firmware use them)."""
    m = re.search(r"the step count commanded\s+over (\d+) readings \(PRESS_DIR_READINGS\).*?as many readings (\d+) "
                  r"readings\s+later \(PRESS_DIR_LAG_READINGS.*?(\d+) steps or more \(PRESS_DIR_STEPS.*?by (\d+) g "
                  r"\(PRESS_DIR_G.*?at most (\d+) readings\s+ago \(PRESS_DIR_PROOF_READINGS\)", spec_text, re.S)
    assert m is not None
    names = ("READINGS", "LAG_READINGS", "STEPS", "G", "PROOF_READINGS")
    for name, value in zip(names, map(int, m.groups())):
        assert h[f"RIGCTL_PRESS_DIR_{name}"] == getattr(wire, f"PRESS_DIR_{name}") == value, name


def test_the_back_off_proof_constants(spec_text, h):
    """Spec 2.11's back-off proof: the same step, force and number of steps in the text, the header and wire.py (the
    firmware uses them; the campaign's step-after-latch judge allows their blind travel, no more)."""
    m = re.search(r"proof steps of at most (\d+) um \(BACKOFF_PROOF_UM\) and (\d+) g.*?\(BACKOFF_PROOF_G\).*?At most\s+"
                  r"(\d+) proof steps \(BACKOFF_PROOF_TRIES\).*?at most (\d+) um", spec_text, re.S)
    assert m is not None
    step_um, force_g, tries, blind_um = map(int, m.groups())
    for name, value in (("UM", step_um), ("G", force_g), ("TRIES", tries)):
        assert h[f"RIGCTL_BACKOFF_PROOF_{name}"] == getattr(wire, f"BACKOFF_PROOF_{name}") == value, name
    assert blind_um == tries * step_um
    from rigctl.simulation.campaign import LATCH_PROOF_MM
    assert LATCH_PROOF_MM == pytest.approx(blind_um * 1e-3)


@pytest.mark.parametrize("table,flags,prefix", [
    ("reset-cause", wire.ResetCause, "RIGCTL_RESET_"),
    ("status-flags", wire.StatusFlag, "RIGCTL_STATUS_"),
])
def test_reset_cause_and_status_flags(tables, h, table, flags, prefix):
    rows = tables[table]
    assert {r["name"] for r in rows} == {f.name for f in flags}
    for r in rows:
        bit = spec_int(r["bit"])
        assert flags[r["name"]] == 1 << bit
        assert h[f"{prefix}{r['name']}_BIT"] == bit and h[f"{prefix}{r['name']}"] == 1 << bit


def test_signed_loadcell_scale(spec_text, h):
    """Spec 2.1: the 32-bit signed scale's absolute range, as the header and wire.py have it; the word split."""
    lo, hi = (int(x.replace(",", "")) for x in re.search(r"absolute value of ([\d,]+)-([\d,]+)", spec_text).groups())
    assert (lo, hi) == wire.LOADCELL_SCALE_X100_ABS_RANGE == (h["RIGCTL_LOADCELL_SCALE_X100_ABS_MIN"],
                                                           h["RIGCTL_LOADCELL_SCALE_X100_ABS_MAX"])
    for v in (42000, -42000, 430000, -1, 0, 2**31 - 1, -2**31):
        assert wire.join_s32(*wire.split_s32(v)) == v
    assert wire.split_s32(-42000) == (0xFFFF, (-42000) & 0xFFFF)


def test_the_scale_check_tolerance(spec_text, h):
    pct = int(re.search(r"\(SCALE_CHECK_PCT = (\d+):", spec_text).group(1))
    assert pct == h["RIGCTL_SCALE_CHECK_PCT"] == wire.SCALE_CHECK_PCT
    assert f"more than {pct} % (SCALE_CHECK_PCT) off" in spec_text


def test_hx711_rate_rules(spec_text, h):
    """Section 2.9's numbers in the header and wire.py; the firmware's integration band in drum_config.h."""
    periods = int(re.search(r"times\s+the first (\d+) periods", spec_text).group(1))
    tol = int(re.search(r"by more than (\d+) %", spec_text).group(1))
    band = float(re.search(r"while abs\(e\) < (\d+) g", spec_text).group(1))
    assert h["RIGCTL_HX711_RATE_PERIODS"] == periods == wire.HX711_RATE_PERIODS
    assert h["RIGCTL_HX711_RATE_TOLERANCE_PCT"] == tol == round(wire.HX711_RATE_TOLERANCE * 100)
    cfg = (REPO / "arduino" / "mega_drum" / "drum_config.h").read_text()
    assert float(re.search(r"#define FORCE_INTEGRATE_BAND_G\s+([\d.]+)f?", cfg).group(1)) == band
    lo, hi, _ = wire.HOLDING_RANGE[wire.HoldingRegister.HX711_RATE_SPS]
    assert (lo, hi) == (min(wire.HX711_RATES_SPS), max(wire.HX711_RATES_SPS))


def test_force_trip_and_contact_probe(spec_text, h):
    """Section 2.10's numbers in the header and wire.py (the firmware and the virtual Mega's force_loop use them)."""
    lead = int(re.search(r"its rise since the previous reading times (\d+) \(FORCE_LEAD_PERIODS\)", spec_text).group(1))
    travel, periods = map(int, re.search(r"approaches at\s+(\d+) um per (\d+) HX711 periods", spec_text).groups())
    contact = int(re.search(r"passes (\d+) g \(PROBE_CONTACT_G", spec_text).group(1))
    step = int(re.search(r"moves (\d+) um further \(PROBE_STEP_UM\)", spec_text).group(1))
    phase, delay = map(float, re.search(r"STIFFNESS_MAX_G_PER_MM = ([\d.]+) / \(Kp x ([\d.]+) x period\)",
                                        spec_text).groups())
    assert lead == periods == h["RIGCTL_FORCE_LEAD_PERIODS"] == wire.FORCE_LEAD_PERIODS
    assert (travel, contact, step) == (h["RIGCTL_PROBE_TRAVEL_UM"], h["RIGCTL_PROBE_CONTACT_G"],
                                       h["RIGCTL_PROBE_STEP_UM"]) == (wire.PROBE_TRAVEL_UM, wire.PROBE_CONTACT_G,
                                                                      wire.PROBE_STEP_UM)
    assert phase == h["RIGCTL_LOOP_PHASE_MRAD"] / 1000 == wire.LOOP_PHASE_RAD
    margin = int(re.search(r"up to (\d+) um before that zero-force\s+point \(PROBE_LOCATED_MARGIN_UM\)",
                           spec_text).group(1))
    assert margin == h["RIGCTL_PROBE_LOCATED_MARGIN_UM"] == wire.PROBE_LOCATED_MARGIN_UM
    assert delay == h["RIGCTL_HX711_DELAY_PERIODS_X10"] / 10 == wire.HX711_DELAY_PERIODS
    from rigctl.simulation import mega_c

    ffi, lib = mega_c.load()  # the controller's own ctl_stiffness_max (controller.c on the host), defaults from ctl_init
    c = ffi.new("ctl_t *")
    lib.ctl_init(c, 0, 0)
    at80 = lib.ctl_stiffness_max(c)
    c.hreg[wire.HoldingRegister.HX711_RATE_SPS] = 10
    at10 = lib.ctl_stiffness_max(c)
    m = re.search(r"\((\d+) g/mm at 80 SPS, (\d+) g/mm at 10 SPS with the default gains\)", spec_text)
    assert (at80, at10) == tuple(map(int, m.groups()))


def test_drum_geometry_and_index_pulse(spec_text, h):
    m = re.search(r"default diameter (\d+) mm, stepper (\d+) full steps/rev, (\d+)\s+microsteps", spec_text)
    assert m is not None
    diameter, steps, micro = map(int, m.groups())
    assert (h["RIGCTL_DRUM_DIAMETER_MM_DEF"], h["RIGCTL_DRUM_STEPS_PER_REV_DEF"], h["RIGCTL_DRUM_MICROSTEPS_DEF"]) \
        == (diameter, steps, micro)
    from rigctl.core import drum
    from rigctl.simulation.model import DrumConfig

    # the host's one home of the geometry (rigctl.core.drum) and the simulated rig's defaults
    assert (drum.DRUM_DIAMETER_MM, drum.DRUM_STEPS_PER_REV, drum.DRUM_MICROSTEPS) == (diameter, steps, micro)
    d = DrumConfig()
    assert (d.diameter_mm, d.steps_per_rev, d.microsteps) == (diameter, steps, micro)
    pulse = int(re.search(r"raises its index output for (\d+) ms", spec_text).group(1))
    assert h["RIGCTL_INDEX_PULSE_MS"] == pulse
    # the firmware's own config header takes its geometry from these defaults
    cfg = (REPO / "arduino" / "mega_drum" / "drum_config.h").read_text()
    assert re.search(r"#define DRUM_DIAMETER_MM\s+\(\(float\)RIGCTL_DRUM_DIAMETER_MM_DEF\)", cfg)
    assert "RIGCTL_DRUM_STEPS_PER_REV_DEF" in cfg and "RIGCTL_DRUM_MICROSTEPS_DEF" in cfg


def test_header_and_python_frame_builders_agree():
    """The header's layout constants build the same bytes as rigctl.devices.frames (no compiler needed)."""
    from rigctl.devices.frames import encode_frame

    h = header_defines(HEADER.read_text())
    samples = np.arange(18) * 50 + 7
    out = bytearray(h["RIGCTL_FRAME_SIZE"])
    out[0], out[1] = h["RIGCTL_FRAME_SYNC0"], h["RIGCTL_FRAME_SYNC1"]
    o = h["RIGCTL_FRAME_SEQ_OFFSET"]
    out[o:o + 2] = (513).to_bytes(2, "little")
    out[h["RIGCTL_FRAME_FLAGS_OFFSET"]] = h["RIGCTL_FLAG_SYNC_IN"] | h["RIGCTL_FLAG_STREAMING_START"]
    o = h["RIGCTL_FRAME_SAMPLES_OFFSET"]
    out[o:o + 36] = np.asarray(samples, "<u2").tobytes()
    crc = wire.crc16(out[h["RIGCTL_FRAME_CRC_START"]:h["RIGCTL_FRAME_CRC_OFFSET"]])
    out[h["RIGCTL_FRAME_CRC_OFFSET"]:] = crc.to_bytes(2, "little")
    assert bytes(out) == encode_frame(513, 0x09, samples)


def test_frame_size_for_any_channel_count(spec_text, h):
    """Section 1.4: the channel count comes from the banner; frame size 7 + 2*ch, CRC over bytes 2..4+2*ch. The
    firmware's 18 channels are the same formula, and the host reads a banner with a layout as the spec says."""
    m = re.search(r"Frame size for ch channels: (\d+) \+ (\d+) \* ch bytes", spec_text)
    assert m is not None
    base, per = map(int, m.groups())
    a, b = map(int, re.search(r"the CRC covers\s+bytes (\d+) \.\. (\d+) \+ (\d+) \* ch", spec_text).groups()[:2])
    assert (base, per, a, b) == (wire.FRAME_OVERHEAD, 2, wire.CRC_START, wire.OFFSET_SAMPLES - 1)
    assert base + per * h["RIGCTL_N_TAXELS"] == h["RIGCTL_FRAME_SIZE"] == wire.FRAME_SIZE
    for ch in (1, 9, 16, 18, 64):
        assert wire.frame_size(ch) == base + per * ch == wire.frame_dtype(ch).itemsize
        assert wire.offset_crc(ch) == wire.frame_size(ch) - 2 == b + per * ch + 1
    from rigctl.devices.taxel_stream import layout_from_banner, parse_identity

    line = re.search(r"Example banner of a 9-taxel board at 100 Hz: `([^`]*)`", spec_text.replace("\n", " "))
    banner = parse_identity(line.group(1))
    layout = layout_from_banner(banner)
    assert (banner["ch"], layout.n_channels, layout.sample_rate_hz, layout.adc_bits, layout.shape_text) == \
        (9, 9, 100.0, 10, "3x3x1")
    paper = layout_from_banner(parse_identity(h["RIGCTL_UNO_BANNER"]))
    assert (paper.n_channels, paper.sample_rate_hz, paper.adc_bits, paper.shape_text) == (18, 1000.0, 10, "3x3x2")
