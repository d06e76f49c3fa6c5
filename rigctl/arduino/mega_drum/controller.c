/* controller.c - see controller.h. Register semantics: docs/wire-protocol.md 2.1-2.5. */
#include "controller.h"
#include "drum_config.h"
#include "steprate.h"

/* every holding register of the spec (table 2.1), once: its range and default come from the header by name.
 * Addresses the list does not name are reserved: range 0-0, default 0 (they read 0 and accept only 0). */
#define HREG_LIST(X)                                                                                              \
    X(SPEED_SETPOINT_0P1MMS) X(FORCE_SETPOINT_G) X(COMMAND) X(SPEED_PROFILE) X(RAMP_START_SPEED_0P1MMS)          \
    X(RAMP_END_SPEED_0P1MMS) X(RAMP_DURATION_MS) X(SPEED_LIMIT_0P1MMS) X(FORCE_LIMIT_G) X(FORCE_TOLERANCE_G)      \
    X(SETTLE_TIME_MS) X(WATCHDOG_MS) X(LOADCELL_SCALE_X100) X(ACTUATOR_STEPS_PER_MM) X(HX711_RATE_SPS)           \
    X(FORCE_KP_80SPS_NMS_G) X(FORCE_KI_80SPS_NMS_GS) X(FORCE_KP_10SPS_NMS_G) X(FORCE_KI_10SPS_NMS_GS)          \
    X(LOADCELL_SCALE_X100_HI) X(LOADCELL_SCALE_X100_LO) X(CALIBRATION_STIFFNESS_G_PER_MM)
#define HREG_MIN(name) [RIGCTL_HREG_##name] = RIGCTL_HREG_##name##_MIN,
#define HREG_MAX(name) [RIGCTL_HREG_##name] = RIGCTL_HREG_##name##_MAX,
#define HREG_DEF(name) [RIGCTL_HREG_##name] = RIGCTL_HREG_##name##_DEF,
static const uint16_t hreg_min[RIGCTL_N_HOLDING] = {HREG_LIST(HREG_MIN)};
static const uint16_t hreg_max[RIGCTL_N_HOLDING] = {HREG_LIST(HREG_MAX)};
static const uint16_t hreg_def[RIGCTL_N_HOLDING] = {HREG_LIST(HREG_DEF)};

#define HI RIGCTL_HREG_LOADCELL_SCALE_X100_HI
#define LO RIGCTL_HREG_LOADCELL_SCALE_X100_LO

static int32_t scale_of(const uint16_t *h)
{
    return (int32_t)(((uint32_t)h[HI] << 16) | h[LO]);
}

/* the 32-bit scale into HI/LO and its 16-bit view into LOADCELL_SCALE_X100 (0 when it does not fit) */
static void set_scale(uint16_t *h, int32_t s)
{
    h[HI] = (uint16_t)((uint32_t)s >> 16);
    h[LO] = (uint16_t)((uint32_t)s & 0xFFFF);
    h[RIGCTL_HREG_LOADCELL_SCALE_X100] = (s >= 1 && s <= 65535) ? (uint16_t)s : 0;
}

static uint8_t scale_ok(int32_t s)
{
    int32_t a;
    if (s == INT32_MIN) return 0; /* before its negation: -INT32_MIN overflows (undefined; cppcheck integerOverflowCond) */
    a = s < 0 ? -s : s;
    return a >= RIGCTL_LOADCELL_SCALE_X100_ABS_MIN && a <= RIGCTL_LOADCELL_SCALE_X100_ABS_MAX;
}

int32_t ctl_scale_x100(const ctl_t *c)
{
    return scale_of(c->hreg);
}

void ctl_init(ctl_t *c, int32_t loadcell_scale_x100, uint16_t actuator_steps_per_mm)
{
    uint16_t i;
    uint8_t *p = (uint8_t *)c;
    for (i = 0; i < sizeof(*c); i++) p[i] = 0;
    for (i = 0; i < RIGCTL_N_HOLDING; i++) c->hreg[i] = hreg_def[i];
    if (loadcell_scale_x100 && scale_ok(loadcell_scale_x100)) set_scale(c->hreg, loadcell_scale_x100);
    if (actuator_steps_per_mm) c->hreg[RIGCTL_HREG_ACTUATOR_STEPS_PER_MM] = actuator_steps_per_mm;
    /* after any reset the actuator's position is unknown (a reset under load leaves it pressed): nothing moves
     * until HOME, and the power-up tare is taken only if the home switch is closed at the first reading */
    c->state = RIGCTL_STATE_NOT_HOMED;
    c->tare_pending = 1;
    c->press_dir_age = 255; /* no proof of the way yet (spec 2.11) */
    force_pi_init(&c->pi, 0.0f, 0.0f, ACT_MAX_SPEED_MM_S, FORCE_INTEGRATE_BAND_G); /* gains: force_loop_gains */
}

static uint8_t force_engaged(const ctl_t *c)
{
    return c->state == RIGCTL_STATE_SEEKING_FORCE || c->state == RIGCTL_STATE_FORCE_SETTLED ||
           c->state == RIGCTL_STATE_RUNNING;
}

static float act_pos_mm(const ctl_t *c)
{
    return (float)c->act_pos_steps / (float)c->hreg[RIGCTL_HREG_ACTUATOR_STEPS_PER_MM];
}

float ctl_force_from_raw(const ctl_t *c, int32_t raw)
{
    return (float)(raw - c->tare_offset) * 100.0f / (float)scale_of(c->hreg);
}

/* the raw zero the direction checks measure the load from, sign-free (spec 2.11): the tare, else the one stored with
 * the calibration; 0 when neither is known (the signed check of spec 2.5 is used then) */
static uint8_t direction_zero(const ctl_t *c, int32_t *zero)
{
    if (c->tared) *zero = c->tare_offset;
    else if (c->zero_valid) *zero = c->zero_raw;
    else return 0;
    return 1;
}

/* the load on the cell, g, whatever the sign of the scale or of the cell's wiring: |raw - zero| */
static float load_g(const ctl_t *c, int32_t raw, int32_t zero)
{
    float g = (float)(raw - zero) * 100.0f / (float)scale_of(c->hreg);
    return g < 0.0f ? -g : g;
}

/* a move that must only take force off the cell begins: its readings' load (sign-free) is compared with the lowest
 * since. A back-off skips the HX711's settling (4 periods): a force that tripped FORCE_LIMIT on its way up (a push on
 * the cell) is still rising in the readings then; HOME starts unloaded or from a reset and checks from the first. */
static void move_watch_start(ctl_t *c, uint8_t skip)
{
    int32_t zero;
    uint8_t known = direction_zero(c, &zero);
    c->move_ref_raw = c->loadcell_raw;
    c->move_ref_valid = c->have_reading;
    c->move_d_min_g = known && c->have_reading ? load_g(c, c->loadcell_raw, zero) : 0.0f;
    c->home_d_start_g = known && c->have_reading ? c->move_d_min_g : -1.0f;
    c->move_skip = skip;
}

/* HOME from an unknown position must not find the cell loaded past the limit, nor load it so (spec 2.11): FORCE_LIMIT_G
 * plus 2 x FORCE_TOLERANCE_G of |raw - zero| (repeated HOMEs of a reversed motor cannot add up past it) */
static float home_load_cap_g(const ctl_t *c)
{
    return (float)c->hreg[RIGCTL_HREG_FORCE_LIMIT_G] + 2.0f * (float)c->hreg[RIGCTL_HREG_FORCE_TOLERANCE_G];
}

static uint8_t home_overloaded(const ctl_t *c)
{
    int32_t zero;
    return !c->homed && c->have_reading && direction_zero(c, &zero) &&
           load_g(c, c->loadcell_raw, zero) > home_load_cap_g(c);
}

/* a back-off under load proves its way first (spec 2.11, issue 75): the press's own proof may be older than the fault
 * (a motor swapped while the loop held: 2,688 g when the back-off ran blind on it for the HX711's settling at 10 SPS).
 * It holds until the drum is at rest and the HX711 has settled (RATE_PERIODS + 1 readings: the load then, d0), then
 * creeps: steps of at most BACKOFF_PROOF_UM and BACKOFF_PROOF_G of spring force at the contact's stiffness (the
 * probe's, else the stiffest the loop holds), each held until the HX711 has settled on it. A load fallen below d0 by
 * half of what a step takes off at the probe's stiffness (at least BACKOFF_MIN_G) proves the way: it goes on at speed,
 * watched; risen as much, ACTUATOR_DIRECTION where it stands (HOME creeps and proves the way later). Its blind travel
 * towards the sensor is one step (<= BACKOFF_PROOF_UM, the campaign's step-after-latch slack) on a contact stiff enough
 * to show it, whatever the HX711's rate. After BACKOFF_PROOF_TRIES steps with neither (a contact so soft that the
 * travel carries no force) it goes on, watched. Under no load (below BACKOFF_LOAD_G) it runs at once, watched. */
#define BACKOFF_PROOF_G ((float)RIGCTL_BACKOFF_PROOF_G)
#define BACKOFF_PROOF_UM ((float)RIGCTL_BACKOFF_PROOF_UM)
/* the smallest fall (or rise) that decides, g, on the mean of BACKOFF_AVG_READINGS settled readings before and after:
 * 3 g is 5 sd of that difference at the model's 0.8 g a reading (30 sd at a real HX711's ~0.1 g). 1 g on single
 * readings decided on noise: a step of 2.5 um at 250 g/mm (0.6 g) read as a rise latched ACTUATOR_DIRECTION on a good
 * motor in about one back-off in six (test_drum_conformance's end-of-travel case, the CI run under load) */
#define BACKOFF_MIN_G 3.0f
#define BACKOFF_AVG_READINGS 4u
#define BACKOFF_PROOF_TRIES ((uint8_t)RIGCTL_BACKOFF_PROOF_TRIES)
#define BACKOFF_LOAD_G 30.0f
enum { BACKOFF_FREE = 0, BACKOFF_REST, BACKOFF_STEP, BACKOFF_SETTLE };
/* the power-up tare's agreement with the stored zero (ctl_loadcell), g */
#define TARE_ZERO_AGREE_G 50.0f

static void backoff_step(ctl_t *c)
{
    c->backoff_target_steps = c->act_pos_steps - c->backoff_step_steps;
    c->backoff_phase = BACKOFF_STEP;
    c->backoff_tries++;
}

/* the back-off's readings of the HX711 settling on a step (or the drum coming to rest) start again */
static void backoff_settle_restart(ctl_t *c)
{
    c->backoff_readings = 0;
    c->backoff_sum_g = 0.0f;
}

