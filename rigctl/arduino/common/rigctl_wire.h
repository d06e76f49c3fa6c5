/*
 * rigctl_wire.h - the wire protocols of docs/wire-protocol.md as C constants (both boards, host tests, harness).
 *
 * docs/wire-protocol.md is the one specification; tests/test_wire_spec.py parses its tables and checks every
 * RIGCTL_* constant below against them (and rigctl/devices/wire.py). Change the spec first, then this header.
 * Naming: RIGCTL_<TABLE>_<NAME> where <TABLE> is FRAME, FLAG, UNO_CMD, HREG, IREG, CMD, STATE, FAULT.
 */
#ifndef RIGCTL_WIRE_H
#define RIGCTL_WIRE_H

/* ---- 1. Taxel stream (Uno -> host) ---------------------------------------------------------------------- */
#define RIGCTL_TAXEL_BAUD            1000000UL
#define RIGCTL_N_TAXELS              18
#define RIGCTL_N_TAXELS_PER_LAYER    9
#define RIGCTL_SAMPLE_RATE_HZ        1000
#define RIGCTL_ADC_BITS              10
#define RIGCTL_ADC_MAX               1023

/* 1.1 frame layout: offset and size of each field (bytes) */
#define RIGCTL_FRAME_SYNC0           0xA5
#define RIGCTL_FRAME_SYNC1           0x5A
#define RIGCTL_FRAME_SYNC_OFFSET     0
#define RIGCTL_FRAME_SYNC_SIZE       2
#define RIGCTL_FRAME_SEQ_OFFSET      2
#define RIGCTL_FRAME_SEQ_SIZE        2
#define RIGCTL_FRAME_FLAGS_OFFSET    4
#define RIGCTL_FRAME_FLAGS_SIZE      1
#define RIGCTL_FRAME_SAMPLES_OFFSET  5
#define RIGCTL_FRAME_SAMPLES_SIZE    36
#define RIGCTL_FRAME_CRC_OFFSET      41
#define RIGCTL_FRAME_CRC_SIZE        2
#define RIGCTL_FRAME_SIZE            43
/* the CRC covers bytes RIGCTL_FRAME_CRC_START .. RIGCTL_FRAME_CRC_OFFSET-1 */
#define RIGCTL_FRAME_CRC_START       2

/* 1.2 flags (bit numbers; the masks are 1 << bit) */
#define RIGCTL_FLAG_SYNC_IN_BIT          0
#define RIGCTL_FLAG_ADC_OVERRUN_BIT      1
#define RIGCTL_FLAG_TX_OVERRUN_BIT       2
#define RIGCTL_FLAG_STREAMING_START_BIT  3
#define RIGCTL_FLAG_SYNC_IN              (1u << RIGCTL_FLAG_SYNC_IN_BIT)
#define RIGCTL_FLAG_ADC_OVERRUN          (1u << RIGCTL_FLAG_ADC_OVERRUN_BIT)
#define RIGCTL_FLAG_TX_OVERRUN           (1u << RIGCTL_FLAG_TX_OVERRUN_BIT)
#define RIGCTL_FLAG_STREAMING_START      (1u << RIGCTL_FLAG_STREAMING_START_BIT)

/* 1.3 host -> Uno commands (single ASCII bytes) */
#define RIGCTL_UNO_CMD_START         'S'
#define RIGCTL_UNO_CMD_STOP          'P'
#define RIGCTL_UNO_CMD_IDENTIFY      'I'

#define RIGCTL_UNO_FW_MAJOR          1
#define RIGCTL_UNO_FW_MINOR          0
/* the banner and the identity reply, without the trailing "\n" */
#define RIGCTL_UNO_BANNER   "#RIGCTL-UNO READY fw=1.0 ch=18 rate_hz=1000 bits=10 baud=1000000"
#define RIGCTL_UNO_IDENTITY "#RIGCTL-UNO fw=1.0 ch=18 rate_hz=1000 bits=10 baud=1000000"

/* 1.5 the on-board encoder image (uno_encoder): host -> Uno commands with a payload (little-endian) and a CRC-16 of
 * the payload, and the two frames it sends while encoding instead of the taxel frames */
