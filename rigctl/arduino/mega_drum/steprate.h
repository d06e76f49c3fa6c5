/* steprate.h - surface speed <-> step rate (docs/wire-protocol.md 2.6) and step-timer settings; pure, host-tested. */
#ifndef STEPRATE_H
#define STEPRATE_H
#include <stdint.h>
#ifdef __cplusplus
extern "C" {
#endif

/* step rate (steps/s) for a surface speed v (mm/s): f = v * usteps_per_rev / (pi * diameter_mm) */
float steprate_hz_from_mm_s(float v_mm_s, float diameter_mm, uint16_t usteps_per_rev);
/* inverse of steprate_hz_from_mm_s */
float steprate_mm_s_from_hz(float f_hz, float diameter_mm, uint16_t usteps_per_rev);

/* a 16-bit AVR timer in CTC mode: clock select (1: /1, 2: /8, 3: /64, 4: /256, 5: /1024) and OCR (period - 1) */
typedef struct {
    uint8_t cs;
    uint16_t ocr;
} steptimer_t;

/* the timer setting whose period is closest to 1/f_hz with the finest prescaler that fits 16 bits.
 * Returns 0 (and cs = 0: timer stopped) when f_hz is below what /1024 can time or not positive. */
uint8_t steprate_timer(float f_hz, uint32_t f_cpu, steptimer_t *out);
/* the step rate a timer setting produces (0 when stopped) */
float steprate_timer_hz(const steptimer_t *t, uint32_t f_cpu);
/* move `current` towards `target` by at most accel * dt (a linear acceleration ramp) */
float steprate_ramp(float current, float target, float accel, float dt);

#ifdef __cplusplus
}
#endif
#endif
