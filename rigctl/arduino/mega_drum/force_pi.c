/* force_pi.c - see force_pi.h */
#include "force_pi.h"

void force_pi_init(force_pi_t *pi, float kp, float ki, float out_max, float band)
{
    pi->band = band;
    pi->kp = kp;
    pi->ki = ki;
    pi->out_max = out_max;
    pi->integ = 0.0f;
}

void force_pi_reset(force_pi_t *pi)
{
    pi->integ = 0.0f;
}

float force_pi_update(force_pi_t *pi, float setpoint_g, float measured_g, float dt)
{
    float e = setpoint_g - measured_g;
    float p = pi->kp * e;
    float integ = (e < pi->band && e > -pi->band) ? pi->integ + pi->ki * e * dt : pi->integ;
    float out = p + integ;
    if (out > pi->out_max) {
        out = pi->out_max;
        if (e < 0.0f) pi->integ = integ; /* only unwind */
    } else if (out < -pi->out_max) {
        out = -pi->out_max;
        if (e > 0.0f) pi->integ = integ;
    } else {
        pi->integ = integ;
    }
    if (pi->integ > pi->out_max) pi->integ = pi->out_max;
    if (pi->integ < -pi->out_max) pi->integ = -pi->out_max;
    return out;
}
