"""Wire-protocol constants of the rig's two boards, as written in ``docs/wire-protocol.md``.

This module holds numbers only (frame layout, flags, commands, the Modbus register map, CRC-16); the framing code
lives in :mod:`rigctl.devices.frames`. ``tests/test_wire_spec.py`` checks every value here, and the firmware header
``arduino/common/rigctl_wire.h``, against the tables of the spec document.
"""

from __future__ import annotations

import enum
import re
from collections.abc import Sequence
from typing import Any

import numba
import numpy as np

# the controller's states, fault bits and speed profiles are shared by every layer: they live in rigctl.core.drum
# (the numbers of spec tables 2.4 and 2.5, checked here by tests/test_wire_spec.py); re-exported as the spec's names
from rigctl.core.drum import (
    CONTACT_STIFFNESS_MAX_G_PER_MM as CONTACT_STIFFNESS_MAX_G_PER_MM,
    SCALE_CHECK_PCT as SCALE_CHECK_PCT,
    DrumState as DrumState,
    Fault as Fault,
    ResetCause as ResetCause,
    SpeedProfile as SpeedProfile,
    StatusFlag as StatusFlag,
)
from rigctl.core.sensor import PAPER_SENSOR

# --------------------------------------------------------------------------------------------------------------
# Taxel stream (Uno -> host), spec section 1
# --------------------------------------------------------------------------------------------------------------
TAXEL_BAUD = 1_000_000
#: the Uno firmware's channel count, rate and resolution (the host reads a link's own from its banner)
N_TAXELS = PAPER_SENSOR.n_channels  # 18: the Uno firmware streams the paper's sensor
N_TAXELS_PER_LAYER = len(PAPER_SENSOR.layer_channels(0))  # 9
SAMPLE_RATE_HZ = int(PAPER_SENSOR.sample_rate_hz)  # 1000
ADC_BITS = PAPER_SENSOR.adc_bits  # 10
ADC_MAX = (1 << ADC_BITS) - 1

SYNC = b"\xa5\x5a"
OFFSET_SYNC = 0
OFFSET_SEQ = 2
OFFSET_FLAGS = 4
OFFSET_SAMPLES = 5
OFFSET_CRC = OFFSET_SAMPLES + 2 * N_TAXELS  # 41
FRAME_SIZE = OFFSET_CRC + 2  # 43
CRC_START = OFFSET_SEQ  # the CRC covers bytes CRC_START..OFFSET_CRC-1

#: bytes of a frame that are not samples (sync 2, seq 2, flags 1, crc 2)
FRAME_OVERHEAD = OFFSET_SAMPLES + 2


def frame_size(n_channels: int = N_TAXELS) -> int:
    """Bytes of a frame carrying ``n_channels`` samples: ``7 + 2 * n_channels`` (43 for the Uno's 18).

    The channel count of a link comes from the board's banner / identify reply (``ch=``, spec section 1.3); the
    layout of a frame is the same for every count (spec table 1.1 with ``samples`` = ``uint16[ch]``).
    Raises ValueError for fewer than 1 channel.
    """
    n = int(n_channels)
    if n < 1:
        raise ValueError(f"a frame carries at least one channel, got {n_channels}")
    return FRAME_OVERHEAD + 2 * n


def offset_crc(n_channels: int = N_TAXELS) -> int:
    """Offset of the CRC in a frame of ``n_channels`` samples: ``5 + 2 * n_channels`` (41 for 18)."""
    return frame_size(n_channels) - 2


_FRAME_DTYPES: dict[int, np.dtype] = {}


def frame_dtype(n_channels: int = N_TAXELS) -> np.dtype[Any]:
    """numpy record type of one frame of ``n_channels`` samples, little-endian, packed (cached)."""
    n = int(n_channels)
    dt = _FRAME_DTYPES.get(n)
    if dt is None:
        frame_size(n)
        dt = np.dtype([("sync", "u1", (2,)), ("seq", "<u2"), ("flags", "u1"), ("samples", "<u2", (n,)),
                       ("crc", "<u2")])
        _FRAME_DTYPES[n] = dt
    return dt


#: numpy record type of one frame, little-endian, packed: view a ``bytes`` buffer with it.
FRAME_DTYPE = frame_dtype(N_TAXELS)
assert FRAME_DTYPE.itemsize == FRAME_SIZE == frame_size(N_TAXELS)


