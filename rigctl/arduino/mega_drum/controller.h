/* controller.h - the drum controller's logic (docs/wire-protocol.md 2.1-2.6), pure and host-tested:
 * register map with range checks, commands and states, speed profiles with the acceleration ramp, the force
 * loop's decisions (PI, settle detection, force limit, end of travel), tare, host watchdog and heartbeat.
 * The hardware glue (mega_drum.cpp) feeds it time, load-cell readings and step counts, and applies its outputs
 * (drum surface speed, actuator velocity) to the step generators. */
#ifndef CONTROLLER_H
#define CONTROLLER_H
#include <stdint.h>
#include "../common/rigctl_wire.h"
#include "force_pi.h"
#include "modbus_slave.h"
#ifdef __cplusplus
extern "C" {
#endif

/* what the actuator does */
#define ACT_MODE_HOLD    0 /* not moving */
#define ACT_MODE_FORCE   1 /* the force loop drives it */
#define ACT_MODE_RETRACT 2 /* backing off to position 0 (home) at full speed */
#define ACT_MODE_HOMING  3 /* seeking the home switch, proving the direction, then position := 0 */
/* HOME's phases (spec 2.5): back to the switch, leave it (it must open: the direction is right), back again */
#define HOME_SEEK   0
#define HOME_LEAVE  1
#define HOME_RETURN 2
/* the contact probe of the first press after a reset (spec 2.10): approach slowly, settle, a small step, settle */
#define PROBE_NONE     0
#define PROBE_APPROACH 1
#define PROBE_SETTLE1  2
#define PROBE_STEP     3
#define PROBE_SETTLE2  4
#define PROBE_STEP2    5 /* the second measuring step, sized to press PROBE_REFINE_G more (spec 2.11) */
#define PROBE_SETTLE3  6
#define PROBE_ZERO     7 /* before the approach of a press from home at rest: the settled reading against the tare (2.13) */

typedef struct {
    uint16_t hreg[RIGCTL_N_HOLDING]; /* hreg[LOADCELL_SCALE_X100] is the view of the 32-bit scale in HI/LO */
    uint8_t state;
    uint32_t faults;        /* FAULT_BITS (bits 0-15) and FAULT_BITS_HI (16-31) */
    /* safety (docs/wire-protocol.md 2.4-2.8) */
    uint8_t homed;          /* HOME succeeded since the last reset / e-stop / failed HOME */
    uint8_t tared;          /* a tare was taken since the last reset */
    uint8_t estop_open;     /* the e-stop input reads open now (glue) */
    uint8_t estop_release;  /* output: CLEAR_FAULT cleared ESTOP; glue re-arms its latch and clears this */
    uint8_t calib_defaults; /* EEPROM calibration missing or bad at boot: defaults in use */
    uint8_t drivers_on;     /* output: the stepper drivers should be enabled (glue drives EN, ANDed with e-stop) */
    uint16_t reset_cause;   /* RIGCTL_RESET_* bits (glue, at boot) */
    uint16_t boot_count;    /* (glue, at boot) */
    uint32_t home_start_ms;
    int32_t home_start_steps;
    uint8_t home_phase;      /* HOME_SEEK, HOME_LEAVE, HOME_RETURN */
    int32_t home_phase_steps; /* the step count when the phase began */
    int32_t home_leave_steps; /* steps HOME_LEAVE took to open the switch */
    /* the ratchet guard (spec 2.11, issue 75): where the last crush-class latch stopped the actuator, in the step
     * count's frame; no HOME leaves the switch past it. The controller's held state: it survives CLEAR_FAULT and
     * failed HOMEs, a HOME that proves the switch releases it, a reset loses it (the count is unknown then: HOME
     * creeps and the load against the zero stored in EEPROM guards instead) */
    uint8_t ratchet_valid;
    int32_t ratchet_steps;
    /* direction by force (spec 2.5): the lowest untared reading since HOME or a back-off began */
    int32_t move_ref_raw;
    uint8_t move_ref_valid;
    uint8_t move_skip;      /* readings still to skip (a back-off: the HX711's 4-period settling of what came before) */
    uint8_t have_reading;
    /* over-force prediction and contact stiffness (spec 2.10) */
    float force_prev_gf;       /* the previous reading's force while the force loop drives (prediction) */
    uint8_t force_prev_valid;
    uint16_t stiffness_g_mm;   /* contact stiffness measured by the probe since the reset, g/mm (0 = not yet) */
    uint8_t probe_phase;       /* PROBE_* */
    uint8_t probe_readings;    /* readings since the actuator stopped (settling) */
    float probe_f1_gf;
    int32_t probe_x1_steps;
    int32_t probe_x_target;
    /* the second channel (spec 2.11): the contact the press probed, valid until the actuator is released */
    uint8_t contact_valid;     /* probed since the last release, HOME or reset */
    float contact_k_g_per_step; /* its stiffness, g per actuator step */
    float contact_x0_steps;    /* its zero-force point, actuator steps */
    /* where the last probe found the contact (its zero-force point, steps), kept across a release (STOP) until HOME,
     * a fault or a reset: the next press approaches it fast up to PROBE_LOCATED_MARGIN_UM before it, then probes */
    uint8_t contact_located;
    float located_x0_steps;
    float located_k_g_per_step; /* its stiffness (2.13: how far past it the approach may go reading no contact) */
    /* the reading's plausibility (spec 2.11) */
    int32_t prev_raw;
    uint8_t same_raw;          /* readings in a row with the same raw value */
    uint8_t line_codes;        /* 0x000000 / 0xFFFFFF readings in a row */
    uint8_t still_readings;    /* readings in a row with the actuator commanded still (255: at least) (2.13) */
    /* the tare's raw zero stored with the calibration (spec 2.11; glue, at boot) */
    int32_t zero_raw;
    uint8_t zero_valid;
    /* HOME from an unknown position (spec 2.11): creep until the force proves the direction */
    uint8_t home_creep;
    float home_d_start_g;      /* |raw - zero| in g when HOME began (-1: no reading yet) */
    float move_d_min_g;        /* the lowest |raw - zero| since HOME or a back-off began, g */
    /* the press's direction watch (spec 2.11): (step count, force) at the last readings while the force loop drove */
    int32_t press_dir_steps[RIGCTL_PRESS_DIR_READINGS + RIGCTL_PRESS_DIR_LAG_READINGS + 1];
    float press_dir_gf[RIGCTL_PRESS_DIR_READINGS + RIGCTL_PRESS_DIR_LAG_READINGS + 1];
    uint8_t press_dir_n;       /* readings held (up to the ring's length); the newest is at [n - 1] */
    uint8_t press_dir_age;     /* readings since the count and the force last moved together (255: not proven) */
    uint8_t press_dir_held;    /* proven by the probe's step or since it was done, nothing against it since */
    uint8_t press_dir_leave;   /* the press left the closed home switch homed and has not reached the contact */
    /* a back-off under load proves its way before it runs (spec 2.11): at rest and settled, short steps held until
     * the HX711 has settled on each, and the load must have fallen (controller.c: backoff_begin); no proof older
     * than the latch moves the actuator */
    uint8_t backoff_phase;     /* BACKOFF_FREE, BACKOFF_REST, BACKOFF_STEP, BACKOFF_SETTLE */
    uint8_t backoff_tries;     /* proof steps taken */
    uint8_t backoff_readings;  /* readings since the proof step stopped */
    int32_t backoff_target_steps;
    int32_t backoff_step_steps;
    float backoff_d0_g;        /* the load (|raw - zero|, g) at rest before the first step */
    float backoff_fall_g;      /* the fall that proves the way (and the rise that disproves it), g */
    float backoff_sum_g;       /* the settled readings' loads the decision averages (BACKOFF_AVG_READINGS), g */
    /* time */
    uint32_t now_ms;
    uint32_t last_request_ms;
    uint32_t last_loadcell_ms;
    uint32_t run_start_ms;
    uint32_t on_target_since_ms;
    uint8_t on_target;
    /* drum */
    uint8_t drum_on;        /* profile active (RUNNING) */
    float drum_cmd_mm_s;    /* commanded surface speed after the acceleration ramp (output) */
    float drum_actual_mm_s; /* surface speed of the step rate actually loaded (glue) */
    uint16_t speed_target_0p1; /* profile target now */
    uint16_t drum_step_in_rev; /* microsteps since the index mark (glue) */
    uint16_t drum_revolutions; /* (glue) */
    /* load cell */
    int32_t loadcell_raw;
    int32_t tare_offset;
    int32_t home_tare_offset; /* the tare HOME (or the power-up, or TARE) took: the zero's follow is bounded by it */
    uint8_t tare_pending;
    int16_t force_g;
    float force_gf;
    /* actuator */
    uint8_t act_mode;
    int32_t act_pos_steps;  /* (glue) */
    uint8_t home_switch;    /* 1 = at home (glue) */
    float act_vel_mm_s;     /* commanded velocity (output), + towards the sensor */
    uint8_t zero_position;  /* output: glue must set its step count to 0 */
    force_pi_t pi;
    uint8_t save_calibration; /* output: glue writes EEPROM and clears it */
    /* HX711 rate measured at boot (spec 2.9) */
    uint32_t hx_last_us;
    uint32_t hx_sum_us;
    uint8_t hx_edges;
    uint16_t hx_rate_0p01;  /* 0 until measured */
    float hx_period_s;      /* the force loop's time step */
    /* drum index (glue; spec 2.6) */
    uint8_t index_source;   /* RIGCTL_INDEX_SOURCE_* */
    uint16_t index_period_ms;
    uint16_t index_steps;
    uint16_t index_count;
    /* drum speed marks (glue; spec 2.6) */
    uint16_t mark_period_0p1ms;
    uint16_t mark_steps;
    uint16_t mark_count;
    uint8_t drum_slip;      /* input: more than DRUM_SLIP_STEPS since the last mark while stepped: DRUM_SLIP */
    /* the reset latch (spec 2.7, issue 76): a reset that may have left the actuator pressing is latched by the
     * controller itself (RESET), for every later host until CLEAR_FAULT (controller.c: ctl_boot) */
    uint8_t away;           /* output, the warm-boot record: the actuator moved since it was last proven back at home
                             * (or the operator's CLEAR_FAULT); the glue keeps it across a warm reset (RAM) */
    uint8_t boot_load_check; /* a cold boot (no warm-boot record): the first timed reading's load decides */
    /* the safety record the glue keeps in EEPROM, written only when it changes (a latch, its clearing) */
    uint8_t ee_reset_held;  /* RESET latched and not yet cleared (kept across power cycles) */
    int16_t ee_ratchet_g;   /* the load ratchet (spec 2.11): the load at the last crush-class latch, g; 0 = none */
} ctl_t;

/* power-up: defaults from the spec, calibration from EEPROM (0 = the default), state NOT_HOMED; the load cell is
 * tared on the first reading only if the home switch is closed then */
void ctl_init(ctl_t *c, int32_t loadcell_scale_x100, uint16_t actuator_steps_per_mm);
/* after ctl_init and the calibration (the zero stored with it): what the glue kept across the reset. `warm`: the
 * warm-boot record (RAM) survived, `was_away` its flag; `reset_held`, `ratchet_g`: the EEPROM safety record. A reset
 * away from home, or a RESET latch not yet cleared, latches RESET now; a cold boot decides at its first timed reading
 * (the load against the stored zero). Nothing moves either way. */
void ctl_boot(ctl_t *c, uint8_t warm, uint8_t was_away, uint8_t reset_held, int16_t ratchet_g);
/* the load-cell scale, counts per g x 100 (signed) */
int32_t ctl_scale_x100(const ctl_t *c);
/* the e-stop input opened (the glue has already disabled the drivers and stopped the step timers in its ISR):
 * latch ESTOP, FAULT, not homed, nothing moves */
void ctl_estop(ctl_t *c);
/* register access for the Modbus handler (addresses already range-checked by it) */
uint16_t ctl_read_holding(void *ctx, uint16_t addr);
uint16_t ctl_read_input(void *ctx, uint16_t addr);
/* write n holding registers from start: every value is checked first (range, limits, command allowed in the
 * current state); returns RIGCTL_MB_EX_ILLEGAL_VALUE and changes nothing if one fails, else applies them all
 * and then runs the command, if COMMAND was written */
uint8_t ctl_write_holding(void *ctx, uint16_t start, uint16_t n, const uint16_t *values);
/* point a Modbus slave at this controller's register map (device id 1, both tables) */
void ctl_bind_modbus(ctl_t *c, mb_slave_t *mb);
/* a valid request for this device arrived (feeds the host watchdog) */
void ctl_feed_watchdog(ctl_t *c);
/* 1 kHz control step: profiles, ramps, watchdog, homing/retract, settle timing, faults */
void ctl_tick(ctl_t *c, uint32_t now_ms);
/* a new HX711 reading (signed 24-bit counts): force, tare, force limit, PI update */
void ctl_loadcell(ctl_t *c, int32_t raw);
/* the HX711's DOUT went low (a reading is ready) at t_us (any microsecond clock): times the first periods after
 * boot (HX711_RATE_0P01SPS, the force loop's time step) and latches HX711_RATE when the rate is not HX711_RATE_SPS */
void ctl_hx711_ready(ctl_t *c, uint32_t t_us);
/* the stiffest contact the force loop holds with its gains now, g/mm (spec 2.10; 65535 with Kp = 0) */
uint16_t ctl_stiffness_max(const ctl_t *c);
/* force in g from raw counts with the current tare and scale */
float ctl_force_from_raw(const ctl_t *c, int32_t raw);

#ifdef __cplusplus
}
#endif
#endif