static void backoff_begin(ctl_t *c, float k_meas_g_per_step)
{
    int32_t zero, by_um;
    float k, spmm = (float)c->hreg[RIGCTL_HREG_ACTUATOR_STEPS_PER_MM];
    c->backoff_phase = BACKOFF_FREE;
    c->backoff_tries = 0;
    backoff_settle_restart(c);
    if (!c->have_reading || !direction_zero(c, &zero) || load_g(c, c->loadcell_raw, zero) < BACKOFF_LOAD_G) return;
    k = k_meas_g_per_step > 0.0f ? k_meas_g_per_step : (float)ctl_stiffness_max(c) / spmm;
    c->backoff_step_steps = (int32_t)(BACKOFF_PROOF_G / k);
    by_um = (int32_t)(BACKOFF_PROOF_UM * 1e-3f * spmm);
    if (c->backoff_step_steps > by_um) c->backoff_step_steps = by_um;
    if (c->backoff_step_steps < 1) c->backoff_step_steps = 1;
    c->backoff_fall_g = k_meas_g_per_step > 0.0f ? 0.5f * k * (float)c->backoff_step_steps : 0.0f;
    if (c->backoff_fall_g < BACKOFF_MIN_G) c->backoff_fall_g = BACKOFF_MIN_G;
    c->backoff_phase = BACKOFF_REST;
}

/* the back-off's speed in its phase (spec 2.11): still until its way is proven (resting, settling on a proof step),
 * a creep on a proof step, full speed once proven or unloaded. Set at the latch too, not only by the next tick
 * (736038: a latch's back-off ran at full speed until the next control period, and its proof step at full speed for
 * one: 45 um towards the sensor on a reversed motor); the proof step creeps at BACKOFF_PROOF_MM_S, so the 1 ms tick
 * (or a model's 10 ms control period) ends it within a micrometre or two of its length */
#define BACKOFF_PROOF_MM_S 0.2f
static float backoff_speed(const ctl_t *c)
{
    if (c->backoff_phase == BACKOFF_REST || c->backoff_phase == BACKOFF_SETTLE) return 0.0f;
    return c->backoff_phase == BACKOFF_STEP ? -BACKOFF_PROOF_MM_S : -ACT_MAX_SPEED_MM_S;
}

/* the actuator stops where it is (position unknown) or, homed, backs off to home */
static void release_actuator(ctl_t *c)
{
    float k_meas = c->contact_valid ? c->contact_k_g_per_step : 0.0f;
    c->contact_valid = 0; /* released: the next press probes the contact again (spec 2.11) */
    if (c->homed) {
        if (c->act_mode != ACT_MODE_RETRACT) {
            move_watch_start(c, RIGCTL_HX711_RATE_PERIODS);
            backoff_begin(c, k_meas);
        }
        c->act_mode = ACT_MODE_RETRACT;
        c->act_vel_mm_s = backoff_speed(c);
    } else {
        c->act_mode = ACT_MODE_HOLD;
        c->act_vel_mm_s = 0.0f;
    }
}

/* the way a back-off takes is proven by this press's own motion (spec 2.11): the count and the force moved
 * together in a window that ended at most PRESS_DIR_PROOF_READINGS readings ago, or the probe's measuring step(s)
 * raised the settled load (or the loop's motion proved it since the probe was done), and nothing moved them apart
 * since (an older proof from the probe's approach would miss a motor swapped while the probe held still; once the
 * loop holds, a reversed motor drives the force off and is seen). Before the contact, HOME's switch proof stands
 * (press_dir_leave): the press left the closed switch, and the switch reading closed more than HOME_PROOF_MM out
 * voids it (a motor reversed since drives the actuator back home) */
static uint8_t press_dir_proven(const ctl_t *c)
{
    return c->press_dir_held || c->press_dir_leave || c->press_dir_age <= RIGCTL_PRESS_DIR_PROOF_READINGS;
}

static void press_dir_forget(ctl_t *c)
{
    c->press_dir_n = 0;
    c->press_dir_age = 255;
    c->press_dir_held = 0;
    c->press_dir_leave = 0;
}

/* the faults after which the way towards the sensor is in doubt: the ratchet guard (spec 2.11, issue 75) holds their
 * latch's position, and no HOME started after it leaves the switch past it (a switch stuck closed reads "home"
 * anywhere: every acknowledged HOME walked the actuator further in). Presses need a homed controller, which after such
 * a latch means a back-off that proved its way or a HOME that proved the switch; that HOME releases the ratchet */
#define RATCHET_FAULTS                                                                                            \
    (RIGCTL_FAULT_FORCE_LIMIT | RIGCTL_FAULT_POSITION_LIMIT | RIGCTL_FAULT_ACTUATOR_DIRECTION |                   \
     RIGCTL_FAULT_CONTACT_LOST | RIGCTL_FAULT_CONTACT_STIFFNESS | RIGCTL_FAULT_LOADCELL_REVERSED |               \
     RIGCTL_FAULT_CONTACT_MISSING)

/* ---- the load ratchet (spec 2.11, issue 75): the ratchet guard's step count is lost at a reset (the count restarts
 * where the actuator stands), so a switch stuck closed let every reset's HOME leave it creeping until the load watch
 * stopped it, one creep's rise (HOME_RISE_G) further each time. The load (|raw - zero|, g) at the first crush-class
 * latch since the last HOME that proved the switch is kept in the EEPROM safety record (written at that latch and at
 * that HOME only: no wear in normal use); no HOME leaves the switch into a load of at least that much (nor of
 * HOME_RISE_G: the watch's own bound), whatever the count says: HOME_NOT_FOUND where it stands. */
static void load_ratchet_latch(ctl_t *c)
{
    int32_t zero;
    float d;
    if (c->ee_ratchet_g || !c->have_reading || !direction_zero(c, &zero)) return; /* kept: the first latch's */
    d = load_g(c, c->loadcell_raw, zero);
    c->ee_ratchet_g = (int16_t)(d >= 32767.0f ? 32767 : (d < 1.0f ? 1 : (int16_t)(d + 0.5f)));
}

static uint8_t load_ratchet_reached(const ctl_t *c, float d)
{
    float at = (float)c->ee_ratchet_g;
    if (at < (float)RIGCTL_HOME_RISE_G) at = (float)RIGCTL_HOME_RISE_G;
    return c->ee_ratchet_g && c->act_mode == ACT_MODE_HOMING && c->home_phase == HOME_LEAVE && d >= at;
}

/* the same at every tick of HOME's leave, on the last reading: it does not start (or go on) into the ratchet's load */
static uint8_t load_ratchet_reached_now(const ctl_t *c)
{
    int32_t zero;
    return c->have_reading && direction_zero(c, &zero) && load_ratchet_reached(c, load_g(c, c->loadcell_raw, zero));
}

static void fault(ctl_t *c, uint32_t bits)
{
    if (bits & RATCHET_FAULTS) { /* no start goes further towards the sensor than this (spec 2.11) */
        c->ratchet_valid = 1;
        c->ratchet_steps = c->act_pos_steps;
        load_ratchet_latch(c); /* ... nor, across resets, into more load than this */
    }
    /* a latch while pressing backs off only the way the loop's motion proved; else it stops where it stands, not
     * homed (the start's HOME creeps and proves the way) */
    if (force_engaged(c) && !press_dir_proven(c)) c->homed = 0;
    press_dir_forget(c);
    c->faults |= bits;
    c->contact_located = 0; /* after any fault the next press locates the contact from scratch (2.11) */
    c->state = RIGCTL_STATE_FAULT;
    c->drum_on = 0;
    release_actuator(c);
    force_pi_reset(&c->pi);
}

/* the actuator may not go where its steps say: its position means nothing, it stops where it stands (a back-off
 * would press if it runs backwards); the start's HOME creeps from an unknown position and proves the way (2.11) */
static void stop_unproven(ctl_t *c, uint32_t bits)
{
    c->homed = 0;
    fault(c, bits);
    c->act_mode = ACT_MODE_HOLD;
    c->act_vel_mm_s = 0.0f;
}

/* the actuator moved the wrong way */
static void direction_fault(ctl_t *c)
{
    stop_unproven(c, RIGCTL_FAULT_ACTUATOR_DIRECTION);
}

void ctl_estop(ctl_t *c)
{
    c->homed = 0; /* the drivers lost power: steps may be lost */
    fault(c, RIGCTL_FAULT_ESTOP);
    c->drum_cmd_mm_s = 0.0f; /* the step timers were stopped in the ISR: no deceleration ramp */
}

/* ---- the reset latch (spec 2.7, issue 76): a reset that may have left the actuator pressing is latched here, by the
 * controller, so that every later host finds it (the host that saw the reset may be gone, or may be the cause: a port
 * opening resets a Mega). Latched: a warm reset whose warm-boot record says the actuator was away from home, a cold
 * boot (the record lost with the RAM) whose first timed reading is loaded against the zero stored with the
 * calibration, and, across power cycles, a RESET latch not yet cleared (the EEPROM safety record). CLEAR_FAULT is the
 * operator's word for where the actuator stands: it clears the latch and the record, and moves nothing (reset is not
 * start: the start's HOME creeps from an unknown position and proves its way). */
static void reset_latch(ctl_t *c)
{
    c->away = 1;
    c->ee_reset_held = 1; /* the glue writes the EEPROM record once (a latch: no wear in normal use) */
    fault(c, RIGCTL_FAULT_RESET);
}

void ctl_boot(ctl_t *c, uint8_t warm, uint8_t was_away, uint8_t reset_held, int16_t ratchet_g)
{
    c->ee_ratchet_g = ratchet_g;
    c->boot_load_check = 0;
    if (reset_held || (warm && was_away)) reset_latch(c);
    else if (!warm) c->boot_load_check = 1;
}

/* a cold boot decides at its first reading once the HX711's rate is timed (the converter settled): loaded against the
 * stored zero by more than the power-up tare accepts (TARE_ZERO_AGREE_G), the actuator may be pressing (a power cut
 * under load) or the cell's zero moved: either way nothing presses on it until the operator says which */
static void boot_load_check(ctl_t *c, int32_t raw)
{
    if (!c->boot_load_check || !c->hx_rate_0p01) return;
    c->boot_load_check = 0;
    if (c->zero_valid && load_g(c, raw, c->zero_raw) > TARE_ZERO_AGREE_G) reset_latch(c);
}

