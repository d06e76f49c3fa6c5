/* On-board SA encoder: Izhikevich SA neurons, incremental speed scaling, SR windows (sa_encoder.h). */
#include "sa_encoder.h"

#include <string.h>

#if defined(SA_FIXED)
#if (-1 >> 1) != -1
#error "SA_FIXED needs an arithmetic right shift of negative integers (gcc, clang, avr-gcc, arm-gcc have one)"
#endif
#define Y_PEAK 10066330L            /* ceil(0.6 * 2^24): v2 >= 30 mV */
#define Y_RESET (-21810381L)        /* round(-1.3 * 2^24): c = -65 mV */
#define Z_REST (-2181038L)          /* round(-0.13 * 2^24): u = b c = -13 */
#define Z_JUMP 1006633L             /* round(0.06 * 2^24): d = 6 */
#define W_E 23488102L               /* round(1.4 * 2^24): h e / 50 */
#define Y_MAX 134217727L            /* 8 * 2^24 - 1 */
#define K_A 1311                    /* round(0.02 * 2^16): a (0.0200043) */
#define K_AB 33554u                 /* round(0.002 * 2^24): a b 50 / 100 */
#define V_REST Y_RESET
#define U_REST Z_REST

/* 16 x 16 -> 32 bit products. Plain C here; an AVR build defines SA_MUL_AVR and gets them as inline MUL code
 * (sa_mul_avr.h: the same integers, no libgcc calls). Without it avr-gcc folds the halves of y back into 32-bit
 * values and calls its 32 x 32 multiply; an empty asm statement that "changes" each operand hides where it came
 * from, so it calls its 16 x 16 -> 32 routines instead (the same products: only the code differs) */
#if defined(__GNUC__)
#define SA_INLINE inline __attribute__((always_inline))
#else
#define SA_INLINE inline
#endif
#if defined(SA_MUL_AVR)
#include "sa_mul_avr.h"
#define mul_ss sa_mul_ss
#define mul_su sa_mul_su
#define mul_uu sa_mul_uu
#else
#if defined(__GNUC__) && defined(__AVR__)
#define SA_OPAQUE(x) __asm__("" : "+r"(x))
#else
#define SA_OPAQUE(x) ((void)0)
#endif
static SA_INLINE int32_t mul_ss(int16_t a, int16_t b) { SA_OPAQUE(a); SA_OPAQUE(b); return (int32_t)a * b; }
static SA_INLINE int32_t mul_su(int16_t a, uint16_t b) { SA_OPAQUE(a); SA_OPAQUE(b); return (int32_t)a * (int32_t)b; }
static SA_INLINE uint32_t mul_uu(uint16_t a, uint16_t b) { SA_OPAQUE(a); SA_OPAQUE(b); return (uint32_t)a * b; }
#endif

/* d R, the input (|d R| < 2^31 by the clamps: 4 span R <= 4 k 2^24 / 100 + 2 span): with d inside int16 (every
 * 10-bit ADC's case) as two 16 x 16 products of R's halves, d R_lo + 2^16 d R_hi, summed modulo 2^32 (the exact
 * product, which fits int32); a 32 x 32 product otherwise */
static SA_INLINE int32_t mul_in(int32_t d, int32_t r) {
    if (d >= INT16_MIN && d <= INT16_MAX) {
        uint32_t lo = (uint32_t)mul_su((int16_t)d, (uint16_t)(r & 0xFFFF));
        uint32_t hi = (uint32_t)mul_ss((int16_t)d, (int16_t)(r >> 16));
        return (int32_t)(lo + (hi << 16));
    }
    return d * r;
}

/* y^2 for a Q24 y in [-8, 8): y = h 2^16 + l, h signed, l in [0, 2^16), m = l's high byte: (h^2 2^8) +
 * floor(2h l / 2^8) + floor(m^2 / 2^8) (l^2 / 2^24 but for < 2 LSB): two 16 x 16 -> 32 bit products and an 8 x 8,
 * shifts by whole bytes. */
