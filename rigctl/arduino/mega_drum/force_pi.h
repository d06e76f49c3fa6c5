/* force_pi.h - PI force loop: load-cell force (g) -> actuator velocity (mm/s, + towards the sensor); pure. */
#ifndef FORCE_PI_H
#define FORCE_PI_H
#ifdef __cplusplus
extern "C" {
#endif
typedef struct {
    float kp;      /* (mm/s) per g */
    float ki;      /* (mm/s) per (g s) */
    float out_max; /* |output| clamp, mm/s */
    float band;    /* the integral grows only while |error| < band, g */
    float integ;   /* integral term (already multiplied by ki), mm/s */
} force_pi_t;

void force_pi_init(force_pi_t *pi, float kp, float ki, float out_max, float band);
void force_pi_reset(force_pi_t *pi);
/* one update with sample period dt (s); conditional integration: the integral grows only while |error| < band and
 * not while the output is saturated in the direction of the error (anti-windup). */
float force_pi_update(force_pi_t *pi, float setpoint_g, float measured_g, float dt);
#ifdef __cplusplus
}
#endif
#endif