/* the warm-boot record: away from the moment the actuator may move towards the sensor (the force loop, HOME) until it
 * is proven back at home (homed, at rest, its step count at home or behind, or the switch closed with the count
 * within AWAY_HOME_UM of home: a back-off ends at the switch a few steps short of the count's zero) or CLEAR_FAULT */
#define AWAY_HOME_UM 100.0f
static uint8_t at_home_at_rest(const ctl_t *c)
{
    return c->homed && c->act_mode == ACT_MODE_HOLD &&
           (c->act_pos_steps <= 0 || (c->home_switch && act_pos_mm(c) * 1000.0f <= AWAY_HOME_UM));
}

static void away_watch(ctl_t *c)
{
    if (c->act_mode == ACT_MODE_FORCE || c->act_mode == ACT_MODE_HOMING) c->away = 1;
    else if (at_home_at_rest(c))
        c->away = 0;
}

static void reset_latch_clear(ctl_t *c)
{
    c->away = 0;
    c->ee_reset_held = 0;
}

/* ---- HX711 rate (spec 2.9) ---- */
/* the measured rate is the one HX711_RATE_SPS accepts (within RIGCTL_HX711_RATE_TOLERANCE_PCT) */
static uint8_t hx711_rate_ok(const ctl_t *c)
{
    uint32_t expected = (uint32_t)c->hreg[RIGCTL_HREG_HX711_RATE_SPS] * 100u;
    uint32_t dev = c->hx_rate_0p01 > expected ? c->hx_rate_0p01 - expected : expected - c->hx_rate_0p01;
    return c->hx_rate_0p01 && dev * 100u <= expected * RIGCTL_HX711_RATE_TOLERANCE_PCT;
}

/* the gains of the rate the loop runs at, into the PI (every update: a gain written while pressing applies) */
static void force_loop_gains(ctl_t *c)
{
    uint8_t slow = c->hreg[RIGCTL_HREG_HX711_RATE_SPS] < 40;
    uint16_t kp = c->hreg[slow ? RIGCTL_HREG_FORCE_KP_10SPS_NMS_G : RIGCTL_HREG_FORCE_KP_80SPS_NMS_G];
    uint16_t ki = c->hreg[slow ? RIGCTL_HREG_FORCE_KI_10SPS_NMS_GS : RIGCTL_HREG_FORCE_KI_80SPS_NMS_GS];
    c->pi.kp = (float)kp * 1e-6f; /* nm/s per g -> mm/s per g */
    c->pi.ki = (float)ki * 1e-6f;
}

/* The first ready edge is not timed from: the HX711 converts on its own from power-up, through an MCU reset and the
 * bootloader's wait (0.8 s on the Mega), so the sketch's first reading may have waited with DOUT low since before it
 * started, and its edge is not the end of a conversion (timed from it, the rate read up to one period in 4 high:
 * 95 SPS for an 80 SPS part under simavr with the bootloader, past the 20 % tolerance in a third of boots). The 4
 * periods are timed from the second edge. */
void ctl_hx711_ready(ctl_t *c, uint32_t t_us)
{
    /* once the rate is known, every reading is timed (spec 2.11): DOUT low sooner than HX711_CADENCE_PCT of the
     * period after the last reading is not a conversion (a broken SCK holds DOUT low: every read returns 0) */
    if (c->hx_rate_0p01 && c->hx_period_s > 0.0f && !(c->faults & RIGCTL_FAULT_HX711_CADENCE) &&
        (float)(uint32_t)(t_us - c->hx_last_us) * 100.0f < c->hx_period_s * 1e6f * (float)RIGCTL_HX711_CADENCE_PCT)
        fault(c, RIGCTL_FAULT_HX711_CADENCE);
    if (c->hx_edges >= 2 && c->hx_edges <= RIGCTL_HX711_RATE_PERIODS + 1) c->hx_sum_us += t_us - c->hx_last_us;
    c->hx_last_us = t_us;
    if (c->hx_edges <= RIGCTL_HX711_RATE_PERIODS + 1) c->hx_edges++;
    if (c->hx_edges == RIGCTL_HX711_RATE_PERIODS + 2 && !c->hx_rate_0p01 && c->hx_sum_us) {
        c->hx_period_s = (float)c->hx_sum_us * 1e-6f / (float)RIGCTL_HX711_RATE_PERIODS;
        c->hx_rate_0p01 = (uint16_t)(100.0f / c->hx_period_s + 0.5f);
        if (!hx711_rate_ok(c)) fault(c, RIGCTL_FAULT_HX711_RATE);
    }
}

static uint8_t fault_persists(const ctl_t *c)
{
    if ((uint32_t)(c->now_ms - c->last_loadcell_ms) > RIGCTL_LOADCELL_TIMEOUT_MS) return 1;
    if (c->tared && c->force_gf > (float)c->hreg[RIGCTL_HREG_FORCE_LIMIT_G]) return 1;
    if (c->hx_rate_0p01 && !hx711_rate_ok(c)) return 1;
    if (c->estop_open) return 1;
    return 0;
}

/* ---- contact stiffness (spec 2.10) ---- */
static float hx_period(const ctl_t *c)
{
    return c->hx_period_s > 0.0f ? c->hx_period_s : 1.0f / (float)c->hreg[RIGCTL_HREG_HX711_RATE_SPS];
}

/* the loop's crossover is k x Kp; with the HX711's delay D it lags k Kp D radians more than an integrator: the
 * stiffest contact held is LOOP_PHASE / (Kp D) */
uint16_t ctl_stiffness_max(const ctl_t *c)
{
    uint8_t slow = c->hreg[RIGCTL_HREG_HX711_RATE_SPS] < 40;
    float kp = (float)c->hreg[slow ? RIGCTL_HREG_FORCE_KP_10SPS_NMS_G : RIGCTL_HREG_FORCE_KP_80SPS_NMS_G] * 1e-6f;
    float d = hx_period(c) * (float)RIGCTL_HX711_DELAY_PERIODS_X10 * 0.1f;
    float k = (float)RIGCTL_LOOP_PHASE_MRAD * 1e-3f / (kp * d);
    return kp <= 0.0f || k >= 65535.0f ? 65535u : (uint16_t)k;
}

/* the probed stiffness is one the loop holds with its gains and one a rig config accepts (the probe's speed is derived
 * from the latter: spec 2.10) */
static uint8_t stiffness_ok(const ctl_t *c)
{
    return !c->stiffness_g_mm ||
           (c->stiffness_g_mm <= ctl_stiffness_max(c) && c->stiffness_g_mm <= RIGCTL_CONTACT_STIFFNESS_MAX_G_MM);
}

/* the probe's speed: PROBE_TRAVEL_UM in the time the trip looks ahead, so a contact is seen within that travel */
static float probe_speed(const ctl_t *c)
{
    float v = (float)RIGCTL_PROBE_TRAVEL_UM * 1e-3f / ((float)RIGCTL_FORCE_LEAD_PERIODS * hx_period(c));
    return v < ACT_MAX_SPEED_MM_S ? v : ACT_MAX_SPEED_MM_S;
}

/* the approach of a press to a contact located by an earlier probe (kept across a release): at the loop's clamp speed
 * up to PROBE_LOCATED_MARGIN_UM before its zero-force point, at the probe's speed from there (2.11) */
static uint8_t approach_fast(const ctl_t *c)
{
    float margin = (float)RIGCTL_PROBE_LOCATED_MARGIN_UM * 1e-3f * (float)c->hreg[RIGCTL_HREG_ACTUATOR_STEPS_PER_MM];
    return c->contact_located && (float)c->act_pos_steps < c->located_x0_steps - margin;
}

/* the reading's scale checked against something other than the reading (spec 2.12, issue 75): a load cell's gain or
 * range, or a wrong calibration saved with a valid checksum, scales the reading and the probed stiffness together, so
 * FORCE_LIMIT and POSITION_LIMIT both allow 1/X of the true force. The contact's stiffness stored with the calibration
 * (CALIBRATION_STIFFNESS_G_PER_MM, EEPROM: measured when the scale was verified with a reference mass) is the contact's
 * own, whatever the reading: the probe's over it outside 100/(100 + SCALE_CHECK_PCT) .. (100 + SCALE_CHECK_PCT)/100
 * is a scale that disagrees. None stored (0): no check (the host's doctor says so) */
static uint8_t scale_disagrees(const ctl_t *c)
{
    uint32_t ref = c->hreg[RIGCTL_HREG_CALIBRATION_STIFFNESS_G_PER_MM], k = c->stiffness_g_mm;
    if (!ref) return 0;
    return k * 100u > ref * (100u + RIGCTL_SCALE_CHECK_PCT) || ref * 100u > k * (100u + RIGCTL_SCALE_CHECK_PCT);
}

/* one reading while the probe runs: approach until contact, settle, step PROBE_STEP_UM, settle, k = dF / dx */
/* the load at which the probe's approach has found the contact: PROBE_CONTACT_G, or half the setpoint if less */
static float contact_g(const ctl_t *c)
{
    float contact = (float)RIGCTL_PROBE_CONTACT_G, half = 0.5f * (float)c->hreg[RIGCTL_HREG_FORCE_SETPOINT_G];
    return half < contact ? half : contact;
}

/* a press commanded with no force rise within its travel (spec 2.13, issue 75 item 5): the approach to a contact an
 * earlier probe located has gone PROBE_LOCATED_MARGIN_UM past its zero-force point, plus the travel that presses the
 * probe's contact load at its stiffness, and the reading has not shown the contact (it reads under PRESS_DIR_G: a
 * load of that much is the contact found late, a slipping coupling or the 10 SPS reading's lag, which the probe takes
 * on from here): the cell reads no load (a broken cell or excitation lead), the screw did not go where its steps say
 * (a slipping coupling, lost steps, a reversed motor) or the plate is gone. The bound is the fast approach's own
 * margin on the other side of the contact; the true force there is at most the probe's contact load plus
 * k x PROBE_LOCATED_MARGIN_UM (1,550 g at 5 kg/mm) on a cell that reads nothing, and a wound-up coupling that
 * catches up brings the screw no further than where the steps put the motor */
static uint8_t contact_missing(const ctl_t *c)
{
    float past = (float)RIGCTL_PROBE_LOCATED_MARGIN_UM * 1e-3f * (float)c->hreg[RIGCTL_HREG_ACTUATOR_STEPS_PER_MM];
    if (!c->contact_located || c->probe_phase != PROBE_APPROACH || c->located_k_g_per_step <= 0.0f) return 0;
    if ((c->force_gf < 0.0f ? -c->force_gf : c->force_gf) >= (float)RIGCTL_PRESS_DIR_G) return 0;
    return (float)c->act_pos_steps > c->located_x0_steps + past + contact_g(c) / c->located_k_g_per_step;
}