class FrameFlag(enum.IntFlag):
    """Bits of a frame's flags byte (spec table 1.2)."""

    SYNC_IN = 1 << 0
    ADC_OVERRUN = 1 << 1
    TX_OVERRUN = 1 << 2
    STREAMING_START = 1 << 3


class UnoCommand(bytes, enum.Enum):
    """Single-byte host -> Uno commands (spec table 1.3)."""

    START = b"S"
    STOP = b"P"
    IDENTIFY = b"I"


class EncoderCommand(bytes, enum.Enum):
    """Host -> Uno commands of the encoder image (spec table 1.5): CALIBRATE, ENCODE, SPEED and FINISH carry a payload
    and its CRC-16 (:mod:`rigctl.devices.encoder_stream` builds them)."""

    CALIBRATE = b"C"
    ARM = b"A"
    ENCODE = b"E"
    SPEED = b"V"
    FINISH = b"F"


class SpikeFlag(enum.IntFlag):
    """Bits of a spike frame's flags byte (spec 1.5)."""

    HELD = 1 << 0
    DROPPED = 1 << 1
    SYNC_IN = 1 << 2


#: the encoder image's frames (spec 1.5): spike frames beside the taxel frames while encoding, a counts frame at
#: FINISH; both CRC-16/MODBUS over their bytes 2 .. size - 3
SPIKE_SYNC = b"\xa5\xc3"
SPIKE_MASKS = 10
SPIKE_FRAME_SIZE = 6 + 2 * SPIKE_MASKS + 2  # 28
COUNTS_SYNC = b"\xa5\xc4"
ENC_N_TAXELS = 9
ENC_N_WINDOWS = 20
#: CALIBRATE's payload (the 9 minima, the 9 maxima and k, uint16 each): the longest a command of the board waits for
ENC_CALIBRATE_PAYLOAD = 2 * (2 * ENC_N_TAXELS + 1)
COUNTS_FRAME_SIZE = 11 + 2 * ENC_N_TAXELS * ENC_N_WINDOWS + 2  # 373
#: the encoder image's banner and identity carry this field (the ring of samples that ENCODE starts from: ARM's)
UNO_ENCODER_FIELD = "encoder=sa_fixed ring=32"
#: samples the encoder image's ring holds (common/sa_ring.h SA_RING_SAMPLES), and the furthest back ENCODE may start
#: from the newest (SA_RING_MAX_BACK: the rest is room while the encoder catches up)
ENC_RING_SAMPLES = 32
ENC_RING_MAX_BACK = 28

UNO_BANNER_PREFIX = "#RIGCTL-UNO READY"
UNO_IDENTITY_PREFIX = "#RIGCTL-UNO"
UNO_FIRMWARE_VERSION = (1, 0)

# --------------------------------------------------------------------------------------------------------------
# Drum controller (Mega), Modbus RTU, spec section 2
# --------------------------------------------------------------------------------------------------------------
DRUM_BAUD = 500_000
DRUM_DEVICE_ID = 1
MEGA_FIRMWARE_VERSION = (1, 9)


class HoldingRegister(enum.IntEnum):
    """Holding register addresses (spec table 2.1); units are in the names."""

    SPEED_SETPOINT_0P1MMS = 0
    FORCE_SETPOINT_G = 1
    COMMAND = 2
    SPEED_PROFILE = 3
    RAMP_START_SPEED_0P1MMS = 4
    RAMP_END_SPEED_0P1MMS = 5
    RAMP_DURATION_MS = 6
    SPEED_LIMIT_0P1MMS = 7
    FORCE_LIMIT_G = 8
    FORCE_TOLERANCE_G = 9
    SETTLE_TIME_MS = 10
    WATCHDOG_MS = 11
    LOADCELL_SCALE_X100 = 12
    ACTUATOR_STEPS_PER_MM = 13
    LOADCELL_SCALE_X100_HI = 14
    LOADCELL_SCALE_X100_LO = 15
    CALIBRATION_STIFFNESS_G_PER_MM = 16
    HX711_RATE_SPS = 20
    FORCE_KP_80SPS_NMS_G = 21
    FORCE_KI_80SPS_NMS_GS = 22
    FORCE_KP_10SPS_NMS_G = 23
    FORCE_KI_10SPS_NMS_GS = 24


