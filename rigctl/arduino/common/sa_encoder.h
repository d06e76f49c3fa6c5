/* On-board SA encoder: fixed-point Izhikevich SA neurons, incremental speed scaling and SR feature windows
 * (paper eqs. 2-5, Methods "Real-time Texture Classification"; host reference: rigctl.encoding.izhikevich,
 * rigctl.encoding.speed.incremental_scale, rigctl.encoding.realtime.ScanEncoder).
 *
 * Plain portable C99 (stdint only, no AVR types): builds for the ATmega328P and a Teensy-class board alike.
 * Two arithmetics: Q13.18 fixed point (default: boards without an FPU, the ATmega328P), or, with -DSA_DOUBLE (a
 * board with a double-precision FPU such as the Teensy 4.0's Cortex-M7; build with -ffp-contract=off), IEEE double
 * with the host float64 kernel's expressions in its order (rigctl.encoding.fused, "exact"): the same spikes.
 *
 * Model, per taxel, one step per 1 kHz sample (the host's scheme, Izhikevich 2003):
 *   I  = k * (x - offset) / (max - min)                     (the host's TaxelRange normalisation, k = 100)
 *   v1 = v0 + 0.5 (0.04 v0^2 + 5 v0 + 140 - u0 + I)
 *   v2 = v1 + 0.5 (0.04 v1^2 + 5 v1 + 140 - u0 + I)
 *   u1 = u0 + a (b v2 - u0)                                  a = 0.02, b = 0.2
 *   v2 >= 30: spike; v <- c = -65, u <- u1 + d (d = 6).     Rest: v = -65, u = b v = -13.
 *
 * Fixed-point format (default): v, u and I are signed Q13.18 in int32_t (1 LSB = 2^-18 mV = 3.8e-6 mV, half
 * float32's ulp at 65 mV; range +-8192 mV). Products are 32 x 32 -> 64-bit multiplies shifted back with rounding;
 * the constants 0.04, a b = 0.004 and a = 0.02 are Q0.32 (relative error < 1e-7); the input gain k / (max - min)
 * is Q8.24 per ADC count (relative error <= 2^-25 / gain). Error bound: each step adds at most 4 LSB (1.5e-5 mV) of
 * rounding to v and u before the spike test; v2 saturates at +-8192 mV (reached only for inputs far above the
 * calibrated range) and I is clamped to +-4000 (40 ranges). The model amplifies any rounding: a spike one sample
 * late changes u by a b (v2 - 30) with v2 then in the hundreds of mV, which moves the train's later spikes, so no
 * arithmetic short of the reference's own operations gives the same spike times everywhere. Measured on simulated
 * handheld scans (tests/firmware/test_fw_sa_encoder.py): 92.9 % of spikes within one sample of the host float64
 * encoder, the same as the host's own float32 kernel (93.3 %); -DSA_DOUBLE gives 100 %.
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
#define SA_Q 18                     /* v, u, I: Q13.18 */

#ifdef SA_DOUBLE
typedef double sa_num_t;                /* the host's float64 reference, operation for operation (FPU boards) */
#else
typedef int32_t sa_num_t;               /* Q13.18 */
#endif

typedef struct {
    sa_num_t v[SA_N_TAXELS];            /* mV */
    sa_num_t u[SA_N_TAXELS];
#ifdef SA_DOUBLE
    double scale[SA_N_TAXELS];          /* 1 / (max - min), 0 when max <= min */
    double k;
#else
    int32_t gain_q24[SA_N_TAXELS];      /* k / (max - min), Q8.24 per ADC count */
#endif
    uint16_t offset[SA_N_TAXELS];       /* ADC count of the taxel's minimum */
    uint32_t n;                         /* samples since the scan started */
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