/* the reading's zero off the contact (spec 2.13, issue 75 item 5): a force that moves with no step. The tare is taken
 * at home; a press that starts there at rest (as the warm-boot record's "at home" says) first judges its reading,
 * settled (HX711_RATE_PERIODS + 1 readings with the actuator still), against it: off by more than PRESS_DIR_G (the
 * smallest change of load the direction watch takes for motion) the cell's zero moved (a cell overloaded or knocked,
 * a lead's joint, its mount) or something loads the sensor (a hand, a tool, debris), and the probe would find a
 * contact that is not there (775401: +302 g between trials at a setpoint of 307 g, the trial recorded without
 * contact on firmware 1.6) or the direction watch a motor turning the wrong way (a zero 10 g low: the load falls as
 * the press approaches). Judged at the press's start, where it matters: a hand resting on the rig between presses is
 * no fault. 8 g is 10 sd of the model's 0.8 g a reading and ~80 sd of a real HX711's (50-90 nV rms at gain 128,
 * 20-40 counts, ~0.1 g at 420 counts/g); off the contact the drum's runout (20 um: 100 g at 5 kg/mm) does not reach
 * the cell; a cell's zero drifts ~0.02 % of its range per 10 K (1 g on a 5 kg cell). */
/* a probe whose steps went forward where the contact's stiffness stored with the calibration says they press half of
 * PROBE_REFINE_G or more, and the load rose by less than a quarter of that (ZERO_RISE_DIV): the load its approach read
 * is not the contact's (the reading's zero moved on the way, or nothing is there; its steps may just reach the real
 * contact: a zero moved by 302 g 0.7 mm before a 442 g/mm contact rose 8.3 g over the steps' 0.52 mm under simavr,
 * which a flat 8 g let through to a press holding 5 g true). A quarter lies below what the bill of materials' other
 * faults leave of the rise (a cell's gain down to 0.3, lost steps up to 60 %: 0.4), which the scale check names */
#define ZERO_RISE_DIV 4.0f
static uint8_t probe_found_nothing(const ctl_t *c, float rise_g, float dx_mm)
{
    float ref = (float)c->hreg[RIGCTL_HREG_CALIBRATION_STIFFNESS_G_PER_MM];
    return ref * dx_mm >= 0.5f * (float)RIGCTL_PROBE_REFINE_G && rise_g * ZERO_RISE_DIV < ref * dx_mm;
}

static void probe_reading(ctl_t *c, float f)
{
    float contact = contact_g(c), half = 0.5f * (float)c->hreg[RIGCTL_HREG_FORCE_SETPOINT_G];
    float spmm = (float)c->hreg[RIGCTL_HREG_ACTUATOR_STEPS_PER_MM];
    c->act_vel_mm_s = 0.0f;
    if (c->probe_phase == PROBE_ZERO) { /* ctl_loadcell judged the settled reading: approach from this one */
        if (c->still_readings <= RIGCTL_HX711_RATE_PERIODS) return;
        c->probe_phase = PROBE_APPROACH;
    }
    switch (c->probe_phase) {
    case PROBE_APPROACH:
        if (f < contact) c->act_vel_mm_s = approach_fast(c) ? ACT_MAX_SPEED_MM_S : probe_speed(c);
        else c->probe_phase = PROBE_SETTLE1, c->probe_readings = 0;
        return;
    case PROBE_STEP: /* ctl_tick stops it at the target */
    case PROBE_STEP2:
        c->act_vel_mm_s = probe_speed(c);
        return;
    default: /* settling: the reading at the 5th edge after the stop averages only the new position (4 periods) */
        if (++c->probe_readings <= RIGCTL_HX711_RATE_PERIODS) return;
        if (c->probe_phase == PROBE_SETTLE1) {
            c->probe_f1_gf = f;
            c->probe_x1_steps = c->act_pos_steps;
            c->probe_x_target = c->act_pos_steps + (int32_t)((float)RIGCTL_PROBE_STEP_UM * 1e-3f * spmm + 0.5f);
            c->probe_phase = PROBE_STEP;
            c->act_vel_mm_s = probe_speed(c);
        } else {
            float dx = (float)(c->act_pos_steps - c->probe_x1_steps) / spmm;
            float k = dx > 0.0f ? (f - c->probe_f1_gf) / dx : 0.0f;
            float refine = (float)RIGCTL_PROBE_REFINE_G;
            if (refine > half) refine = half;
            c->stiffness_g_mm = k >= 65535.0f ? 65535u : (k < 1.0f ? 1u : (uint16_t)k);
            if (!stiffness_ok(c)) { /* backs off: the loop cannot hold it */
                c->probe_phase = PROBE_NONE;
                force_pi_reset(&c->pi);
                fault(c, RIGCTL_FAULT_CONTACT_STIFFNESS);
                return;
            }
            if (c->probe_phase == PROBE_SETTLE2 && f - c->probe_f1_gf < refine) {
                /* a step too short for the stiffness to be known well: a second one sized from the first to bring
                 * the rise to PROBE_REFINE_G (at most 0.5 mm), then k over both (spec 2.11). Skipped only when the
                 * first rose PROBE_REFINE_G itself (a contact stiffer than the loop holds): a first step that rose
                 * 50-100 g (1.7-3.3 kg/mm) spans 12 microsteps, whose +-1 of the screw's position against the count
                 * read 2 kg/mm as 1.91-2.20 kg/mm (the model rig, 12 seeds, 80 SPS; a CI run's 2,201) */
                float k1 = k < 200.0f ? 200.0f : k, dx2 = (refine - (f - c->probe_f1_gf)) / k1;
                if (dx2 > 0.5f) dx2 = 0.5f;
                c->probe_x_target = c->act_pos_steps + (int32_t)(dx2 * spmm + 0.5f);
                c->probe_phase = PROBE_STEP2;
                c->act_vel_mm_s = probe_speed(c);
                return;
            }
            c->probe_phase = PROBE_NONE;
            force_pi_reset(&c->pi);
            if (probe_found_nothing(c, f - c->probe_f1_gf, dx)) {
                fault(c, RIGCTL_FAULT_LOADCELL_ZERO);
                return;
            }
            if (k < 1.0f) k = 1.0f;
            c->contact_k_g_per_step = k / spmm;
            c->contact_x0_steps = (float)c->probe_x1_steps - c->probe_f1_gf / c->contact_k_g_per_step;
            c->contact_valid = 1;
            c->contact_located = 1;
            c->located_x0_steps = c->contact_x0_steps;
            /* its stiffness bounds CONTACT_MISSING's travel past it (2.13) only where the probe measured one: its
             * steps pressed half of PROBE_REFINE_G or more (the scale check's own condition, which also holds it to
             * the stiffness stored with the calibration). A probe at a tiny setpoint (a RUN at 0 g: the contact "found"
             * at 0 g wherever the actuator stood), or one that took a load resting on the cell for the contact,
             * measures noise: 38 g/mm where the contact was 1 kg/mm, and the next press latched CONTACT_MISSING with
             * no contact ever there (the conformance suite, the model rig) */
            c->located_k_g_per_step =
                f - c->probe_f1_gf >= 0.5f * (float)RIGCTL_PROBE_REFINE_G ? c->contact_k_g_per_step : 0.0f;
            /* the probe's measuring step(s) went forward and the settled load rose with them: the way is proven for
             * the rest of this press (spec 2.11), until the release, HOME, a fault or the watch's evidence against */
            c->press_dir_held = f - c->probe_f1_gf >= (float)RIGCTL_PRESS_DIR_G;
            /* before any press past the probe's force: the way proven by the step(s), it backs off home. Only a probe
             * whose steps pressed half of PROBE_REFINE_G or more measures the stiffness within the tolerance (a
             * setpoint under 100 g, a RUN at 0 g: not checked; the next press at a force checks it) */
            if (f - c->probe_f1_gf >= 0.5f * (float)RIGCTL_PROBE_REFINE_G && scale_disagrees(c))
                fault(c, RIGCTL_FAULT_LOADCELL_SCALE);
        }
        return;
    }
}

/* the force loop never commands a speed whose rise the trip would extrapolate past the limit (spec 2.11, issue 75:
 * fault-free presses of 1,400 g on a 2,400 g/mm mount the probe accepts latched FORCE_LIMIT on the loop's own
 * approach, its clamp speed rising 150 g a period there). The force now is the most of the contact's at the position
 * (the probe's k and zero-force point), the reading plus k x the travel since the force it shows (2 periods ago, the
 * sinc^4's delay: the probe's k errs on that short travel only) and the reading itself,
 * and a speed v raises the reading k v T a period, which the trip extrapolates FORCE_LEAD_PERIODS ahead; so the speed
 * towards the sensor is held to (FORCE_LIMIT_G - FORCE_TOLERANCE_G - F) / (k (LEAD + 1) T). Without a probed contact
 * (never while the loop drives: it runs after the probe) the reading and the stiffest contact the loop holds. */
static float limit_governor(const ctl_t *c, float f, float v)
{
    float spmm = (float)c->hreg[RIGCTL_HREG_ACTUATOR_STEPS_PER_MM];
    float k = c->contact_valid ? c->contact_k_g_per_step * spmm : (float)ctl_stiffness_max(c);
    float f_pos = c->contact_valid ? ((float)c->act_pos_steps - c->contact_x0_steps) * c->contact_k_g_per_step : f;
    float f_now = f, room;
    if (c->press_dir_n >= 3) /* the reading plus the travel since the true force it shows (2 periods: sinc^4) */
        f_now = f + k * (float)(c->act_pos_steps - c->press_dir_steps[c->press_dir_n - 3]) / spmm;
    if (f_pos > f_now) f_now = f_pos;
    if (f > f_now) f_now = f;
    room = (float)c->hreg[RIGCTL_HREG_FORCE_LIMIT_G] - (float)c->hreg[RIGCTL_HREG_FORCE_TOLERANCE_G] - f_now;
    float vmax = room > 0.0f ? room / (k * (float)(RIGCTL_FORCE_LEAD_PERIODS + 2) * hx_period(c)) : 0.0f;
    return v > vmax ? vmax : v;
}

