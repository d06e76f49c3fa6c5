/* On-board SA encoder: fixed-point Izhikevich SA neurons, incremental speed scaling, SR windows (sa_encoder.h). */
#include "sa_encoder.h"

#include <string.h>

#ifndef SA_DOUBLE
#define Q1 ((int32_t)1 << SA_Q)
#define V_REST (-65L * Q1)          /* c */
#define U_REST (-13L * Q1)          /* b c */
#define V_PEAK (30L * Q1)
#define D_JUMP (6L * Q1)
#define C140 (140L * Q1)
#define K004 171798692L             /* 0.04 in Q0.32 */
#define KAB 17179869L               /* a b = 0.004 in Q0.32 */
#define KA 85899346L                /* a = 0.02 in Q0.32 */
#define SAT 0x7FFFFFFFL
#define I_MAX (4000L * Q1)

/* (x * k) >> 32 with rounding, k a Q0.32 constant < 1 */
static int32_t mul_q32(int32_t x, int32_t k) {
    return (int32_t)(((int64_t)x * k + ((int64_t)1 << 31)) >> 32);
}

static int32_t sat32(int64_t x) {
    return x > SAT ? SAT : (x < -SAT ? -SAT : (int32_t)x);
}

/* 0.5 (0.04 v^2 + 5 v + 140 - u + I) in Q13.18 (64-bit: no overflow for any int32 v) */
static int64_t half_dv(int32_t v, int32_t rest) {
    int64_t sq = ((int64_t)mul_q32(v, K004) * v) >> SA_Q; /* 0.04 v^2 */
    return (sq + 5 * (int64_t)v + rest) >> 1;
}

/* One 1 ms step of taxel i on reading x; returns 1 on a spike. */
static uint8_t neuron_step(sa_encoder_t *e, uint8_t i, uint16_t x) {
    int32_t in = (int32_t)((((int64_t)((int32_t)x - (int32_t)e->offset[i]) * e->gain_q24[i]) + (1L << (23 - SA_Q))) >> (24 - SA_Q));
    if (in > I_MAX) in = I_MAX;
    if (in < -I_MAX) in = -I_MAX;
    int32_t u0 = e->u[i];
    int32_t rest = C140 - u0 + in;
    int32_t v1 = sat32((int64_t)e->v[i] + half_dv(e->v[i], rest));
    int32_t v2 = sat32((int64_t)v1 + half_dv(v1, rest));
    int32_t u1 = u0 + mul_q32(v2, KAB) - mul_q32(u0, KA);
    if (v2 >= V_PEAK) {
        e->v[i] = V_REST;
        e->u[i] = u1 + D_JUMP;
        return 1;
    }
    e->v[i] = v2;
    e->u[i] = u1;
    return 0;
}

static void set_range(sa_encoder_t *e, uint8_t i, uint16_t lo, uint16_t hi, uint16_t k) {
    uint32_t span = (uint32_t)(hi - lo);
    e->gain_q24[i] = hi <= lo ? 0 : (int32_t)((((uint64_t)k << 24) + span / 2) / span);
}
#else /* SA_DOUBLE: the host float64 kernel's expressions, in its order (rigctl.encoding.fused, _sa_step "exact") */
#define V_REST (-65.0)
#define U_REST (0.2 * -65.0)

static uint8_t neuron_step(sa_encoder_t *e, uint8_t i, uint16_t x) {
    const double h = 0.5, q = 0.04, f = 5.0, ee = 140.0, a = 0.02, b = 0.2;
    double in = (((double)x - (double)e->offset[i]) * e->scale[i]) * e->k;
    double v0 = e->v[i], u0 = e->u[i];
    double v1 = v0 + h * (q * v0 * v0 + f * v0 + ee - u0 + in);
    double v2 = v1 + h * (q * v1 * v1 + f * v1 + ee - u0 + in);
    double u1 = u0 + a * (b * v2 - u0);
    if (v2 >= 30.0) {
        e->v[i] = -65.0;
        e->u[i] = u1 + 6.0;
        return 1;
    }
    e->v[i] = v2;
    e->u[i] = u1;
    return 0;
}

static void set_range(sa_encoder_t *e, uint8_t i, uint16_t lo, uint16_t hi, uint16_t k) {
    e->scale[i] = hi <= lo ? 0.0 : 1.0 / ((double)hi - (double)lo);
    e->k = (double)k;
}
#endif


