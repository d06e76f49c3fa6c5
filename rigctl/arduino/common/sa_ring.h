/* The on-board encoder's sample ring: the 9 top-layer taxels' raw samples, kept from ARM so that the scan is encoded
 * from the finger's true entry onto the plate, which the host knows only once its tracker has seen it (issue 78
 * item 4; docs/wire-protocol.md 1.5, docs/firmware.md "The encoder in the Uno image").
 *
 * Plain portable C99 (stdint only): the Uno encoder image runs it (its tick interrupt pushes, loop() pops), and the
 * host runs the same file through cffi (rigctl.simulation.onboard_c) to model the board; no copy of it elsewhere.
 *
 * Samples are numbered from ARM (0 = the first sample after ARM, mod 65536). The ring keeps the last SA_RING_SAMPLES
 * samples, encoded or not (a push overwrites the oldest kept). BEGIN(from) starts the encoding at sample `from`: the
 * pops from then on give sample `from`, `from` + 1, ... in order. A `from` older than the ring keeps starts at the
 * oldest it may: SA_RING_MAX_BACK back from the newest (SA_RING_SPARE slots stay free for the samples that come while
 * the encoder catches up: a push that would overwrite a sample not yet encoded is dropped and counted); a `from` not
 * sampled yet discards the samples until it comes. sa_ring_begin returns the sample the encoding starts at. BEGIN
 * again (a pass begun again, a later entry) restarts from its sample out of the kept ones.
 *
 * Storage: 10-bit samples (the ADC's) packed in SA_RING_BYTES bytes each (the low 8 bits of the 9 values, then their
 * high 2 bits in 3 bytes); a value above 1023 is stored as 1023. The storage is the caller's (the Uno shares it with
 * the taxel frames' buffers, which are idle while the encoder runs).
 *
 * Concurrency (one producer, one consumer): push from an interrupt, pop from the main loop; head and tail are single
 * bytes (atomic on the AVR). arm and begin must run with the producer stopped (interrupts off on the board).
 */
#ifndef RIGCTL_SA_RING_H
#define RIGCTL_SA_RING_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define SA_RING_TAXELS 9
#define SA_RING_SAMPLES 32u         /* a power of 2, <= 128: 32 ms of samples at 1 kHz */
#define SA_RING_BYTES 12u           /* 9 x 10 bits, packed */
#define SA_RING_SPARE 4u            /* free slots left at BEGIN for the samples that come while the encoder catches up */
#define SA_RING_MAX_BACK (SA_RING_SAMPLES - SA_RING_SPARE) /* the furthest back a BEGIN can start: 28 samples */

typedef struct {
    uint8_t (*buf)[SA_RING_BYTES];  /* SA_RING_SAMPLES slots (the caller's storage) */
    volatile uint8_t head, tail;    /* free-running slot counters (mod 256): waiting to be encoded = head - tail */
    volatile uint8_t old;           /* the oldest slot kept: kept = head - old (<= SA_RING_SAMPLES) */
    volatile uint16_t head_seq;     /* the number of the next sample pushed (mod 65536) */
    volatile uint16_t skip;         /* samples still to discard before the encoding's first */
    volatile uint8_t encoding;      /* 0 armed (nothing waits), 1 encoding (a ring full of waiting samples drops) */
    volatile uint16_t dropped;      /* samples the full ring dropped while encoding (since ARM) */
    uint8_t depth_max;              /* the deepest it was while encoding (since ARM) */
} sa_ring_t;

/* Armed on `storage` (SA_RING_SAMPLES x SA_RING_BYTES bytes): empty, the next sample is sample 0. */
void sa_ring_arm(sa_ring_t *r, uint8_t (*storage)[SA_RING_BYTES]);
/* One sample (the producer); returns 0 if it was dropped (encoding, ring full), else 1. */
uint8_t sa_ring_push(sa_ring_t *r, const uint16_t x[SA_RING_TAXELS]);
/* Encode from sample `from` (mod 65536, header comment); returns the sample the encoding starts at. */
uint16_t sa_ring_begin(sa_ring_t *r, uint16_t from);
/* The next sample to encode into x (the consumer); returns 1 if there was one, else 0. */
uint8_t sa_ring_pop(sa_ring_t *r, uint16_t x[SA_RING_TAXELS]);
/* Samples waiting. */
uint8_t sa_ring_depth(const sa_ring_t *r);

#ifdef __cplusplus
}
#endif
#endif