static void engage(ctl_t *c)
{
    force_pi_reset(&c->pi);
    press_dir_forget(c);
    c->press_dir_leave = c->homed && c->home_switch; /* HOME's switch proof stands until the contact (2.11) */
    c->probe_phase = c->contact_valid ? PROBE_NONE : PROBE_APPROACH; /* every press from rest probes (2.11) */
    if (c->probe_phase == PROBE_APPROACH && at_home_at_rest(c) && c->tared)
        c->probe_phase = PROBE_ZERO; /* from home at rest: its reading's zero first (2.13) */
    c->force_prev_valid = 0;
    c->act_mode = ACT_MODE_FORCE;
    c->state = RIGCTL_STATE_SEEKING_FORCE;
    c->on_target = 0;
}

static void start_drum(ctl_t *c)
{
    c->drum_on = 1;
    c->run_start_ms = c->now_ms;
    c->state = RIGCTL_STATE_RUNNING;
}

/* is command `cmd` allowed now? docs/wire-protocol.md's command table (command-states) says it cell by cell, and
 * tests/firmware/test_fw_command_table.py walks every (state, command) pair against this function built for the host */
static uint8_t command_allowed(const ctl_t *c, uint16_t cmd)
{
    uint8_t s = c->state;
    switch (cmd) {
    case RIGCTL_CMD_NONE:
    case RIGCTL_CMD_STOP:
    case RIGCTL_CMD_SAVE_CALIBRATION:
        return 1;
    case RIGCTL_CMD_RUN:
    case RIGCTL_CMD_PRESS: /* never after a reset, e-stop or failed HOME until HOME has succeeded */
        return s != RIGCTL_STATE_FAULT && s != RIGCTL_STATE_HOMING && s != RIGCTL_STATE_NOT_HOMED &&
               hx711_rate_ok(c) && stiffness_ok(c) && !c->calib_defaults; /* no pressing on a guess (2.11) */
    case RIGCTL_CMD_STOP_DRUM:
        return force_engaged(c);
    case RIGCTL_CMD_TARE: /* only at home (switch closed), with no load on the cell once a tare is known */
        return (s == RIGCTL_STATE_IDLE || s == RIGCTL_STATE_NOT_HOMED) && c->home_switch &&
               (!c->tared || c->force_gf < 2.0f * (float)c->hreg[RIGCTL_HREG_FORCE_TOLERANCE_G]);
    case RIGCTL_CMD_HOME: /* from IDLE only with the actuator released (no load on the cell); NOT_HOMED: unless the
                           * cell is loaded past the limit (a direction unknown could only press it further, 2.11) */
        if (home_overloaded(c) || c->boot_load_check) return 0; /* nor before a cold boot's load is judged (2.7) */
        return s == RIGCTL_STATE_NOT_HOMED ||
               (s == RIGCTL_STATE_IDLE && c->force_gf < 2.0f * (float)c->hreg[RIGCTL_HREG_FORCE_TOLERANCE_G]);
    case RIGCTL_CMD_CLEAR_FAULT:
        return !fault_persists(c);
    default:
        return 0;
    }
}

static void run_command(ctl_t *c, uint16_t cmd)
{
    switch (cmd) {
    case RIGCTL_CMD_RUN: /* engages the force loop if needed; the drum starts at once */
        if (!force_engaged(c)) engage(c);
        start_drum(c);
        break;
    case RIGCTL_CMD_STOP:
        c->drum_on = 0;
        release_actuator(c);
        force_pi_reset(&c->pi);
        if (c->state != RIGCTL_STATE_FAULT) c->state = c->homed ? RIGCTL_STATE_IDLE : RIGCTL_STATE_NOT_HOMED;
        break;
    case RIGCTL_CMD_TARE:
        c->tare_pending = 1;
        break;
    case RIGCTL_CMD_HOME:
        c->act_mode = ACT_MODE_HOMING;
        c->state = RIGCTL_STATE_HOMING;
        c->home_start_ms = c->now_ms;
        c->home_start_steps = c->act_pos_steps;
        c->home_phase = HOME_SEEK;
        c->home_creep = !c->homed; /* from an unknown position: creep until the force proves the way (2.11) */
        c->contact_valid = 0;
        c->contact_located = 0; /* HOME (the host's after a plate change too): the next press locates it again */
        move_watch_start(c, 0);
        break;
    case RIGCTL_CMD_CLEAR_FAULT:
        if (c->faults & RIGCTL_FAULT_ESTOP) c->estop_release = 1;
        c->faults = 0;
        reset_latch_clear(c);
        if (c->state == RIGCTL_STATE_FAULT) c->state = c->homed ? RIGCTL_STATE_IDLE : RIGCTL_STATE_NOT_HOMED;
        break;
    case RIGCTL_CMD_PRESS:
        if (!force_engaged(c)) engage(c);
        break;
    case RIGCTL_CMD_STOP_DRUM:
        c->drum_on = 0;
        c->state = RIGCTL_STATE_SEEKING_FORCE;
        c->on_target = 0;
        break;
    case RIGCTL_CMD_SAVE_CALIBRATION:
        c->save_calibration = 1;
        break;
    default:
        break;
    }
}

uint16_t ctl_read_holding(void *ctx, uint16_t addr)
{
    const ctl_t *c = (const ctl_t *)ctx;
    return addr < RIGCTL_N_HOLDING ? c->hreg[addr] : 0;
}

/* the build id (docs/wire-protocol.md 2.2, BUILD_ID_0 .. _2): make BUILD_ID=<hex> passes it as RIGCTL_BUILD_ID_NUM
 * (rigctl's builds give the sources' digest); a build without one reports 0 */
#ifndef RIGCTL_BUILD_ID_NUM
#define RIGCTL_BUILD_ID_NUM 0ULL
#endif

static uint16_t s16(float v)
{
    long r = (long)(v < 0 ? v - 0.5f : v + 0.5f);
    if (r > 32767) r = 32767;
    if (r < -32768) r = -32768;
    return (uint16_t)(int16_t)r;
}

uint16_t ctl_read_input(void *ctx, uint16_t addr)
{
    const ctl_t *c = (const ctl_t *)ctx;
    switch (addr) {
    case RIGCTL_IREG_FORCE_G: return (uint16_t)c->force_g;
    case RIGCTL_IREG_SPEED_0P1MMS: return s16(c->drum_actual_mm_s * 10.0f);
    case RIGCTL_IREG_DRUM_ANGLE_0P01DEG:
        return (uint16_t)((uint32_t)c->drum_step_in_rev * 36000UL / DRUM_USTEPS_PER_REV);
    case RIGCTL_IREG_DRUM_REVOLUTIONS: return c->drum_revolutions;
    case RIGCTL_IREG_ACTUATOR_POSITION_0P01MM: return s16(act_pos_mm(c) * 100.0f);
    case RIGCTL_IREG_STATE: return c->state;
    case RIGCTL_IREG_FAULT_BITS: return (uint16_t)(c->faults & 0xFFFFu);
    case RIGCTL_IREG_FAULT_BITS_HI: return (uint16_t)(c->faults >> 16);
    case RIGCTL_IREG_FIRMWARE_VERSION: return RIGCTL_MEGA_FIRMWARE_VERSION;
    case RIGCTL_IREG_HEARTBEAT: return (uint16_t)(c->now_ms / 10);
    case RIGCTL_IREG_SPEED_TARGET_0P1MMS: return c->speed_target_0p1;
    case RIGCTL_IREG_LOADCELL_RAW_HI: return (uint16_t)((uint32_t)c->loadcell_raw >> 16);
    case RIGCTL_IREG_LOADCELL_RAW_LO: return (uint16_t)((uint32_t)c->loadcell_raw & 0xFFFF);
    case RIGCTL_IREG_FORCE_SETPOINT_ACTIVE_G:
        return force_engaged(c) ? c->hreg[RIGCTL_HREG_FORCE_SETPOINT_G] : 0;
    case RIGCTL_IREG_HX711_RATE_0P01SPS: return c->hx_rate_0p01;
    case RIGCTL_IREG_INDEX_SOURCE: return c->index_source;
    case RIGCTL_IREG_INDEX_PERIOD_MS: return c->index_period_ms;
    case RIGCTL_IREG_INDEX_STEPS: return c->index_steps;
    case RIGCTL_IREG_INDEX_COUNT: return c->index_count;
    case RIGCTL_IREG_MARK_PERIOD_0P1MS: return c->mark_period_0p1ms;
    case RIGCTL_IREG_MARK_STEPS: return c->mark_steps;
    case RIGCTL_IREG_MARK_COUNT: return c->mark_count;
    case RIGCTL_IREG_CONTACT_STIFFNESS_G_PER_MM: return c->stiffness_g_mm;
    case RIGCTL_IREG_STIFFNESS_MAX_G_PER_MM: return ctl_stiffness_max(c);
    case RIGCTL_IREG_RESET_CAUSE: return c->reset_cause;
    case RIGCTL_IREG_BOOT_COUNT: return c->boot_count;
    case RIGCTL_IREG_BUILD_ID_0: return (uint16_t)((RIGCTL_BUILD_ID_NUM >> 32) & 0xFFFF);
    case RIGCTL_IREG_BUILD_ID_1: return (uint16_t)((RIGCTL_BUILD_ID_NUM >> 16) & 0xFFFF);
    case RIGCTL_IREG_BUILD_ID_2: return (uint16_t)(RIGCTL_BUILD_ID_NUM & 0xFFFF);
    case RIGCTL_IREG_STATUS_FLAGS:
        return (uint16_t)((c->calib_defaults ? RIGCTL_STATUS_CALIBRATION_DEFAULTS : 0) |
                          (c->homed ? RIGCTL_STATUS_HOMED : 0) | (c->drivers_on ? RIGCTL_STATUS_DRIVERS_ENABLED : 0) |
                          (c->estop_open ? RIGCTL_STATUS_ESTOP_OPEN : 0) |
                          (c->home_switch ? RIGCTL_STATUS_HOME_SWITCH : 0) | (c->tared ? RIGCTL_STATUS_TARED : 0));
    default: return 0;
    }
}