#define RIGCTL_ENC_CMD_CALIBRATE     'C'   /* + 9 x uint16 minimum, 9 x uint16 maximum, uint16 k, crc */
#define RIGCTL_ENC_CMD_ARM           'A'   /* a new scan: its samples into the board's ring (sample 0 = the first) */
#define RIGCTL_ENC_CMD_ENCODE        'E'   /* + uint16 sample since ARM to encode from, crc: spike frames from it */
#define RIGCTL_ENC_CMD_SPEED         'V'   /* + uint16 window, uint16 speed (0.01 mm/s), crc */
#define RIGCTL_ENC_CMD_FINISH        'F'   /* + uint16 speed (0.01 mm/s), crc */
#define RIGCTL_ENC_CALIBRATE_PAYLOAD 38
#define RIGCTL_ENC_SPEED_PAYLOAD     4
#define RIGCTL_ENC_FINISH_PAYLOAD    2
#define RIGCTL_ENC_ENCODE_PAYLOAD    2
#define RIGCTL_ENC_N_TAXELS          9
#define RIGCTL_ENC_N_WINDOWS         20
/* spike frame: sync, seq of its first sample, n samples (1-10), flags, 10 x uint16 spike masks, crc over 2..25 */
#define RIGCTL_SPIKE_SYNC0           0xA5
#define RIGCTL_SPIKE_SYNC1           0xC3
#define RIGCTL_SPIKE_SEQ_OFFSET      2
#define RIGCTL_SPIKE_N_OFFSET        4
#define RIGCTL_SPIKE_FLAGS_OFFSET    5
#define RIGCTL_SPIKE_MASKS_OFFSET    6
#define RIGCTL_SPIKE_MASKS           10
#define RIGCTL_SPIKE_CRC_OFFSET      26
#define RIGCTL_SPIKE_FRAME_SIZE      28
#define RIGCTL_SPIKE_CRC_START       2
#define RIGCTL_SPIKE_FLAG_HELD_BIT    0  /* a window was scaled with the last speed since the previous spike frame */
#define RIGCTL_SPIKE_FLAG_DROPPED_BIT 1  /* a sample was dropped (the encoder's ring was full) since then */
#define RIGCTL_SPIKE_FLAG_SYNC_IN_BIT 2  /* a sync-in edge was latched since then */
#define RIGCTL_SPIKE_FLAG_HELD        (1u << RIGCTL_SPIKE_FLAG_HELD_BIT)
#define RIGCTL_SPIKE_FLAG_DROPPED     (1u << RIGCTL_SPIKE_FLAG_DROPPED_BIT)
#define RIGCTL_SPIKE_FLAG_SYNC_IN     (1u << RIGCTL_SPIKE_FLAG_SYNC_IN_BIT)
/* counts frame (after FINISH): sync, samples uint32, held uint16, dropped uint16, queue_max uint8,
 * counts uint16[9][20] (taxel-major), crc over 2..370 */
#define RIGCTL_COUNTS_SYNC0          0xA5
#define RIGCTL_COUNTS_SYNC1          0xC4
#define RIGCTL_COUNTS_SAMPLES_OFFSET 2
#define RIGCTL_COUNTS_HELD_OFFSET    6
#define RIGCTL_COUNTS_DROPPED_OFFSET 8
#define RIGCTL_COUNTS_QUEUE_MAX_OFFSET   10
#define RIGCTL_COUNTS_COUNTS_OFFSET  11
#define RIGCTL_COUNTS_CRC_OFFSET     371
#define RIGCTL_COUNTS_FRAME_SIZE     373
#define RIGCTL_COUNTS_CRC_START      2
/* the encoder image's banner and identity: the stream's, and the encoder it runs */
#define RIGCTL_UNO_ENC_FIELD         " encoder=sa_fixed ring=32"  /* ring: common/sa_ring.h SA_RING_SAMPLES */

/* ---- 2. Drum controller (Mega), Modbus RTU ------------------------------------------------------------- */
/* 500000 baud: exact at 16 MHz (UBRR = 1), and on the 16U2 bridge; 115200 was +2.1 % off (docs/wire-protocol.md) */
#define RIGCTL_DRUM_BAUD             500000UL
#define RIGCTL_DRUM_DEVICE_ID        1
#define RIGCTL_MEGA_FW_MAJOR         1
#define RIGCTL_MEGA_FW_MINOR         9
#define RIGCTL_MEGA_FIRMWARE_VERSION ((RIGCTL_MEGA_FW_MAJOR << 8) | RIGCTL_MEGA_FW_MINOR)