#: (min, max, default) of every holding register, spec table 2.1.
HOLDING_RANGE: dict[HoldingRegister, tuple[int, int, int]] = {
    HoldingRegister.SPEED_SETPOINT_0P1MMS: (0, 2000, 0),
    HoldingRegister.FORCE_SETPOINT_G: (0, 2000, 0),
    HoldingRegister.COMMAND: (0, 8, 0),
    HoldingRegister.SPEED_PROFILE: (0, 1, 0),
    HoldingRegister.RAMP_START_SPEED_0P1MMS: (0, 2000, 400),
    HoldingRegister.RAMP_END_SPEED_0P1MMS: (0, 2000, 1200),
    HoldingRegister.RAMP_DURATION_MS: (1, 60000, 3000),
    HoldingRegister.SPEED_LIMIT_0P1MMS: (0, 2000, 1500),
    HoldingRegister.FORCE_LIMIT_G: (0, 2000, 1500),
    HoldingRegister.FORCE_TOLERANCE_G: (1, 500, 15),
    HoldingRegister.SETTLE_TIME_MS: (0, 10000, 300),
    HoldingRegister.WATCHDOG_MS: (100, 10000, 1000),
    HoldingRegister.LOADCELL_SCALE_X100: (1, 65535, 42000),
    HoldingRegister.ACTUATOR_STEPS_PER_MM: (1, 65535, 400),
    HoldingRegister.LOADCELL_SCALE_X100_HI: (0, 65535, 0),
    HoldingRegister.LOADCELL_SCALE_X100_LO: (0, 65535, 42000),
    HoldingRegister.CALIBRATION_STIFFNESS_G_PER_MM: (0, 5000, 0),
    HoldingRegister.HX711_RATE_SPS: (10, 80, 80),
    HoldingRegister.FORCE_KP_80SPS_NMS_G: (0, 20000, 10000),
    HoldingRegister.FORCE_KI_80SPS_NMS_GS: (0, 20000, 10000),
    HoldingRegister.FORCE_KP_10SPS_NMS_G: (0, 2000, 1200),
    HoldingRegister.FORCE_KI_10SPS_NMS_GS: (0, 2000, 600),
}

#: the signed 32-bit load-cell scale (LOADCELL_SCALE_X100_HI/_LO, counts per g x 100): its absolute value's range
LOADCELL_SCALE_X100_ABS_RANGE = (100, 10_000_000)


def split_s32(value: int) -> tuple[int, int]:
    """A signed 32-bit value as its (high, low) uint16 register words (two's complement)."""
    v = int(value) & 0xFFFFFFFF
    return v >> 16, v & 0xFFFF


def join_s32(high: int, low: int) -> int:
    """The signed 32-bit value of (high, low) uint16 register words."""
    v = ((int(high) & 0xFFFF) << 16) | (int(low) & 0xFFFF)
    return v - (1 << 32) if v & 0x80000000 else v

#: holding registers whose value must not exceed the value of another holding register
SPEED_REGISTERS = (
    HoldingRegister.SPEED_SETPOINT_0P1MMS,
    HoldingRegister.RAMP_START_SPEED_0P1MMS,
    HoldingRegister.RAMP_END_SPEED_0P1MMS,
)


class InputRegister(enum.IntEnum):
    """Input register addresses (spec table 2.2); units are in the names."""

    FORCE_G = 0
    SPEED_0P1MMS = 1
    DRUM_ANGLE_0P01DEG = 2
    DRUM_REVOLUTIONS = 3
    ACTUATOR_POSITION_0P01MM = 4
    STATE = 5
    FAULT_BITS = 6
    FIRMWARE_VERSION = 7
    HEARTBEAT = 8
    SPEED_TARGET_0P1MMS = 9
    LOADCELL_RAW_HI = 10
    LOADCELL_RAW_LO = 11
    FORCE_SETPOINT_ACTIVE_G = 12
    RESET_CAUSE = 13
    BOOT_COUNT = 14
    STATUS_FLAGS = 15
    FAULT_BITS_HI = 16
    HX711_RATE_0P01SPS = 20
    INDEX_SOURCE = 21
    INDEX_PERIOD_MS = 22
    INDEX_STEPS = 23
    INDEX_COUNT = 24
    MARK_PERIOD_0P1MS = 25
    MARK_STEPS = 26
    MARK_COUNT = 27
    CONTACT_STIFFNESS_G_PER_MM = 28
    STIFFNESS_MAX_G_PER_MM = 29
    BUILD_ID_0 = 30
    BUILD_ID_1 = 31
    BUILD_ID_2 = 32