uint8_t ctl_write_holding(void *ctx, uint16_t start, uint16_t n, const uint16_t *values)
{
    ctl_t *c = (ctl_t *)ctx;
    uint16_t cand[RIGCTL_N_HOLDING];
    uint16_t i, cmd = RIGCTL_CMD_NONE;
    uint8_t cmd_written = 0, w12 = 0, whi = 0, wlo = 0;
    if ((uint32_t)start + n > RIGCTL_N_HOLDING) return RIGCTL_MB_EX_ILLEGAL_ADDRESS;
    for (i = 0; i < RIGCTL_N_HOLDING; i++) cand[i] = c->hreg[i];
    for (i = 0; i < n; i++) {
        uint16_t a = (uint16_t)(start + i);
        if (values[i] < hreg_min[a] || values[i] > hreg_max[a]) return RIGCTL_MB_EX_ILLEGAL_VALUE;
        if (a == RIGCTL_HREG_HX711_RATE_SPS && values[i] != 10 && values[i] != 80) return RIGCTL_MB_EX_ILLEGAL_VALUE;
        cand[a] = values[i];
        if (a == RIGCTL_HREG_LOADCELL_SCALE_X100) w12 = 1;
        if (a == HI) whi = 1;
        if (a == LO) wlo = 1;
        if (a == RIGCTL_HREG_COMMAND) {
            cmd = values[i];
            cmd_written = 1;
        }
    }
    /* a setpoint written now must respect the limits as they stand after this write */
    for (i = 0; i < n; i++) {
        uint16_t a = (uint16_t)(start + i);
        if ((a == RIGCTL_HREG_SPEED_SETPOINT_0P1MMS || a == RIGCTL_HREG_RAMP_START_SPEED_0P1MMS ||
             a == RIGCTL_HREG_RAMP_END_SPEED_0P1MMS) &&
            cand[a] > cand[RIGCTL_HREG_SPEED_LIMIT_0P1MMS])
            return RIGCTL_MB_EX_ILLEGAL_VALUE;
        if (a == RIGCTL_HREG_FORCE_SETPOINT_G && cand[a] > cand[RIGCTL_HREG_FORCE_LIMIT_G])
            return RIGCTL_MB_EX_ILLEGAL_VALUE;
    }
    /* the 32-bit scale: HI and LO together, in range; register 12 (its 16-bit view) must agree when written too */
    if (whi != wlo) return RIGCTL_MB_EX_ILLEGAL_VALUE;
    if (whi) {
        int32_t s = scale_of(cand);
        if (!scale_ok(s) || (w12 && s != (int32_t)cand[RIGCTL_HREG_LOADCELL_SCALE_X100])) return RIGCTL_MB_EX_ILLEGAL_VALUE;
        set_scale(cand, s);
    } else if (w12) {
        if (!scale_ok((int32_t)cand[RIGCTL_HREG_LOADCELL_SCALE_X100])) return RIGCTL_MB_EX_ILLEGAL_VALUE;
        set_scale(cand, (int32_t)cand[RIGCTL_HREG_LOADCELL_SCALE_X100]);
    }
    if (cmd_written && !command_allowed(c, cmd)) return RIGCTL_MB_EX_ILLEGAL_VALUE;
    cand[RIGCTL_HREG_COMMAND] = RIGCTL_CMD_NONE; /* reads back 0 once accepted */
    if (cand[RIGCTL_HREG_FORCE_SETPOINT_G] != c->hreg[RIGCTL_HREG_FORCE_SETPOINT_G] &&
        (c->state == RIGCTL_STATE_SEEKING_FORCE || c->state == RIGCTL_STATE_FORCE_SETTLED)) {
        c->state = RIGCTL_STATE_SEEKING_FORCE; /* a new setpoint must settle again */
        c->on_target = 0;
    }
    for (i = 0; i < RIGCTL_N_HOLDING; i++) c->hreg[i] = cand[i];
    if (c->hx_rate_0p01 && !hx711_rate_ok(c) && !(c->faults & RIGCTL_FAULT_HX711_RATE))
        fault(c, RIGCTL_FAULT_HX711_RATE); /* a rate the HX711 does not have: the loop must not run */
    if (cmd_written) run_command(c, cmd);
    return 0;
}

void ctl_bind_modbus(ctl_t *c, mb_slave_t *mb)
{
    mb->device_id = RIGCTL_DRUM_DEVICE_ID;
    mb->n_holding = RIGCTL_N_HOLDING;
    mb->n_input = RIGCTL_N_INPUT;
    mb->ctx = c;
    mb->read_holding = ctl_read_holding;
    mb->read_input = ctl_read_input;
    mb->write_holding = ctl_write_holding;
}

void ctl_feed_watchdog(ctl_t *c)
{
    c->last_request_ms = c->now_ms;
}

static float profile_target_mm_s(ctl_t *c)
{
    uint16_t target;
    if (!c->drum_on) {
        target = 0;
    } else if (c->hreg[RIGCTL_HREG_SPEED_PROFILE] == RIGCTL_PROFILE_RAMP) {
        uint32_t t = c->now_ms - c->run_start_ms;
        uint32_t d = c->hreg[RIGCTL_HREG_RAMP_DURATION_MS];
        int32_t a = c->hreg[RIGCTL_HREG_RAMP_START_SPEED_0P1MMS];
        int32_t b = c->hreg[RIGCTL_HREG_RAMP_END_SPEED_0P1MMS];
        if (t >= d) target = (uint16_t)b;
        else target = (uint16_t)(a + (int32_t)(((int64_t)(b - a) * (int64_t)t) / (int64_t)d));
    } else {
        target = c->hreg[RIGCTL_HREG_SPEED_SETPOINT_0P1MMS];
    }
    if (target > c->hreg[RIGCTL_HREG_SPEED_LIMIT_0P1MMS]) target = c->hreg[RIGCTL_HREG_SPEED_LIMIT_0P1MMS];
    c->speed_target_0p1 = target;
    return (float)target * 0.1f;
}

/* the longest a creeping HOME may take beyond HOME_TIMEOUT_MS: its whole travel limit at the creep speed, s */
static float home_creep_s(const ctl_t *c)
{
    return ACT_HOME_MAX_TRAVEL_MM * hx_period(c) / ((float)RIGCTL_HOME_CREEP_UM * 1e-3f);
}

/* HOME (spec 2.5): back until the switch closes (25 mm / 10 s budget: HOME_NOT_FOUND), then prove the direction:
 * leave home until the switch opens (within HOME_PROOF_MM, else ACTUATOR_DIRECTION: a reversed motor drives into the
 * rear stop and the switch stays closed) and come back until it closes again; only then zero and tare. */
static void home_step(ctl_t *c, uint32_t now_ms)
{
    float spmm = (float)c->hreg[RIGCTL_HREG_ACTUATOR_STEPS_PER_MM];
    int32_t moved = c->act_pos_steps - c->home_phase_steps; /* + towards the sensor */
    uint8_t late = (uint32_t)(now_ms - c->home_start_ms) >= ACT_HOME_TIMEOUT_MS;
    switch (c->home_phase) {
    case HOME_SEEK:
        if (c->home_switch) {
            c->home_creep = 0;
            c->home_phase = HOME_LEAVE;
            c->home_phase_steps = c->act_pos_steps;
            c->act_vel_mm_s = 0.0f; /* the next tick leaves creeping (or not at all: the ratchet) */
            return;
        }
        if ((float)(c->home_start_steps - c->act_pos_steps) >= ACT_HOME_MAX_TRAVEL_MM * spmm ||
            (late && !c->home_creep) ||
            (float)(uint32_t)(now_ms - c->home_start_ms) >= (float)ACT_HOME_TIMEOUT_MS + 1000.0f * home_creep_s(c))
            break;
        /* creeping: HOME_CREEP_UM per HX711 period, so a load growing the wrong way is read before it is large
         * (the timeout runs from the end of the creep; the travel limit bounds it) */
        c->act_vel_mm_s = c->home_creep ? -(float)RIGCTL_HOME_CREEP_UM * 1e-3f / hx_period(c) : -ACT_HOME_SPEED_MM_S;
        return;
    case HOME_LEAVE:
        /* it leaves creeping (HOME_CREEP_UM per HX711 period, the load watched at HOME_RISE_G: ctl_loadcell) and the
         * switch must open within HOME_LEAVE_UM, before any fast move (issue 75: a switch stuck closed walked the
         * actuator 2 mm into the sensor at 3 mm/s on every acknowledged HOME); never past the ratchet */
        if (!c->home_switch) {
            c->home_phase = HOME_RETURN;
            c->home_leave_steps = moved;
            c->home_phase_steps = c->act_pos_steps;
            c->act_vel_mm_s = -ACT_HOME_SPEED_MM_S;
        } else if ((c->ratchet_valid && c->act_pos_steps >= c->ratchet_steps) || load_ratchet_reached_now(c)) {
            break; /* the switch reads closed where the last latch stopped the actuator: it is not home */
        } else if ((float)moved >= (float)RIGCTL_HOME_LEAVE_UM * 1e-3f * spmm) {
            /* left creeping, the switch still closed and no load risen: the motor turns the other way (into its rear
             * stop: the count is not the position, so no ratchet from it), or the switch is stuck closed off the
             * contact (the next HOME creeps on; the load watch latches at the contact, with its ratchet) */
            uint8_t had = c->ratchet_valid;
            int32_t at = c->ratchet_steps;
            direction_fault(c);
            c->ratchet_valid = had;
            c->ratchet_steps = at;
        } else {
            c->act_vel_mm_s = (float)RIGCTL_HOME_CREEP_UM * 1e-3f / hx_period(c);
        }
        return;
    default: /* HOME_RETURN */
        if (c->home_switch) {
            /* home: zero the position, then tare on the next reading (ctl_loadcell ends HOMING: IDLE is tared); the
             * switch proven (left and returned), the ratchet is released, the load ratchet too */
            c->ratchet_valid = 0;
            c->ee_ratchet_g = 0;
            c->act_vel_mm_s = 0.0f;
            c->act_mode = ACT_MODE_HOLD;
            c->zero_position = 1;
            c->act_pos_steps = 0;
            c->tare_pending = 1;
            return;
        }
        if ((float)(-moved - c->home_leave_steps) >= (float)RIGCTL_HOME_PROOF_MM * spmm || late) break;
        c->act_vel_mm_s = -ACT_HOME_SPEED_MM_S;
        return;
    }
    c->homed = 0; /* a broken switch wire, a stalled motor: do not drive into the rear stop for ever */
    fault(c, RIGCTL_FAULT_HOME_NOT_FOUND);
}

