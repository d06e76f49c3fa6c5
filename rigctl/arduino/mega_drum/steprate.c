/* steprate.c - see steprate.h */
#include "steprate.h"

#define STEPRATE_PI 3.14159265358979f

float steprate_hz_from_mm_s(float v_mm_s, float diameter_mm, uint16_t usteps_per_rev)
{
    return v_mm_s * (float)usteps_per_rev / (STEPRATE_PI * diameter_mm);
}

float steprate_mm_s_from_hz(float f_hz, float diameter_mm, uint16_t usteps_per_rev)
{
    return f_hz * STEPRATE_PI * diameter_mm / (float)usteps_per_rev;
}

static const uint16_t prescalers[5] = {1, 8, 64, 256, 1024};
/* 1 / prescaler: powers of two, exact in float */
static const float prescaler_inv[5] = {1.0f, 0.125f, 0.015625f, 0.00390625f, 0.0009765625f};

/* One float division (~500 cycles on the AVR) instead of one per prescaler tried: the period at /1 in CPU clocks,
 * scaled by 1 / prescaler, a power of two. Scaling by a power of two is exact in float, so each period, and the
 * comparison with 65536, is bit for bit f_cpu / (prescaler * f_hz) as computed per prescaler (host_tests checks it
 * over the whole range against that form). */
uint8_t steprate_timer(float f_hz, uint32_t f_cpu, steptimer_t *out)
{
    uint8_t i;
    out->cs = 0;
    out->ocr = 0;
    if (!(f_hz > 0.0f)) return 0;
    float period1 = (float)f_cpu / f_hz;
    for (i = 0; i < 5; i++) {
        float period = period1 * prescaler_inv[i];
        if (period <= 65536.0f) {
            uint32_t p = (uint32_t)(period + 0.5f);
            if (p < 2) p = 2;
            out->cs = (uint8_t)(i + 1);
            out->ocr = (uint16_t)(p - 1);
            return 1;
        }
    }
    return 0;
}

float steprate_timer_hz(const steptimer_t *t, uint32_t f_cpu)
{
    if (t->cs < 1 || t->cs > 5) return 0.0f;
    return (float)f_cpu / ((float)prescalers[t->cs - 1] * ((float)t->ocr + 1.0f));
}

float steprate_ramp(float current, float target, float accel, float dt)
{
    float dv = accel * dt;
    if (target > current + dv) return current + dv;
    if (target < current - dv) return current - dv;
    return target;
}