/* Modbus function codes and exception codes used by the spec */
#define RIGCTL_MB_FC_READ_HOLDING    3
#define RIGCTL_MB_FC_READ_INPUT      4
#define RIGCTL_MB_FC_WRITE_SINGLE    6
#define RIGCTL_MB_FC_WRITE_MULTIPLE  16
#define RIGCTL_MB_EX_ILLEGAL_FUNCTION 1
#define RIGCTL_MB_EX_ILLEGAL_ADDRESS  2
#define RIGCTL_MB_EX_ILLEGAL_VALUE    3
/* t3.5 silence above 19200 baud (microseconds) */
#define RIGCTL_MB_T35_US             1750

/* 2.1 holding registers: address, range (MIN/MAX) and default (DEF) */
#define RIGCTL_HREG_SPEED_SETPOINT_0P1MMS     0
#define RIGCTL_HREG_SPEED_SETPOINT_0P1MMS_MIN 0
#define RIGCTL_HREG_SPEED_SETPOINT_0P1MMS_MAX 2000
#define RIGCTL_HREG_SPEED_SETPOINT_0P1MMS_DEF 0
#define RIGCTL_HREG_FORCE_SETPOINT_G          1
#define RIGCTL_HREG_FORCE_SETPOINT_G_MIN      0
#define RIGCTL_HREG_FORCE_SETPOINT_G_MAX      2000
#define RIGCTL_HREG_FORCE_SETPOINT_G_DEF      0
#define RIGCTL_HREG_COMMAND                   2
#define RIGCTL_HREG_COMMAND_MIN               0
#define RIGCTL_HREG_COMMAND_MAX               8
#define RIGCTL_HREG_COMMAND_DEF               0
#define RIGCTL_HREG_SPEED_PROFILE             3
#define RIGCTL_HREG_SPEED_PROFILE_MIN         0
#define RIGCTL_HREG_SPEED_PROFILE_MAX         1
#define RIGCTL_HREG_SPEED_PROFILE_DEF         0
#define RIGCTL_HREG_RAMP_START_SPEED_0P1MMS     4
#define RIGCTL_HREG_RAMP_START_SPEED_0P1MMS_MIN 0
#define RIGCTL_HREG_RAMP_START_SPEED_0P1MMS_MAX 2000
#define RIGCTL_HREG_RAMP_START_SPEED_0P1MMS_DEF 400
#define RIGCTL_HREG_RAMP_END_SPEED_0P1MMS       5
#define RIGCTL_HREG_RAMP_END_SPEED_0P1MMS_MIN   0
#define RIGCTL_HREG_RAMP_END_SPEED_0P1MMS_MAX   2000
#define RIGCTL_HREG_RAMP_END_SPEED_0P1MMS_DEF   1200
#define RIGCTL_HREG_RAMP_DURATION_MS          6
#define RIGCTL_HREG_RAMP_DURATION_MS_MIN      1
#define RIGCTL_HREG_RAMP_DURATION_MS_MAX      60000
#define RIGCTL_HREG_RAMP_DURATION_MS_DEF      3000
#define RIGCTL_HREG_SPEED_LIMIT_0P1MMS        7
#define RIGCTL_HREG_SPEED_LIMIT_0P1MMS_MIN    0
#define RIGCTL_HREG_SPEED_LIMIT_0P1MMS_MAX    2000
#define RIGCTL_HREG_SPEED_LIMIT_0P1MMS_DEF    1500
#define RIGCTL_HREG_FORCE_LIMIT_G             8
#define RIGCTL_HREG_FORCE_LIMIT_G_MIN         0
#define RIGCTL_HREG_FORCE_LIMIT_G_MAX         2000
#define RIGCTL_HREG_FORCE_LIMIT_G_DEF         1500
#define RIGCTL_HREG_FORCE_TOLERANCE_G         9
#define RIGCTL_HREG_FORCE_TOLERANCE_G_MIN     1
#define RIGCTL_HREG_FORCE_TOLERANCE_G_MAX     500
#define RIGCTL_HREG_FORCE_TOLERANCE_G_DEF     15
#define RIGCTL_HREG_SETTLE_TIME_MS            10
#define RIGCTL_HREG_SETTLE_TIME_MS_MIN        0
#define RIGCTL_HREG_SETTLE_TIME_MS_MAX        10000
#define RIGCTL_HREG_SETTLE_TIME_MS_DEF        300
#define RIGCTL_HREG_WATCHDOG_MS               11
#define RIGCTL_HREG_WATCHDOG_MS_MIN           100
#define RIGCTL_HREG_WATCHDOG_MS_MAX           10000
#define RIGCTL_HREG_WATCHDOG_MS_DEF           1000
#define RIGCTL_HREG_LOADCELL_SCALE_X100       12
#define RIGCTL_HREG_LOADCELL_SCALE_X100_MIN   1
#define RIGCTL_HREG_LOADCELL_SCALE_X100_MAX   65535
#define RIGCTL_HREG_LOADCELL_SCALE_X100_DEF   42000
#define RIGCTL_HREG_ACTUATOR_STEPS_PER_MM     13
#define RIGCTL_HREG_ACTUATOR_STEPS_PER_MM_MIN 1
#define RIGCTL_HREG_ACTUATOR_STEPS_PER_MM_MAX 65535
#define RIGCTL_HREG_ACTUATOR_STEPS_PER_MM_DEF 400
#define RIGCTL_HREG_LOADCELL_SCALE_X100_HI     14
#define RIGCTL_HREG_LOADCELL_SCALE_X100_HI_MIN 0
#define RIGCTL_HREG_LOADCELL_SCALE_X100_HI_MAX 65535
#define RIGCTL_HREG_LOADCELL_SCALE_X100_HI_DEF 0
#define RIGCTL_HREG_LOADCELL_SCALE_X100_LO     15
#define RIGCTL_HREG_LOADCELL_SCALE_X100_LO_MIN 0
#define RIGCTL_HREG_LOADCELL_SCALE_X100_LO_MAX 65535
#define RIGCTL_HREG_LOADCELL_SCALE_X100_LO_DEF 42000
#define RIGCTL_HREG_CALIBRATION_STIFFNESS_G_PER_MM     16
#define RIGCTL_HREG_CALIBRATION_STIFFNESS_G_PER_MM_MIN 0
#define RIGCTL_HREG_CALIBRATION_STIFFNESS_G_PER_MM_MAX 5000
#define RIGCTL_HREG_CALIBRATION_STIFFNESS_G_PER_MM_DEF 0
/* the signed 32-bit scale (HI/LO): range of its absolute value */
#define RIGCTL_LOADCELL_SCALE_X100_ABS_MIN    100L
#define RIGCTL_LOADCELL_SCALE_X100_ABS_MAX    10000000L
#define RIGCTL_HREG_HX711_RATE_SPS            20
#define RIGCTL_HREG_HX711_RATE_SPS_MIN        10
#define RIGCTL_HREG_HX711_RATE_SPS_MAX        80
#define RIGCTL_HREG_HX711_RATE_SPS_DEF        80
#define RIGCTL_HREG_FORCE_KP_80SPS_NMS_G      21
#define RIGCTL_HREG_FORCE_KP_80SPS_NMS_G_MIN  0
#define RIGCTL_HREG_FORCE_KP_80SPS_NMS_G_MAX  20000
#define RIGCTL_HREG_FORCE_KP_80SPS_NMS_G_DEF  10000
#define RIGCTL_HREG_FORCE_KI_80SPS_NMS_GS     22
#define RIGCTL_HREG_FORCE_KI_80SPS_NMS_GS_MIN 0
#define RIGCTL_HREG_FORCE_KI_80SPS_NMS_GS_MAX 20000
#define RIGCTL_HREG_FORCE_KI_80SPS_NMS_GS_DEF 10000
#define RIGCTL_HREG_FORCE_KP_10SPS_NMS_G      23
#define RIGCTL_HREG_FORCE_KP_10SPS_NMS_G_MIN  0
#define RIGCTL_HREG_FORCE_KP_10SPS_NMS_G_MAX  2000
#define RIGCTL_HREG_FORCE_KP_10SPS_NMS_G_DEF  1200
#define RIGCTL_HREG_FORCE_KI_10SPS_NMS_GS     24
#define RIGCTL_HREG_FORCE_KI_10SPS_NMS_GS_MIN 0
#define RIGCTL_HREG_FORCE_KI_10SPS_NMS_GS_MAX 2000
#define RIGCTL_HREG_FORCE_KI_10SPS_NMS_GS_DEF 600
/* the span 0 .. highest address; addresses it holds that the spec does not list are reserved (read 0, accept 0) */
#define RIGCTL_N_HOLDING                      25

