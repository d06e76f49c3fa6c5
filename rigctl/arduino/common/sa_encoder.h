/* On-board SA encoder: Izhikevich SA neurons (bit for bit the host kernel), incremental speed scaling and SR feature windows
 * (paper eqs. 2-5, Methods "Real-time Texture Classification"; host reference: rigctl.encoding.izhikevich,
 * rigctl.encoding.speed.incremental_scale, rigctl.encoding.realtime.ScanEncoder).
 *
 * Plain portable C99 (stdint only, no AVR types): builds for the ATmega328P and a Teensy-class board alike.
 *
 * Arithmetic: bit for bit the host's encoder. The model is chaotic in its rounding: the host's float64 loop fed an
 * input nudged by a relative 1e-15 keeps only 99.2 % of its spikes within one sample (1e-12: 98.1 %, 1e-7: 94.9 %;
 * the float32 kernel and a Q13.18 fixed-point version of this file both scored ~93 % against float64), so the issue's
 * criterion (>= 99 % of spikes within one sample, window counts within 1 %) is met only by repeating the host's own
 * operations. Default: IEEE single precision with the operations of the host's live kernel (float32,
 * rigctl.encoding.fused _sa_step "fast": EncodeParams.kernel_dtype "float32", the ScanEncoder's), its folded
 * constants rounded as the host rounds them; -DSA_DOUBLE: IEEE double with the float64 kernel's expressions
 * (kernel_dtype "float64"); -DSA_FIXED: an integer kernel (below) that fits the AVR's 1 kHz tick, which the host runs
 * integer for integer (rigctl.encoding.fixed_sa, ScanEncoder(kernel="fixed")): equal by construction, not to the
 * float kernels (docs/firmware.md, "The integer kernel"). The float builds need a compiler that rounds every
 * operation to its type (no FMA contraction: -ffp-contract=off; no x87 excess precision) and a correctly rounded
 * (round to nearest even) float library:
 * an FPU, or avr-libc's software float on the AVR (tests/firmware/test_fw_sa_encoder.py runs the AVR build under
 * simavr against the host).
 *
 * Model, per taxel, one step per 1 kHz sample (the host's scheme, Izhikevich 2003; h = 0.5 ms half-steps):
 *   I  = k * ((x - offset) * scale)                         (the host's TaxelRange normalisation, k = 100)
 *   w  = h e + h (I - u0)                                   (float32 form: e = 140, the input term shared)
 *   v1 = v0 (h q v0 + 1 + h f) + w                          q = 0.04, f = 5
 *   v2 = v1 (h q v1 + 1 + h f) + w
 *   u1 = (1 - a) u0 + a b v2                                a = 0.02, b = 0.2
 *   v2 >= 30: spike; v <- c = -65, u <- u1 + d (d = 6).     Rest: v = -65, u = b v = -13.
 * (-DSA_DOUBLE: v1 = v0 + h (q v0 v0 + f v0 + e - u0 + I), the same for v2, u1 = u0 + a (b v2 - u0).)
 * Speed scaling (eq. 2, incremental, reference 100 mm/s): real-time window w = samples [100 w, 100 w + 100); the
 * host sends its mean speed in 0.01 mm/s (speed_cmm_s). Scaled time is kept as an integer in ticks of 0.1 us: one
 * real ms at speed v advances it by exactly speed_cmm_s ticks (1 ms * (v / 100 mm/s) = v_cmm * 1e-7 s), so a spike at
 * sample n of window w has the scaled time T_w + (n - 100 w) * speed_cmm_s, T_w the sum of the earlier windows'
 * 100 * speed_cmm_s: exact integer arithmetic of the host's piecewise map for speeds given to 0.01 mm/s. Scaled
 * window k (100 ms of scaled time = 1e6 ticks) counts the spikes with floor(T / 1e6) = k, k < SA_N_WINDOWS.
 * The SR feature is count / (real-time duration of the scaled window), which the host computes from the speeds it
 * sent; the board reports counts.
 *
 * A window's spikes wait in a 100-bit map per taxel until its speed arrives (SA_PENDING windows may wait; a speed
 * may also arrive early). When a window ends and SA_PENDING windows already wait,
 * the oldest is scaled with the last speed received (held) and counted in sa_encoder_t.held_windows.
 */
#ifndef RIGCTL_SA_ENCODER_H
#define RIGCTL_SA_ENCODER_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define SA_N_TAXELS 9
#define SA_WINDOW_MS 100
#define SA_N_WINDOWS 20             /* scaled-time windows: 2 s of scaled time, 20 x 9 = 180 features */
#define SA_PENDING 2                /* real-time windows that may wait for their speed */
#define SA_MAP_BYTES ((SA_WINDOW_MS + 7) / 8)
#define SA_WINDOW_TICKS 1000000UL   /* 100 ms of scaled time in 0.1 us ticks */