#: input registers holding two's-complement values
SIGNED_INPUT_REGISTERS = frozenset(
    {InputRegister.FORCE_G, InputRegister.SPEED_0P1MMS, InputRegister.ACTUATOR_POSITION_0P01MM}
)

#: registers in each table's span (0 .. highest address); addresses inside it that the spec does not list are
#: reserved: they read 0 and accept only 0 (spec section 2)
N_HOLDING = max(HoldingRegister) + 1
N_INPUT = max(InputRegister) + 1
RESERVED_HOLDING = frozenset(range(N_HOLDING)) - set(HoldingRegister)
RESERVED_INPUT = frozenset(range(N_INPUT)) - set(InputRegister)


#: the build id's input registers, most significant word first (spec 2.2), and its width in hex digits
BUILD_ID_REGISTERS = (InputRegister.BUILD_ID_0, InputRegister.BUILD_ID_1, InputRegister.BUILD_ID_2)
BUILD_ID_HEX_DIGITS = 4 * len(BUILD_ID_REGISTERS)  # 12


def build_id_words(build_id: str | None) -> tuple[int, ...]:
    """The BUILD_ID_0 .. _2 register values (most significant first) of a build id of up to 12 hex digits (spec 2.2);
    None -> zeros (a build without an id). Raises ValueError for anything else."""
    if build_id is None:
        return (0,) * len(BUILD_ID_REGISTERS)
    if not re.fullmatch(rf"[0-9a-fA-F]{{1,{BUILD_ID_HEX_DIGITS}}}", build_id):
        raise ValueError(f"a build id is 1-{BUILD_ID_HEX_DIGITS} hex digits, got {build_id!r}")
    value = int(build_id, 16)
    return tuple((value >> (16 * i)) & 0xFFFF for i in reversed(range(len(BUILD_ID_REGISTERS))))


def build_id_from_words(words: Sequence[int]) -> str | None:
    """The build id (12 lower-case hex digits) in BUILD_ID_0 .. _2 (spec 2.2), or None when all three are 0 (a build
    without an id: a plain make, the Arduino IDE)."""
    value = 0
    for w in words:
        value = (value << 16) | (int(w) & 0xFFFF)
    return f"{value:0{BUILD_ID_HEX_DIGITS}x}" if value else None


def holding_range(address: int) -> tuple[int, int, int]:
    """(min, max, default) of any address of the holding span: a reserved one is (0, 0, 0)."""
    return HOLDING_RANGE.get(HoldingRegister(address), (0, 0, 0)) if address not in RESERVED_HOLDING else (0, 0, 0)


#: the HX711 rates the firmware knows (spec 2.9), and how far the measured rate may be from HX711_RATE_SPS
HX711_RATES_SPS = (10, 80)
HX711_RATE_TOLERANCE = 0.2
HX711_RATE_PERIODS = 4  #: periods between DOUT-ready edges the firmware times at boot


class Command(enum.IntEnum):
    """Codes written to the COMMAND holding register (spec table 2.3)."""

    NONE = 0
    RUN = 1
    STOP = 2
    TARE = 3
    HOME = 4
    CLEAR_FAULT = 5
    PRESS = 6
    STOP_DRUM = 7
    SAVE_CALIBRATION = 8


#: HOME gives up (HOME_NOT_FOUND) after this much travel towards home, mm, or this long, ms (spec 2.5)
HOME_MAX_TRAVEL_MM = 25
HOME_TIMEOUT_MS = 10000
#: HOME's direction proof: the switch must open within this travel when leaving home (spec 2.5, ACTUATOR_DIRECTION)
HOME_PROOF_MM = 2
#: HOME leaves the closed switch creeping (HOME_CREEP_UM per HX711 period, the load watched at HOME_RISE_G) and the
#: switch must open within this travel, um, before any fast move (spec 2.5, issue 75: a switch stuck closed walked the
#: actuator 2 mm into the sensor at 3 mm/s on every acknowledged HOME)
HOME_LEAVE_UM = 1500
#: ACTUATOR_DIRECTION: an untared force rise above the lowest reading since HOME or a back-off began, g (spec 2.5)
DIRECTION_RISE_G = 150