/* 2.2 input registers (read only) */
#define RIGCTL_IREG_FORCE_G                  0
#define RIGCTL_IREG_SPEED_0P1MMS             1
#define RIGCTL_IREG_DRUM_ANGLE_0P01DEG       2
#define RIGCTL_IREG_DRUM_REVOLUTIONS         3
#define RIGCTL_IREG_ACTUATOR_POSITION_0P01MM 4
#define RIGCTL_IREG_STATE                    5
#define RIGCTL_IREG_FAULT_BITS               6
#define RIGCTL_IREG_FIRMWARE_VERSION         7
#define RIGCTL_IREG_HEARTBEAT                8
#define RIGCTL_IREG_SPEED_TARGET_0P1MMS      9
#define RIGCTL_IREG_LOADCELL_RAW_HI          10
#define RIGCTL_IREG_LOADCELL_RAW_LO          11
#define RIGCTL_IREG_FORCE_SETPOINT_ACTIVE_G  12
#define RIGCTL_IREG_RESET_CAUSE              13
#define RIGCTL_IREG_BOOT_COUNT               14
#define RIGCTL_IREG_STATUS_FLAGS             15
#define RIGCTL_IREG_FAULT_BITS_HI            16
#define RIGCTL_IREG_HX711_RATE_0P01SPS       20
#define RIGCTL_IREG_INDEX_SOURCE             21
#define RIGCTL_IREG_INDEX_PERIOD_MS          22
#define RIGCTL_IREG_INDEX_STEPS              23
#define RIGCTL_IREG_INDEX_COUNT              24
#define RIGCTL_IREG_MARK_PERIOD_0P1MS        25
#define RIGCTL_IREG_MARK_STEPS               26
#define RIGCTL_IREG_MARK_COUNT               27
#define RIGCTL_IREG_CONTACT_STIFFNESS_G_PER_MM 28
#define RIGCTL_IREG_STIFFNESS_MAX_G_PER_MM   29
/* the build id (make BUILD_ID=<12 hex digits>), 48 bits, most significant word first; 0 = built without one */
#define RIGCTL_IREG_BUILD_ID_0               30
#define RIGCTL_IREG_BUILD_ID_1               31
#define RIGCTL_IREG_BUILD_ID_2               32
#define RIGCTL_N_INPUT                       33