#if defined(SA_FIXED)
/* The integer kernel (-DSA_FIXED): the host runs the same integers (rigctl.encoding.fixed_sa), so the two agree by
 * construction. Scaled variables, Q24 (value * 2^24) in int32: y = v / 50 (mV), z = u / 100, J = I / 100.
 *   w  = 1.4 + J - z0                       (h (e - u + I) / 50)
 *   y1 = sq(y0) + 3.5 y0 + w                (v1 = v0 + h (0.04 v0^2 + 5 v0 + 140 - u0 + I), divided by 50)
 *   y2 = sq(y1) + 3.5 y1 + w
 *   z1 = z0 - a z0 + ab50 y2                (u1 = u0 + a (b v2 - u0), divided by 100: a = 0.02, a b 50 / 100 = 0.002)
 *   y2 >= 0.6 (v >= 30 mV): spike; y <- -1.3 (c = -65), z <- z1 + 0.06 (d = 6).   Rest: y = -1.3, z = -0.13.
 * sq(y) = y^2 in Q24 from three 16 x 16 -> 32 products of y's halves; a z0 and ab50 y2 two each (constants in Q20 and
 * Q24); J = clamp(x - offset, -2 span, 4 span) * R, R = round(k 2^24 / (100 span)) once per scan (k <= 255). y is
 * held in [-8, 8) before each square (|v| < 400 mV: never reached by inputs inside [-2, 4] of the range), which
 * bounds every intermediate inside int32 (docs/firmware.md). Right shifts are floors (arithmetic shifts). */
#define SA_FIXED_K_MAX 255
#elif defined(SA_DOUBLE)
typedef double sa_num_t;                /* the host's float64 kernel, operation for operation */
#else
typedef float sa_num_t;                 /* the host's float32 kernel, operation for operation */
#endif

typedef struct {
#if defined(SA_FIXED)
    int32_t y[SA_N_TAXELS];             /* v / 50, Q24 */
    int32_t z[SA_N_TAXELS];             /* u / 100, Q24 */
    int32_t gain[SA_N_TAXELS];          /* R: J (Q24) per ADC count above the minimum */
    int32_t d_lo[SA_N_TAXELS];          /* -2 span: the input's clamp, ADC counts */
    int32_t d_hi[SA_N_TAXELS];          /* 4 span */
#else
    sa_num_t v[SA_N_TAXELS];            /* mV */
    sa_num_t u[SA_N_TAXELS];
    sa_num_t scale[SA_N_TAXELS];        /* 1 / (max - min), 0 when max <= min */
    sa_num_t k;                         /* input gain (k_SA times the force coefficient C) */
#endif
    uint16_t offset[SA_N_TAXELS];       /* ADC count of the taxel's minimum */
    uint32_t n;                         /* samples since the scan started */
    uint32_t win;                       /* n / SA_WINDOW_MS: the real-time window of the next sample */
    uint8_t pos;                        /* n % SA_WINDOW_MS (kept, not divided: a 32-bit division is ~600 cycles) */
    uint32_t windows_scaled;            /* real-time windows scaled so far */
    uint32_t scaled_ticks;              /* scaled time of the next unscaled window's start, 0.1 us */
    uint32_t held_windows;              /* windows scaled with the last speed: theirs came too late */
    uint16_t last_speed_cmm_s;          /* the last speed used */
    uint16_t speed_cmm_s[SA_PENDING];   /* speeds received ahead of their window (ring, by window index) */
    uint8_t n_speeds;                   /* speeds queued */
    uint8_t map[SA_PENDING][SA_N_TAXELS][SA_MAP_BYTES]; /* spikes of waiting windows, bit = sample in window */
    uint16_t counts[SA_N_TAXELS][SA_N_WINDOWS];         /* spikes per scaled window */
} sa_encoder_t;

/* Per-taxel normalisation (the host's TaxelRange: each taxel's minimum and maximum ADC count of the calibration) and
 * the input gain k (100 for SA; the force coefficient C of eq. 1, 1 in the real-time experiment, folded in by the
 * host if wanted). A taxel with max <= min gets a constant 0 input, as on the host. Resets the scan. */
void sa_init(sa_encoder_t *e, const uint16_t min_count[SA_N_TAXELS], const uint16_t max_count[SA_N_TAXELS],
             uint16_t k);
/* Start a new scan: neurons at rest, time 0, counts cleared. */
void sa_reset(sa_encoder_t *e);
/* One 1 ms sample of the 9 taxels (ADC counts); returns the taxels that spiked (bit i = taxel i). */
uint16_t sa_step(sa_encoder_t *e, const uint16_t x[SA_N_TAXELS]);
/* The mean speed of the next real-time window without one, 0.01 mm/s; returns 0, or -1 if SA_PENDING speeds wait. */
int8_t sa_speed(sa_encoder_t *e, uint16_t speed_cmm_s);
/* End of scan: scale the waiting windows (the last partial one too) with the speeds queued, the last one held for
 * those without (the host's window_speeds holds the trace past its end); speed_cmm_s if none was ever given. */
void sa_finish(sa_encoder_t *e, uint16_t speed_cmm_s);

#ifdef __cplusplus
}
#endif
#endif