#: resets that cost the RAM (spec 2.7): BOOT_COUNT's EEPROM part counts them; the others count in RAM
COLD_RESETS = ResetCause.POWER_ON | ResetCause.BROWN_OUT


def boot_count_register(cold_boots: int, warm_resets: int) -> int:
    """BOOT_COUNT (spec 2.7) from the cold boots the EEPROM counts and the warm resets since the last (RAM): high
    byte and low byte, each wrapping at 256; a low byte of 0 is a cold boot."""
    return ((cold_boots & 0xFF) << 8) | (warm_resets & 0xFF)


def boot_count_after(boot_count: int, cause: ResetCause | int) -> int:
    """The BOOT_COUNT a controller reports after a reset of ``cause`` when it reported ``boot_count`` before
    (:func:`boot_count_register`; a cold reset, :data:`COLD_RESETS`, only when the MCU saw its flag)."""
    if ResetCause(cause) & COLD_RESETS:
        return boot_count_register((boot_count >> 8) + 1, 0)
    return boot_count_register(boot_count >> 8, boot_count + 1)


#: spec 2.10: the over-force trip extrapolates the last period's rise over this many HX711 periods
FORCE_LEAD_PERIODS = 3
#: the contact probe of the first press after a reset: contact at this force, g; approach speed: this travel, um,
#: per FORCE_LEAD_PERIODS; the measuring step, um
PROBE_CONTACT_G = 50
#: the force the probe's approach may add at the stiffest contact a rig config accepts
#: (rigctl.core.drum.CONTACT_STIFFNESS_MAX_G_PER_MM) before a reading can show it, g: the approach's travel per
#: FORCE_LEAD_PERIODS is derived from both (issue 75)
PROBE_BLIND_G = 500
PROBE_TRAVEL_UM = int(PROBE_BLIND_G * 1000 // CONTACT_STIFFNESS_MAX_G_PER_MM)
PROBE_STEP_UM = 20
#: the contact travel :func:`probe_time_s` allows for, mm (the simulated rigs' gap is 3 mm)
PROBE_ALLOWANCE_TRAVEL_MM = 5.0


def probe_time_s(hx711_rate_sps: float, travel_mm: float = PROBE_ALLOWANCE_TRAVEL_MM) -> float:
    """What the first press after a reset spends on its contact probe (spec 2.10) beyond a plain press, at most, s:
    ``travel_mm`` to the contact at the probe's speed plus two settles of HX711_RATE_PERIODS + 1 readings (a host
    adds it to its settle timeout; 16 s at 10 SPS, 2 s at 80 SPS)."""
    period = 1.0 / hx711_rate_sps if hx711_rate_sps > 0 else 0.1
    speed_mm_s = PROBE_TRAVEL_UM * 1e-3 / (FORCE_LEAD_PERIODS * period)
    return travel_mm / speed_mm_s + 2 * (HX711_RATE_PERIODS + 1) * period


#: spec 2.11 (firmware 1.2): travel past the probed contact's zero-force point is bounded by (FORCE_LIMIT_G +
#: POSITION_MARGIN_G) / k (POSITION_LIMIT); the probe's second step presses PROBE_REFINE_G more to measure k; this many
#: identical raw readings in a row latch HX711_STUCK; a DOUT-ready edge sooner than HX711_CADENCE_PCT % of the
#: measured period latches HX711_CADENCE; HOME from an unknown position creeps HOME_CREEP_UM per HX711 period until
#: |raw - zero| fell by HOME_PROOF_FALL_G (the direction proven by the force), and a rise of HOME_RISE_G of it stops
#: HOME (ACTUATOR_DIRECTION)
POSITION_MARGIN_G = 100
#: a press to a contact an earlier probe located (kept across a release until HOME, a fault or a reset) approaches at
#: the loop's clamp speed up to this far before its zero-force point, um, then probes from there (the stiffness and
#: the zero-force point measured again at every press)
PROBE_LOCATED_MARGIN_UM = 300
PROBE_REFINE_G = 100
HX711_STUCK_READINGS = 6
#: the press's direction watch (spec 2.11, the firmware's RIGCTL_PRESS_DIR_*): while the force loop drives, the step
#: count commanded over PRESS_DIR_READINGS readings (monotone, at least PRESS_DIR_STEPS) and the force read over the
#: same span PRESS_DIR_LAG_READINGS later (the HX711's sinc filter and the reading's age lag the motion by ~2 periods)
#: moving apart by PRESS_DIR_G is ACTUATOR_DIRECTION; moving together by PRESS_DIR_G proves the way a back-off takes.
#: 8 steps = 20 um of the lead screw (400 steps/mm): at the softest contact accepted (250 g/mm) 5 g, 50 x the HX711's
#: noise (20-40 counts at 420 counts/g: ~0.1 g); PRESS_DIR_G = 3 g is 30 x that noise and under the 5 g the softest
#: contact gives for the smallest decisive move
PRESS_DIR_READINGS = 4
PRESS_DIR_LAG_READINGS = 2
PRESS_DIR_STEPS = 16
PRESS_DIR_PROOF_READINGS = 2
PRESS_DIR_G = 8
HX711_CADENCE_PCT = 50
#: a back-off under load proves its way first (spec 2.11): steps of at most BACKOFF_PROOF_UM (and BACKOFF_PROOF_G of
#: spring force at the contact's stiffness), each held until the HX711 settled on it, at most BACKOFF_PROOF_TRIES of
#: them: the blind travel towards the sensor on a reversed motor is at most TRIES x UM (32 um; 160 g at the stiffest
#: contact accepted, where the first step already shows 40 g)
BACKOFF_PROOF_UM = 8
BACKOFF_PROOF_G = 40
BACKOFF_PROOF_TRIES = 4
HOME_CREEP_UM = 12
HOME_PROOF_FALL_G = 50
HOME_RISE_G = 30
#: the HX711's line codes (spec 2.11): the saturation codes latch HX711_LINE at once, the all-zero and all-one
#: words (a clock line that never clocks, a data line stuck) when read twice in a row
HX711_SATURATION_CODES = (0x7FFFFF, -0x800000)
HX711_LINE_CODES = (0x000000, -1)

#: the stiffest contact accepted: LOOP_PHASE_RAD / (Kp x HX711_DELAY_PERIODS x the HX711 period)
LOOP_PHASE_RAD = 0.75
HX711_DELAY_PERIODS = 2.5


# --------------------------------------------------------------------------------------------------------------
# CRC-16/MODBUS (used by both boards)
# --------------------------------------------------------------------------------------------------------------
def _crc_table() -> np.ndarray:
    table = np.zeros(256, dtype=np.uint16)
    for i in range(256):
        crc = i
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
        table[i] = crc
    return table


CRC16_TABLE = _crc_table()


def crc16(data: bytes | bytearray | memoryview) -> int:
    """CRC-16/MODBUS (reflected poly 0xA001, init 0xFFFF) of ``data``; returns an int 0-65535.

    ``crc16(b"123456789") == 0x4B37`` (the catalogue check value).
    """
    crc = 0xFFFF
    table = CRC16_TABLE
    for byte in bytes(data):
        crc = (crc >> 8) ^ int(table[(crc ^ byte) & 0xFF])
    return crc


def crc16_rows(rows: np.ndarray) -> np.ndarray:
    """Vectorised CRC-16/MODBUS of each row of ``rows``: ``(n, m) uint8`` -> ``(n,) uint16``.

    A numba kernel (table-driven, one pass over the bytes); the frame parser checks a whole chunk's frames at once.
    """
    rows = np.ascontiguousarray(rows, dtype=np.uint8)
    if rows.ndim != 2:
        raise ValueError(f"rows must be 2-D (n, m) uint8, got shape {rows.shape}")
    return np.asarray(_crc16_rows_kernel(rows, CRC16_TABLE))


@numba.njit(cache=True, nogil=True)
def _crc16_rows_kernel(rows: Any, table: Any) -> Any:  # pragma: no cover - compiled
    n, m = rows.shape
    out = np.empty(n, dtype=np.uint16)
    for i in range(n):
        crc = np.uint16(0xFFFF)
        for j in range(m):
            crc = (crc >> np.uint16(8)) ^ table[(crc ^ rows[i, j]) & np.uint16(0xFF)]
        out[i] = crc
    return out