/* 2.3 commands (values written to RIGCTL_HREG_COMMAND) */
#define RIGCTL_CMD_NONE              0
#define RIGCTL_CMD_RUN               1
#define RIGCTL_CMD_STOP              2
#define RIGCTL_CMD_TARE              3
#define RIGCTL_CMD_HOME              4
#define RIGCTL_CMD_CLEAR_FAULT       5
#define RIGCTL_CMD_PRESS             6
#define RIGCTL_CMD_STOP_DRUM         7
#define RIGCTL_CMD_SAVE_CALIBRATION  8

/* SPEED_PROFILE values */
#define RIGCTL_PROFILE_CONSTANT      0
#define RIGCTL_PROFILE_RAMP          1

/* 2.4 states */
#define RIGCTL_STATE_IDLE            0
#define RIGCTL_STATE_HOMING          1
#define RIGCTL_STATE_SEEKING_FORCE   2
#define RIGCTL_STATE_FORCE_SETTLED   3
#define RIGCTL_STATE_RUNNING         4
#define RIGCTL_STATE_FAULT           5
#define RIGCTL_STATE_NOT_HOMED       6

/* 2.5 fault bits (bit numbers; masks are 1 << bit) */
#define RIGCTL_FAULT_FORCE_LIMIT_BIT       0
#define RIGCTL_FAULT_WATCHDOG_BIT          1
#define RIGCTL_FAULT_LOADCELL_TIMEOUT_BIT  2
#define RIGCTL_FAULT_ACTUATOR_TRAVEL_BIT   3
#define RIGCTL_FAULT_FORCE_LIMIT           (1u << RIGCTL_FAULT_FORCE_LIMIT_BIT)
#define RIGCTL_FAULT_WATCHDOG              (1u << RIGCTL_FAULT_WATCHDOG_BIT)
#define RIGCTL_FAULT_LOADCELL_TIMEOUT      (1u << RIGCTL_FAULT_LOADCELL_TIMEOUT_BIT)
#define RIGCTL_FAULT_ACTUATOR_TRAVEL       (1u << RIGCTL_FAULT_ACTUATOR_TRAVEL_BIT)
#define RIGCTL_FAULT_ESTOP_BIT             4
#define RIGCTL_FAULT_LOADCELL_REVERSED_BIT 5
#define RIGCTL_FAULT_HOME_NOT_FOUND_BIT    6
#define RIGCTL_FAULT_ESTOP                 (1u << RIGCTL_FAULT_ESTOP_BIT)
#define RIGCTL_FAULT_LOADCELL_REVERSED     (1u << RIGCTL_FAULT_LOADCELL_REVERSED_BIT)
#define RIGCTL_FAULT_HOME_NOT_FOUND        (1u << RIGCTL_FAULT_HOME_NOT_FOUND_BIT)
#define RIGCTL_FAULT_HX711_RATE_BIT        8
#define RIGCTL_FAULT_HX711_RATE            (1u << RIGCTL_FAULT_HX711_RATE_BIT)
#define RIGCTL_FAULT_ACTUATOR_DIRECTION_BIT 9
#define RIGCTL_FAULT_ACTUATOR_DIRECTION    (1u << RIGCTL_FAULT_ACTUATOR_DIRECTION_BIT)
#define RIGCTL_FAULT_DRUM_SLIP_BIT         10
#define RIGCTL_FAULT_DRUM_SLIP             (1u << RIGCTL_FAULT_DRUM_SLIP_BIT)
#define RIGCTL_FAULT_CONTACT_STIFFNESS_BIT 11
#define RIGCTL_FAULT_CONTACT_STIFFNESS     (1u << RIGCTL_FAULT_CONTACT_STIFFNESS_BIT)
/* 2.11 the force path's second channel and the reading's plausibility (firmware 1.2) */
#define RIGCTL_FAULT_POSITION_LIMIT_BIT    7
#define RIGCTL_FAULT_POSITION_LIMIT        (1u << RIGCTL_FAULT_POSITION_LIMIT_BIT)
#define RIGCTL_FAULT_HX711_STUCK_BIT       12
#define RIGCTL_FAULT_HX711_STUCK           (1u << RIGCTL_FAULT_HX711_STUCK_BIT)
#define RIGCTL_FAULT_HX711_LINE_BIT        13
#define RIGCTL_FAULT_HX711_LINE            (1u << RIGCTL_FAULT_HX711_LINE_BIT)
#define RIGCTL_FAULT_HX711_CADENCE_BIT     14
#define RIGCTL_FAULT_HX711_CADENCE         (1u << RIGCTL_FAULT_HX711_CADENCE_BIT)
#define RIGCTL_FAULT_CONTACT_LOST_BIT      15
#define RIGCTL_FAULT_CONTACT_LOST          (1u << RIGCTL_FAULT_CONTACT_LOST_BIT)
/* bits 16-31: FAULT_BITS_HI (firmware 1.5; the fault word is 32 bits, masks unsigned long) */
#define RIGCTL_FAULT_RESET_BIT             16
#define RIGCTL_FAULT_RESET                 (1UL << RIGCTL_FAULT_RESET_BIT)
#define RIGCTL_FAULT_LOADCELL_SCALE_BIT    17
#define RIGCTL_FAULT_LOADCELL_SCALE        (1UL << RIGCTL_FAULT_LOADCELL_SCALE_BIT)
#define RIGCTL_FAULT_LOADCELL_ZERO_BIT     18
#define RIGCTL_FAULT_LOADCELL_ZERO         (1UL << RIGCTL_FAULT_LOADCELL_ZERO_BIT)
#define RIGCTL_FAULT_CONTACT_MISSING_BIT   19
#define RIGCTL_FAULT_CONTACT_MISSING       (1UL << RIGCTL_FAULT_CONTACT_MISSING_BIT)
#define RIGCTL_LOADCELL_TIMEOUT_MS         200
#define RIGCTL_HOME_MAX_TRAVEL_MM          25
#define RIGCTL_HOME_TIMEOUT_MS             10000
#define RIGCTL_HOME_PROOF_MM               2   /* the switch opens within this when HOME leaves home (2.5) */
#define RIGCTL_HOME_LEAVE_UM               1500 /* HOME leaves the switch creeping; it must open within this: the rear stop
                                                 * 1 mm behind the switch + 0.5 mm (2.5) */