static SA_INLINE int32_t sq(int32_t y) {
    int16_t h = (int16_t)(y >> 16);
    uint16_t l = (uint16_t)(y & 0xFFFF);
    uint8_t m = (uint8_t)(l >> 8);
    return mul_ss(h, h) * 256 + (mul_su((int16_t)(2 * h), l) >> 8) + (int32_t)(((uint16_t)m * m) >> 8);
}

/* floor(y * c / 2^16) as h c + floor(l c / 2^16): two 16 x 16 -> 32 bit products */
static SA_INLINE int32_t mulc16(int32_t y, uint16_t c) {
    int16_t h = (int16_t)(y >> 16);
    uint16_t l = (uint16_t)(y & 0xFFFF);
    return mul_su(h, c) + (int32_t)(mul_uu(l, c) >> 16);
}

/* floor(y * c / 2^24) as floor(h c / 2^8) + floor(l c / 2^24) */
static SA_INLINE int32_t mulc24(int32_t y, uint16_t c) {
    int16_t h = (int16_t)(y >> 16);
    uint16_t l = (uint16_t)(y & 0xFFFF);
    return (mul_su(h, c) >> 8) + (int32_t)(mul_uu(l, c) >> 24);
}

static SA_INLINE int32_t clamp_y(int32_t y) {
    return y > Y_MAX ? Y_MAX : (y < -Y_MAX - 1 ? -Y_MAX - 1 : y);
}

/* One 1 ms step of taxel i on reading x; returns 1 on a spike. */
static uint8_t neuron_step(sa_encoder_t *e, uint8_t i, uint16_t x) {
    int32_t d = (int32_t)x - (int32_t)e->offset[i];
    d = d < e->d_lo[i] ? e->d_lo[i] : (d > e->d_hi[i] ? e->d_hi[i] : d);
    int32_t z0 = e->z[i];
    int32_t w = W_E + mul_in(d, e->gain[i]) - z0;
    int32_t y0 = clamp_y(e->y[i]);
    int32_t y1 = clamp_y(sq(y0) + 4 * y0 - (y0 >> 1) + w);
    int32_t y2 = sq(y1) + 4 * y1 - (y1 >> 1) + w;
    int32_t z1 = z0 - mulc16(z0, K_A) + mulc24(y2, K_AB);
    if (y2 >= Y_PEAK) {
        e->y[i] = Y_RESET;
        e->z[i] = z1 + Z_JUMP;
        return 1;
    }
    e->y[i] = y2;
    e->z[i] = z1;
    return 0;
}

static void set_range(sa_encoder_t *e, uint8_t i, uint16_t lo, uint16_t hi, uint16_t k) {
    uint32_t span = hi > lo ? (uint32_t)(hi - lo) : 0u;
    if (k > SA_FIXED_K_MAX)
        k = SA_FIXED_K_MAX;
    /* R = round(k 2^24 / (100 span)); a taxel with max <= min gets a constant 0 input, as on the host */
    e->gain[i] = span ? (int32_t)(((uint32_t)k * 16777216UL + 50u * span) / (100u * span)) : 0;
    e->d_lo[i] = -2 * (int32_t)span;
    e->d_hi[i] = 4 * (int32_t)span;
}
#elif !defined(SA_DOUBLE)
/* float32: the host's default (live) kernel, rigctl.encoding.fused _sa_step "fast", operation for operation: the
 * constants are the float32 values the host folds (kc[4:9]: h q, 1 + h f, h e, 1 - a, a b, each rounded from its
 * float64 value; hex literals, so no compiler folds them differently), and every expression below is one IEEE
 * single operation in the host's order (no contraction: -ffp-contract=off where the compiler would fuse). */
#define K_HQ 0x1.47ae14p-6f         /* float32(0.5 * 0.04) */
#define K_1HF 3.5f                  /* 1 + 0.5 * 5 */
#define K_HE 70.0f                  /* 0.5 * 140 */
#define K_1A 0x1.f5c29p-1f          /* float32(1 - 0.02) */
#define K_AB 0x1.0624dep-8f         /* float32(0.02 * 0.2) */
#define V_REST (-65.0f)
#define U_REST (-13.0f)             /* float32(0.2) * -65 rounds to -13 exactly */

