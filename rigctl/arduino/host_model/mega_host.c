/* mega_host.c - the drum controller's logic (controller.c, force_pi.c, steprate.c) built for the host, for the model
 * rig (rigctl.simulation.controller loads it through cffi). Never on the Mega: the board's glue is mega_drum.cpp.
 *
 * What is here is only what makes the Python glue cheap: one call runs the 1 kHz ticks that mega_drum.cpp's loop()
 * runs between two readings (its `while (done_ms != now)` catch-up), and one applies the drum's surface speed as
 * drum_apply() does (steprate.c's timer setting, and the rate that setting really makes). Every rule stays in
 * controller.c. */
#include "mega_host.h"
#include "../mega_drum/drum_config.h"
#include "../mega_drum/steprate.h"

size_t mega_host_sizeof_ctl(void)
{
    return sizeof(ctl_t);
}

size_t mega_host_offsetof_drum_slip(void)
{
    return offsetof(ctl_t, drum_slip);
}

/* loop()'s ticks for the ms first_ms .. first_ms + n - 1 (ctl_tick), the actuator's step count going from pos0 (before
 * the first) to pos1 (at the last) as its step timer made them. Stops after a tick that leaves the glue something to
 * do at once (zero the step count at home, re-arm the e-stop's latch); returns the ticks run. */
uint16_t mega_host_ticks(ctl_t *c, uint32_t first_ms, uint16_t n, int32_t pos0, int32_t pos1)
{
    uint16_t i;
    for (i = 0; i < n; i++) {
        c->act_pos_steps = pos0 + (int32_t)(((int64_t)(pos1 - pos0) * (int64_t)(i + 1)) / (int64_t)n);
        ctl_tick(c, first_ms + i);
        if (c->zero_position || c->estop_release) return (uint16_t)(i + 1);
    }
    return n;
}

/* drum_apply() and drum_actual_mm_s(): the step timer set for the commanded surface speed (stopped when `inhibit`:
 * the e-stop or the watchdog), the controller told the speed that setting makes; returns its step rate, steps/s */
float mega_host_drum_apply(ctl_t *c, uint8_t inhibit)
{
    steptimer_t t;
    float hz;
    steprate_timer(steprate_hz_from_mm_s(c->drum_cmd_mm_s, DRUM_DIAMETER_MM, DRUM_USTEPS_PER_REV), 16000000UL, &t);
    if (inhibit) t.cs = 0;
    hz = steprate_timer_hz(&t, 16000000UL);
    c->drum_actual_mm_s = steprate_mm_s_from_hz(hz, DRUM_DIAMETER_MM, DRUM_USTEPS_PER_REV);
    return hz;
}