#define RIGCTL_DIRECTION_RISE_G            150 /* untared rise while moving home or backing off: ACTUATOR_DIRECTION */

/* 2.7 reset cause (bit numbers = the MCUSR bits PORF, EXTRF, BORF, WDRF) */
#define RIGCTL_RESET_POWER_ON_BIT          0
#define RIGCTL_RESET_EXTERNAL_BIT          1
#define RIGCTL_RESET_BROWN_OUT_BIT         2
#define RIGCTL_RESET_WATCHDOG_BIT          3
#define RIGCTL_RESET_POWER_ON              (1u << RIGCTL_RESET_POWER_ON_BIT)
#define RIGCTL_RESET_EXTERNAL              (1u << RIGCTL_RESET_EXTERNAL_BIT)
#define RIGCTL_RESET_BROWN_OUT             (1u << RIGCTL_RESET_BROWN_OUT_BIT)
#define RIGCTL_RESET_WATCHDOG              (1u << RIGCTL_RESET_WATCHDOG_BIT)

/* 2.8 status flags */
#define RIGCTL_STATUS_CALIBRATION_DEFAULTS_BIT 0
#define RIGCTL_STATUS_HOMED_BIT                1
#define RIGCTL_STATUS_DRIVERS_ENABLED_BIT      2
#define RIGCTL_STATUS_ESTOP_OPEN_BIT           3
#define RIGCTL_STATUS_HOME_SWITCH_BIT          4
#define RIGCTL_STATUS_TARED_BIT                5
#define RIGCTL_STATUS_CALIBRATION_DEFAULTS     (1u << RIGCTL_STATUS_CALIBRATION_DEFAULTS_BIT)
#define RIGCTL_STATUS_HOMED                    (1u << RIGCTL_STATUS_HOMED_BIT)
#define RIGCTL_STATUS_DRIVERS_ENABLED          (1u << RIGCTL_STATUS_DRIVERS_ENABLED_BIT)
#define RIGCTL_STATUS_ESTOP_OPEN               (1u << RIGCTL_STATUS_ESTOP_OPEN_BIT)
#define RIGCTL_STATUS_HOME_SWITCH              (1u << RIGCTL_STATUS_HOME_SWITCH_BIT)
#define RIGCTL_STATUS_TARED                    (1u << RIGCTL_STATUS_TARED_BIT)