void ctl_tick(ctl_t *c, uint32_t now_ms)
{
    float dt = (float)(uint32_t)(now_ms - c->now_ms) * 0.001f;
    c->now_ms = now_ms;
    if (dt > 0.1f) dt = 0.1f;

    if (c->drum_slip && !(c->faults & RIGCTL_FAULT_DRUM_SLIP)) {
        fault(c, RIGCTL_FAULT_DRUM_SLIP); /* the drum stops on its ramp, the actuator backs off */
    }
    c->drum_slip = 0;
    if (c->state != RIGCTL_STATE_FAULT) {
        if ((uint32_t)(now_ms - c->last_loadcell_ms) > RIGCTL_LOADCELL_TIMEOUT_MS) {
            fault(c, RIGCTL_FAULT_LOADCELL_TIMEOUT);
        } else if ((force_engaged(c) || c->drum_cmd_mm_s > 0.0f) &&
                   (uint32_t)(now_ms - c->last_request_ms) > c->hreg[RIGCTL_HREG_WATCHDOG_MS]) {
            fault(c, RIGCTL_FAULT_WATCHDOG);
        }
    }

    /* drum: profile target through the acceleration ramp */
    c->drum_cmd_mm_s = steprate_ramp(c->drum_cmd_mm_s, profile_target_mm_s(c), DRUM_ACCEL_MM_S2, dt);

    /* actuator */
    switch (c->act_mode) {
    case ACT_MODE_RETRACT:
        if (c->act_pos_steps <= 0 || c->home_switch) {
            c->act_vel_mm_s = 0.0f;
            c->act_mode = ACT_MODE_HOLD;
        } else if (c->backoff_phase == BACKOFF_STEP && c->act_pos_steps <= c->backoff_target_steps) {
            c->act_vel_mm_s = 0.0f; /* the proof step is done: hold until the HX711 has settled on it */
            c->backoff_phase = BACKOFF_SETTLE;
            backoff_settle_restart(c);
        } else {
            c->act_vel_mm_s = backoff_speed(c);
        }
        break;
    case ACT_MODE_HOMING:
        home_step(c, now_ms);
        break;
    case ACT_MODE_FORCE:
        if (c->probe_phase == PROBE_APPROACH && c->act_vel_mm_s > probe_speed(c) && !approach_fast(c))
            c->act_vel_mm_s = probe_speed(c); /* the fast approach ends PROBE_LOCATED_MARGIN_UM before the contact */
        if ((c->probe_phase == PROBE_STEP || c->probe_phase == PROBE_STEP2) &&
            c->act_pos_steps >= c->probe_x_target) {
            c->act_vel_mm_s = 0.0f;
            c->probe_phase = c->probe_phase == PROBE_STEP ? PROBE_SETTLE2 : PROBE_SETTLE3;
            c->probe_readings = 0;
        }
        /* the second channel (2.11): past the probed contact no further than the force limit at its stiffness
         * (plus POSITION_MARGIN_G), whatever the reading says */
        if (c->contact_valid && c->probe_phase == PROBE_NONE &&
            (float)c->act_pos_steps > c->contact_x0_steps + ((float)c->hreg[RIGCTL_HREG_FORCE_LIMIT_G] +
                                                              (float)RIGCTL_POSITION_MARGIN_G) /
                                                                 c->contact_k_g_per_step) {
            /* the two channels disagree: the reading lies (the position bounds the force where it stands) or
             * the actuator does not go where its steps say (a reversed motor: a back-off would press) */
            stop_unproven(c, RIGCTL_FAULT_POSITION_LIMIT);
            break;
        }
        /* no force where the contact was (2.13): it stands where it latched, its way unproven (the steps did not do
         * what they say: a back-off may press too); the start's HOME creeps and proves the way */
        if (contact_missing(c)) {
            stop_unproven(c, RIGCTL_FAULT_CONTACT_MISSING);
            break;
        }
        /* HOME's switch proof is void once the switch reads closed with the count HOME_PROOF_MM out (2.11): the
         * motor runs backwards (a reversed one sits in its rear stop until ACTUATOR_TRAVEL, which then stops it) */
        if (c->home_switch && act_pos_mm(c) > (float)RIGCTL_HOME_PROOF_MM) c->press_dir_leave = 0;
        if (act_pos_mm(c) >= ACT_MAX_TRAVEL_MM && c->act_vel_mm_s > 0.0f) {
            c->act_vel_mm_s = 0.0f;
            fault(c, RIGCTL_FAULT_ACTUATOR_TRAVEL);
        }
        break;
    default:
        c->act_vel_mm_s = 0.0f;
        break;
    }

    away_watch(c);

    /* the drivers are enabled only while something moves or the force loop holds (EN also drops in the e-stop ISR) */
    c->drivers_on = !(c->faults & RIGCTL_FAULT_ESTOP) && !c->estop_open &&
                    (c->act_mode != ACT_MODE_HOLD || c->state == RIGCTL_STATE_HOMING || force_engaged(c) ||
                     c->drum_cmd_mm_s > 0.0f || c->drum_actual_mm_s > 0.0f || c->act_vel_mm_s != 0.0f);

    /* settle detection: FORCE_SETTLED is "force on target, drum at rest" (spec 2.4): after STOP_DRUM the drum
     * may still be decelerating when the force has been on target for SETTLE_TIME_MS */
    if (force_engaged(c)) {
        if (c->on_target) {
            if (c->state == RIGCTL_STATE_SEEKING_FORCE && c->drum_cmd_mm_s <= 0.0f && c->drum_actual_mm_s <= 0.0f &&
                (uint32_t)(now_ms - c->on_target_since_ms) >= c->hreg[RIGCTL_HREG_SETTLE_TIME_MS]) {
                c->state = RIGCTL_STATE_FORCE_SETTLED;
            }
        }
    }
}

/* a new reading while the force loop drives (spec 2.11): the step count commanded over PRESS_DIR_READINGS readings
 * (monotone) against the load read (|force|, sign-free: a reversed cell presses as a load too) over as many
 * readings PRESS_DIR_LAG_READINGS later (the HX711's sinc^4 filter and the reading's age). At least PRESS_DIR_STEPS
 * with the load against it by PRESS_DIR_G: ACTUATOR_DIRECTION, stopped where it stands; with it by PRESS_DIR_G: the
 * way proven, for PRESS_DIR_PROOF_READINGS
 * readings while the probe runs, and from then on once it is done (the loop holds: a reversed motor would drive the
 * force off and be seen); half of both against it: the proof is void. Returns 1 if it latched. */
static uint8_t press_dir_watch(ctl_t *c, float f)
{
    enum { N = RIGCTL_PRESS_DIR_READINGS, LEN = RIGCTL_PRESS_DIR_READINGS + RIGCTL_PRESS_DIR_LAG_READINGS + 1 };
    uint8_t i, up = 1, down = 1;
    int32_t ds, ads;
    float df;
    if (c->press_dir_age < 255) c->press_dir_age++;
    if (c->probe_phase != PROBE_NONE) c->press_dir_held = 0;
    if ((f < 0.0f ? -f : f) >= contact_g(c)) c->press_dir_leave = 0; /* the contact: the force proves from here */
    if (c->press_dir_n == LEN) {
        for (i = 1; i < LEN; i++) {
            c->press_dir_steps[i - 1] = c->press_dir_steps[i];
            c->press_dir_gf[i - 1] = c->press_dir_gf[i];
        }
        c->press_dir_n = LEN - 1;
    }
    c->press_dir_steps[c->press_dir_n] = c->act_pos_steps;
    c->press_dir_gf[c->press_dir_n] = f < 0.0f ? -f : f; /* the load, sign-free: the motor's way, not the cell's */
    c->press_dir_n++;
    if (c->press_dir_n < LEN) return 0;
    for (i = 1; i <= N; i++) { /* the count over the oldest N readings: the motion the newest force answers */
        if (c->press_dir_steps[i] < c->press_dir_steps[i - 1]) up = 0;
        if (c->press_dir_steps[i] > c->press_dir_steps[i - 1]) down = 0;
    }
    ds = c->press_dir_steps[N] - c->press_dir_steps[0];
    ads = ds < 0 ? -ds : ds;
    if (2 * ads < RIGCTL_PRESS_DIR_STEPS || !(up || down)) return 0;
    df = c->press_dir_gf[LEN - 1] - c->press_dir_gf[LEN - 1 - N];
    if (ds < 0) df = -df; /* + : the force follows the count */
    if (2.0f * df <= -(float)RIGCTL_PRESS_DIR_G) {
        c->press_dir_age = 255;
        c->press_dir_held = 0;
        if (ads >= RIGCTL_PRESS_DIR_STEPS && df <= -(float)RIGCTL_PRESS_DIR_G) {
            direction_fault(c);
            return 1;
        }
    } else if (ads >= RIGCTL_PRESS_DIR_STEPS && df >= (float)RIGCTL_PRESS_DIR_G) {
        c->press_dir_age = 0;
        c->press_dir_held = c->probe_phase == PROBE_NONE;
    }
    return 0;
}

/* a reading while the back-off holds still to prove its way (spec 2.11): the mean of BACKOFF_AVG_READINGS settled
 * readings at rest is what the steps are judged against (d0); after each proof step the mean of as many settled
 * readings decides: risen by the fall it proves, ACTUATOR_DIRECTION; fallen as much (or the tries spent), the way is
 * proven and it goes on at speed, watched; else one more step */
static void backoff_reading(ctl_t *c, int32_t raw)
{
    int32_t zero;
    float d;
    if (!direction_zero(c, &zero)) return;
    if (c->backoff_phase == BACKOFF_REST && (c->drum_cmd_mm_s > 0.0f || c->drum_actual_mm_s > 0.0f)) {
        backoff_settle_restart(c); /* the runout's ripple: wait for the drum at rest */
        return;
    }
    if (++c->backoff_readings <= RIGCTL_HX711_RATE_PERIODS) return; /* the HX711 settling on the step */
    c->backoff_sum_g += load_g(c, raw, zero);
    if (c->backoff_readings < RIGCTL_HX711_RATE_PERIODS + BACKOFF_AVG_READINGS) return;
    d = c->backoff_sum_g / (float)BACKOFF_AVG_READINGS;
    if (c->backoff_phase == BACKOFF_REST) {
        c->backoff_d0_g = d; /* at rest, settled: what the steps are judged against */
        backoff_step(c);
    } else if (d >= c->backoff_d0_g + c->backoff_fall_g) {
        direction_fault(c); /* it pressed: stop where it stands, not homed (HOME creeps and proves) */
    } else if (d <= c->backoff_d0_g - c->backoff_fall_g || c->backoff_tries >= BACKOFF_PROOF_TRIES) {
        c->backoff_phase = BACKOFF_FREE; /* the load fell: the way is proven now; watched from here */
        move_watch_start(c, 0);
    } else {
        backoff_step(c); /* no clear change yet (a soft contact, backlash): one more step */
    }
}

/* the force of a reading against the tare: FORCE_G (rounded, saturated) and the float the loop uses, g */
static float force_reading(ctl_t *c, int32_t raw)
{
    float f = ctl_force_from_raw(c, raw);
    c->force_gf = f;
    c->force_g = (int16_t)(f > 32767.0f ? 32767 : (f < -32768.0f ? -32768 : (f < 0 ? f - 0.5f : f + 0.5f)));
    return f;
}