/* x / 2 for the float32 x = i_in - u0: exact in IEEE arithmetic, so it is done on the exponent (one integer
 * subtraction instead of a software multiply on boards without an FPU) unless x is zero, subnormal-bound or not
 * finite, where the multiply gives the IEEE result. */
static float half(float x) {
    union { float f; uint32_t b; } q;
    q.f = x;
    uint32_t ex = q.b & 0x7F800000UL;
    if (ex > 0x00800000UL && ex != 0x7F800000UL) {
        q.b -= 0x00800000UL;
        return q.f;
    }
    return 0.5f * x;
}

/* One 1 ms step of taxel i on reading x; returns 1 on a spike. */
static uint8_t neuron_step(sa_encoder_t *e, uint8_t i, uint16_t x) {
    /* the host's normalisation in float32: ((float)x - (float)offset) * scale, exact integer difference first */
    float in = (float)((int32_t)x - (int32_t)e->offset[i]) * e->scale[i];
    in = in * e->k;
    float v0 = e->v[i], u0 = e->u[i];
    float w = K_HE + half(in - u0);             /* h (e - u + I) */
    float v1 = v0 * (K_HQ * v0 + K_1HF) + w;
    float v2 = v1 * (K_HQ * v1 + K_1HF) + w;
    float u1 = K_1A * u0 + K_AB * v2;
    if (v2 >= 30.0f) {
        e->v[i] = V_REST;
        e->u[i] = u1 + 6.0f;
        return 1;
    }
    e->v[i] = v2;
    e->u[i] = u1;
    return 0;
}

static void set_range(sa_encoder_t *e, uint8_t i, uint16_t lo, uint16_t hi, uint16_t k) {
    /* float32(1 / span) rounded once equals the host's float32(float64(1 / span)) for every span 1..65535
     * (checked exhaustively: no double-rounding case), so the board may divide in single precision */
    e->scale[i] = hi <= lo ? 0.0f : 1.0f / (float)(hi - lo);
    e->k = (float)k;
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
#if defined(SA_FIXED)
        e->y[i] = V_REST;
        e->z[i] = U_REST;
#else
        e->v[i] = V_REST;
        e->u[i] = U_REST;
#endif
    }
    e->n = 0;
    e->win = 0;
    e->pos = 0;
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
    /* sample j's scaled window is floor((t0 + j s) / ticks) = k0 + the edges it has passed: the first sample past
     * each edge (at most 7 in a window: 99 x 65535 ticks < 7e6) found once, not a division per spike */
    uint32_t k0 = t0 / SA_WINDOW_TICKS;
    uint8_t cut[8], n_cut = 0;
    if (s > 0) {
        for (uint32_t edge = (k0 + 1u) * SA_WINDOW_TICKS; n_cut < 8u; edge += SA_WINDOW_TICKS) {
            uint32_t j = (edge - t0 + s - 1u) / s;
            if (j >= SA_WINDOW_MS)
                break;
            cut[n_cut++] = (uint8_t)j;
        }
    }
    for (uint8_t i = 0; i < SA_N_TAXELS; i++) {
        uint8_t *m = e->map[slot][i];
        for (uint8_t b = 0; b < SA_MAP_BYTES; b++) {
            uint8_t bits = m[b];
            m[b] = 0;
            for (uint8_t j = (uint8_t)(b * 8u); bits; j++, bits >>= 1) {
                if (bits & 1u) {
                    uint32_t k = k0;
                    for (uint8_t c = 0; c < n_cut && j >= cut[c]; c++)
                        k++;
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
    while (e->n_speeds > 0 && e->windows_scaled < e->win) {
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
    uint32_t w = e->win;
    uint8_t pos = e->pos;
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
    if (pos == SA_WINDOW_MS - 1) {
        e->pos = 0;
        e->win++;
        scale_ready(e);
    } else {
        e->pos = (uint8_t)(pos + 1u);
    }
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