/* 2.6 drum geometry defaults (the firmware's own values live in mega_drum/drum_config.h) */
#define RIGCTL_DRUM_DIAMETER_MM_DEF        100
#define RIGCTL_DRUM_STEPS_PER_REV_DEF      200
#define RIGCTL_DRUM_MICROSTEPS_DEF         16
#define RIGCTL_INDEX_PULSE_MS              1
/* 2.6 speed marks: a slotted disc on the drum with this many marks per revolution (its sensor on the Mega's D19);
 * DRUM_SLIP latches when the drum was stepped more than (1 + this many percent) x the microsteps of one mark
 * interval since the last mark (a stall: no mark; a slip: a late one) */
#define RIGCTL_DRUM_MARKS_PER_REV          8
#define RIGCTL_DRUM_SLIP_TOLERANCE_PCT     5

/* 2.9 HX711 rate: the firmware times this many periods at boot; the measured rate may differ from HX711_RATE_SPS
 * by this many percent */
#define RIGCTL_HX711_RATE_PERIODS          4
#define RIGCTL_HX711_RATE_TOLERANCE_PCT    20
/* 2.10 over-force prediction and contact stiffness: the trip looks this many periods ahead (sinc^4 group delay 2 +
 * the next reading 1); the first press after a reset probes the contact: approach at PROBE_TRAVEL_UM per LEAD
 * periods until PROBE_CONTACT_G, settle, PROBE_STEP_UM further, settle; accepted up to a loop phase of
 * LOOP_PHASE_MRAD at the crossover k x Kp with the HX711's DELAY_PERIODS_X10 / 10 periods of delay */