void sa_reset(sa_encoder_t *e) {
    for (uint8_t i = 0; i < SA_N_TAXELS; i++) {
        e->v[i] = V_REST;
        e->u[i] = U_REST;
    }
    e->n = 0;
    e->windows_scaled = 0;
    e->scaled_ticks = 0;
    e->held_windows = 0;
    e->last_speed_cmm_s = 0;
    e->n_speeds = 0;
    memset(e->map, 0, sizeof e->map);
    memset(e->counts, 0, sizeof e->counts);
}

void sa_init(sa_encoder_t *e, const uint16_t min_count[SA_N_TAXELS], const uint16_t max_count[SA_N_TAXELS],
             uint16_t k) {
    for (uint8_t i = 0; i < SA_N_TAXELS; i++) {
        e->offset[i] = min_count[i];
        set_range(e, i, min_count[i], max_count[i], k);
    }
    sa_reset(e);
}

/* Scale the oldest waiting window with speed s: bin its spikes into the scaled windows, clear its map. */
static void scale_window(sa_encoder_t *e, uint16_t s) {
    uint8_t slot = (uint8_t)(e->windows_scaled % SA_PENDING);
    uint32_t t0 = e->scaled_ticks;
    for (uint8_t i = 0; i < SA_N_TAXELS; i++) {
        uint8_t *m = e->map[slot][i];
        for (uint8_t b = 0; b < SA_MAP_BYTES; b++) {
            uint8_t bits = m[b];
            m[b] = 0;
            for (uint8_t j = 0; bits; j++, bits >>= 1) {
                if (bits & 1u) {
                    uint32_t k = (t0 + (uint32_t)(b * 8u + j) * s) / SA_WINDOW_TICKS;
                    if (k < SA_N_WINDOWS && e->counts[i][k] < 0xFFFFu)
                        e->counts[i][k]++;
                }
            }
        }
    }
    e->scaled_ticks = t0 + (uint32_t)SA_WINDOW_MS * s;
    e->last_speed_cmm_s = s;
    e->windows_scaled++;
}

/* Scale every complete window whose speed is queued. */
static void scale_ready(sa_encoder_t *e) {
    while (e->n_speeds > 0 && e->windows_scaled < e->n / SA_WINDOW_MS) {
        uint16_t s = e->speed_cmm_s[e->windows_scaled % SA_PENDING];
        e->n_speeds--;
        scale_window(e, s);
    }
}

int8_t sa_speed(sa_encoder_t *e, uint16_t speed_cmm_s) {
    if (e->n_speeds >= SA_PENDING)
        return -1;
    e->speed_cmm_s[(e->windows_scaled + e->n_speeds) % SA_PENDING] = speed_cmm_s;
    e->n_speeds++;
    scale_ready(e);
    return 0;
}

uint16_t sa_step(sa_encoder_t *e, const uint16_t x[SA_N_TAXELS]) {
    uint32_t w = e->n / SA_WINDOW_MS;
    uint8_t pos = (uint8_t)(e->n - w * SA_WINDOW_MS);
    if (pos == 0) {
        while (w - e->windows_scaled >= SA_PENDING) { /* no slot: the oldest waits no longer */
            e->held_windows++; /* (no speed is queued here: a queued speed is used as soon as its window ends) */
            scale_window(e, e->last_speed_cmm_s);
        }
    }
    uint8_t slot = (uint8_t)(w % SA_PENDING);
    uint16_t mask = 0;
    for (uint8_t i = 0; i < SA_N_TAXELS; i++) {
        if (neuron_step(e, i, x[i])) {
            mask |= (uint16_t)(1u << i);
            e->map[slot][i][pos >> 3] |= (uint8_t)(1u << (pos & 7u));
        }
    }
    e->n++;
    if (pos == SA_WINDOW_MS - 1)
        scale_ready(e);
    return mask;
}

void sa_finish(sa_encoder_t *e, uint16_t speed_cmm_s) {
    uint32_t n_win = (e->n + SA_WINDOW_MS - 1) / SA_WINDOW_MS;
    if (e->windows_scaled == 0 && e->n_speeds == 0)
        e->last_speed_cmm_s = speed_cmm_s;
    while (e->windows_scaled < n_win) {
        uint16_t s = e->last_speed_cmm_s;
        if (e->n_speeds > 0) {
            s = e->speed_cmm_s[e->windows_scaled % SA_PENDING];
            e->n_speeds--;
        }
        scale_window(e, s);
    }
}