/* a press's start at home at rest judges its settled reading against the tare (spec 2.13, above the probe): within
 * PRESS_DIR_G the tare follows it half the way, so a zero that drifts slowly (a cell's ~1 g per 10 K, the HX711's
 * offset drift, creep after a heavy press) is no fault between HOMEs, and the reading's noise does not walk the tare
 * (half the way: the tare's own noise is the reading's over sqrt(3); a drift of d a press leaves the tare 2 d behind);
 * never more than ZERO_TRACK_G from the tare HOME took, so a load that grows press by press cannot be tared away
 * unnoticed (a hand, debris: at most ZERO_TRACK_G of it ends up pressed on top of the setpoint, 1.6 % of
 * FORCE_LIMIT). Off by more: 0, the caller latches LOADCELL_ZERO and the operator's HOME tares again */
static uint8_t zero_follow(ctl_t *c, int32_t raw)
{
    int32_t tare = c->tare_offset + (raw - c->tare_offset) / 2;
    float f = c->force_gf;
    if ((f < 0.0f ? -f : f) > (float)RIGCTL_PRESS_DIR_G ||
        load_g(c, tare, c->home_tare_offset) > (float)RIGCTL_ZERO_TRACK_G) return 0;
    c->tare_offset = tare;
    c->force_prev_valid = 0;
    (void)force_reading(c, raw);
    return 1;
}

void ctl_loadcell(ctl_t *c, int32_t raw)
{
    float f, rise;
    uint16_t sp = c->hreg[RIGCTL_HREG_FORCE_SETPOINT_G];
    uint8_t on;
    int32_t zero;
    c->last_loadcell_ms = c->now_ms;
    /* a reading that can be lying is a fault (spec 2.11): the same 24 bits again and again (a working HX711 at gain
     * 128 has 20-40 counts of noise), a saturation code, an all-zero or all-one word twice (a broken line) */
    c->same_raw = c->have_reading && raw == c->prev_raw ? (uint8_t)(c->same_raw < 255 ? c->same_raw + 1 : 255) : 1;
    c->prev_raw = raw;
    c->line_codes = raw == 0 || raw == -1 ? (uint8_t)(c->line_codes < 255 ? c->line_codes + 1 : 255) : 0;
    if ((raw == 0x7FFFFFL || raw == -0x800000L || c->line_codes >= 2) && !(c->faults & RIGCTL_FAULT_HX711_LINE))
        fault(c, RIGCTL_FAULT_HX711_LINE);
    if (c->same_raw >= RIGCTL_HX711_STUCK_READINGS && !(c->faults & RIGCTL_FAULT_HX711_STUCK))
        fault(c, RIGCTL_FAULT_HX711_STUCK);
    if (c->line_codes == 1) {
        /* one all-zero or all-one word is doubtful, not a force: a line may just have broken (the next reading says:
         * HX711_LINE) or a real reading sat on the code. The actuator holds where it is for that period and nothing is
         * judged on it (a broken SCK's first 0 read as -tare otherwise latched LOADCELL_REVERSED, a wrong cause) */
        if (c->act_mode == ACT_MODE_FORCE) c->act_vel_mm_s = 0.0f;
        return;
    }
    c->loadcell_raw = raw;
    c->have_reading = 1;
    c->still_readings = c->act_vel_mm_s != 0.0f ? 0 : (uint8_t)(c->still_readings < 255 ? c->still_readings + 1 : 255);
    boot_load_check(c, raw);
    if (c->act_mode == ACT_MODE_RETRACT && (c->backoff_phase == BACKOFF_REST || c->backoff_phase == BACKOFF_SETTLE)) {
        backoff_reading(c, raw);
    }
    if (c->act_mode == ACT_MODE_HOMING || c->act_mode == ACT_MODE_RETRACT) {
        /* moving home or backing off only takes force off the cell: a load (|raw - zero|, sign-free: a reversed
         * motor and a reversed cell alike) grown above the lowest since the move began means it drives towards the
         * sensor (spec 2.11); without a known zero, an untared rise in the scale's sign (spec 2.5) */
        /* from an unknown position HOME creeps and stops at a small rise; from home's known position (and backing
         * off) the readings still carry the press's last rise: the larger threshold */
        float thr = c->act_mode == ACT_MODE_HOMING && (!c->homed || c->home_phase == HOME_LEAVE)
                        ? (float)RIGCTL_HOME_RISE_G
                        : (float)RIGCTL_DIRECTION_RISE_G;
        if (c->move_skip) c->move_skip--;
        if (direction_zero(c, &zero)) {
            float d = load_g(c, raw, zero);
            if (c->home_d_start_g < 0.0f) c->home_d_start_g = d;
            if (!c->move_ref_valid || d < c->move_d_min_g || c->move_skip) {
                c->move_d_min_g = d;
                c->move_ref_valid = 1;
            } else if (d - c->move_d_min_g > thr) {
                direction_fault(c);
            }
            if (c->act_mode == ACT_MODE_HOMING && !c->homed && d > home_load_cap_g(c)) direction_fault(c);
            if (load_ratchet_reached(c, d)) { /* the switch reads closed in the last latch's load: it is not home */
                c->homed = 0;
                fault(c, RIGCTL_FAULT_HOME_NOT_FOUND);
            }
            if (c->home_creep && c->act_mode == ACT_MODE_HOMING && d <= c->home_d_start_g - RIGCTL_HOME_PROOF_FALL_G) {
                c->home_creep = 0; /* the load fell: the direction is right, HOME goes on at its speed */
                c->home_start_ms = c->now_ms;
            }
        } else {
            float rise_g = (float)(raw - c->move_ref_raw) * 100.0f / (float)scale_of(c->hreg);
            if (!c->move_ref_valid || rise_g < 0.0f || c->move_skip) {
                c->move_ref_raw = raw;
                c->move_ref_valid = 1;
            } else if (rise_g > thr) {
                direction_fault(c);
            }
        }
    }
    /* never under load: only at home. After a reset the switch alone is no proof of home (a switch stuck closed reads
     * closed anywhere, under load too: issue 75): the power-up tare is taken only where the zero stored with the
     * calibration agrees within TARE_ZERO_AGREE_G; HOME's own tare (its switch proven by leaving and returning: at its
     * end, not on a switch read closed while it seeks, which a switch stuck closed under load is) and a homed TARE
     * always */
    if (c->tare_pending && c->home_switch &&
        (c->homed || (c->state == RIGCTL_STATE_HOMING && c->act_mode == ACT_MODE_HOLD) || !c->zero_valid ||
         load_g(c, raw, c->zero_raw) <= TARE_ZERO_AGREE_G)) {
        c->tare_offset = raw;
        c->home_tare_offset = raw;
        c->tare_pending = 0;
        c->force_prev_valid = 0;
        c->tared = 1;
        if (c->state == RIGCTL_STATE_HOMING && c->act_mode == ACT_MODE_HOLD) { /* HOME done: at the switch, tared */
            c->homed = 1;
            c->state = RIGCTL_STATE_IDLE;
        }
    }
    f = force_reading(c, raw);
    /* the trip sees the future (spec 2.10): while the loop drives, the force read now is the true force ~2 periods
     * ago (sinc^4) and the next reading comes a period later, so the rise of the last period is extrapolated over
     * FORCE_LEAD_PERIODS (only then: a mass put on an idle cell is not the actuator's doing) */
    rise = c->act_mode == ACT_MODE_FORCE && c->force_prev_valid && f > c->force_prev_gf ? f - c->force_prev_gf : 0.0f;
    c->force_prev_gf = f;
    c->force_prev_valid = 1;
    if (force_engaged(c) && press_dir_watch(c, f)) return;
    if (c->tared && f + rise * (float)RIGCTL_FORCE_LEAD_PERIODS > (float)c->hreg[RIGCTL_HREG_FORCE_LIMIT_G]) {
        if (c->state != RIGCTL_STATE_FAULT || !(c->faults & RIGCTL_FAULT_FORCE_LIMIT)) {
            fault(c, RIGCTL_FAULT_FORCE_LIMIT); /* backs the actuator off at once */
        }
        return;
    }
    if (!force_engaged(c)) return;
    if (c->probe_phase == PROBE_ZERO && c->still_readings > RIGCTL_HX711_RATE_PERIODS) {
        if (!zero_follow(c, raw)) {
            /* nothing moved and the reading is off its zero: not homed, so the operator's HOME (allowed from
             * NOT_HOMED whatever the load) proves the switch and tares again once the cause is found */
            stop_unproven(c, RIGCTL_FAULT_LOADCELL_ZERO);
            return;
        }
        f = c->force_gf;
    }
    if (f < -2.0f * (float)c->hreg[RIGCTL_HREG_FORCE_TOLERANCE_G]) {
        fault(c, RIGCTL_FAULT_LOADCELL_REVERSED); /* pressing makes it read negative: reversed cell or scale */
        return;
    }
    /* a held force must stay on the contact (2.11): the position says what the contact carries */
    if (c->contact_valid && c->probe_phase == PROBE_NONE &&
        f > 2.0f * (float)c->hreg[RIGCTL_HREG_FORCE_TOLERANCE_G] &&
        ((float)c->act_pos_steps - c->contact_x0_steps) * c->contact_k_g_per_step < 0.5f * f) {
        stop_unproven(c, RIGCTL_FAULT_CONTACT_LOST); /* the channels disagree: as POSITION_LIMIT */
        return;
    }
    on = c->probe_phase == PROBE_NONE && (f >= (float)sp - (float)c->hreg[RIGCTL_HREG_FORCE_TOLERANCE_G]) &&
         (f <= (float)sp + (float)c->hreg[RIGCTL_HREG_FORCE_TOLERANCE_G]);
    if (on && !c->on_target) c->on_target_since_ms = c->now_ms;
    c->on_target = on;
    if (c->act_mode == ACT_MODE_FORCE && c->probe_phase != PROBE_NONE) {
        probe_reading(c, f);
    } else if (c->act_mode == ACT_MODE_FORCE) {
        force_loop_gains(c);
        c->act_vel_mm_s = limit_governor(c, f, force_pi_update(&c->pi, (float)sp, f, c->hx_period_s));
        if (act_pos_mm(c) >= ACT_MAX_TRAVEL_MM && c->act_vel_mm_s > 0.0f) {
            c->act_vel_mm_s = 0.0f;
            fault(c, RIGCTL_FAULT_ACTUATOR_TRAVEL);
        }
    }
}