#define RIGCTL_FORCE_LEAD_PERIODS          3
#define RIGCTL_PROBE_CONTACT_G             50
#define RIGCTL_PROBE_TRAVEL_UM             100 /* = PROBE_BLIND_G x 1000 / CONTACT_STIFFNESS_MAX_G_MM */
/* the stiffest contact a rig config accepts, g/mm (a precondition: the rig as built's mount), and the force the
 * probe's approach may add at it before a reading can show the contact (the approach speed is derived from both) */
#define RIGCTL_CONTACT_STIFFNESS_MAX_G_MM  5000
#define RIGCTL_PROBE_BLIND_G               500
#define RIGCTL_PROBE_STEP_UM               20
#define RIGCTL_LOOP_PHASE_MRAD             750
#define RIGCTL_HX711_DELAY_PERIODS_X10     25
/* 2.11 the force path's second channel (the actuator's position past the probed contact) and the reading's
 * plausibility: travel past the contact's zero-force point is bounded by (FORCE_LIMIT_G + POSITION_MARGIN_G) / k;
 * the probe's second step presses PROBE_REFINE_G more for k; HX711_STUCK after this many identical raw readings;
 * HX711_CADENCE for a DOUT-ready edge sooner than this percentage of the measured period; HOME from an unknown
 * position moves HOME_CREEP_UM per HX711 period until the untared force fell by HOME_PROOF_FALL_G, and a rise of
 * HOME_RISE_G of |raw - zero| stops it (ACTUATOR_DIRECTION) */
#define RIGCTL_POSITION_MARGIN_G           100
/* a press to a contact an earlier probe located (kept across a release until HOME, a fault or a reset) approaches at
 * the loop's clamp speed up to this far before its zero-force point, then probes from there */
#define RIGCTL_PROBE_LOCATED_MARGIN_UM     300
#define RIGCTL_PROBE_REFINE_G              100
/* 2.12 the reading's scale checked against the contact's stiffness stored with the calibration: the probe's
 * stiffness over the stored one outside 100/(100 + SCALE_CHECK_PCT) .. (100 + SCALE_CHECK_PCT)/100 latches
 * LOADCELL_SCALE */
#define RIGCTL_SCALE_CHECK_PCT             15
#define RIGCTL_HX711_STUCK_READINGS        6
#define RIGCTL_HX711_CADENCE_PCT           50
/* 2.11 a back-off under load proves its way first: steps of at most BACKOFF_PROOF_UM (and BACKOFF_PROOF_G of spring
 * force at the contact's stiffness), each held until the HX711 has settled on it, at most BACKOFF_PROOF_TRIES of them:
 * its blind travel towards the sensor on a reversed motor is at most TRIES x UM */
#define RIGCTL_BACKOFF_PROOF_UM            8
#define RIGCTL_BACKOFF_PROOF_G             40
#define RIGCTL_BACKOFF_PROOF_TRIES         4
#define RIGCTL_HOME_CREEP_UM               12
#define RIGCTL_HOME_PROOF_FALL_G           50
#define RIGCTL_HOME_RISE_G                 30
/* 2.11 the press's direction watch: while the force loop drives, the step count commanded over PRESS_DIR_READINGS
 * readings (monotone, at least PRESS_DIR_STEPS) and the force read over as many readings PRESS_DIR_LAG_READINGS later
 * moving apart by PRESS_DIR_G latch ACTUATOR_DIRECTION; moving together, they prove the way for a back-off that
 * begins within PRESS_DIR_PROOF_READINGS readings (a latch without that proof stops the actuator where it stands) */
#define RIGCTL_PRESS_DIR_READINGS          4
#define RIGCTL_PRESS_DIR_LAG_READINGS      2
#define RIGCTL_PRESS_DIR_STEPS             16
#define RIGCTL_PRESS_DIR_G                 8
#define RIGCTL_PRESS_DIR_PROOF_READINGS    2
/* 2.13 the reading's zero at a press's start at home: the tare follows a settled reading within PRESS_DIR_G half the
 * way (slow drift: the cell's temperature, the HX711's offset, creep), never more than ZERO_TRACK_G from HOME's tare */
#define RIGCTL_ZERO_TRACK_G                24
#define RIGCTL_INDEX_SOURCE_STEPS          0
#define RIGCTL_INDEX_SOURCE_SENSOR         1

#endif /* RIGCTL_WIRE_H */
