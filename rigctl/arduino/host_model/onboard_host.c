/* onboard_host.c - the on-board encoder's C for the host (onboard_host.h): only glue, every rule in sa_ring.c and
 * sa_encoder.c. */
#include "onboard_host.h"

#include <string.h>

size_t onboard_host_sizeof(void) { return sizeof(onboard_host_t); }

void onboard_host_arm(onboard_host_t *b, const uint16_t lo[SA_N_TAXELS], const uint16_t hi[SA_N_TAXELS], uint16_t k)
{
    memcpy(b->cal_min, lo, sizeof b->cal_min);
    memcpy(b->cal_max, hi, sizeof b->cal_max);
    b->cal_k = k;
    sa_ring_arm(&b->ring, b->storage);
}

uint8_t onboard_host_push(onboard_host_t *b, const uint16_t x[SA_N_TAXELS]) { return sa_ring_push(&b->ring, x); }

uint16_t onboard_host_begin(onboard_host_t *b, uint16_t from)
{
    sa_init(&b->enc, b->cal_min, b->cal_max, b->cal_k);
    return sa_ring_begin(&b->ring, from);
}

uint8_t onboard_host_step(onboard_host_t *b, uint16_t *mask)
{
    uint16_t x[SA_N_TAXELS];
    if (!b->ring.encoding || !sa_ring_pop(&b->ring, x)) return 0;
    *mask = sa_step(&b->enc, x);
    return 1;
}

int8_t onboard_host_speed(onboard_host_t *b, uint16_t speed_cmm_s) { return sa_speed(&b->enc, speed_cmm_s); }

void onboard_host_finish(onboard_host_t *b, uint16_t speed_cmm_s)
{
    uint16_t mask;
    while (onboard_host_step(b, &mask)) {
    }
    sa_finish(&b->enc, speed_cmm_s);
}

void onboard_host_counts(const onboard_host_t *b, uint16_t counts[SA_N_TAXELS * SA_N_WINDOWS])
{
    memcpy(counts, b->enc.counts, sizeof b->enc.counts);
}

uint32_t onboard_host_samples(const onboard_host_t *b) { return b->enc.n; }
uint32_t onboard_host_held(const onboard_host_t *b) { return b->enc.held_windows; }
uint16_t onboard_host_dropped(const onboard_host_t *b) { return b->ring.dropped; }
uint8_t onboard_host_depth_max(const onboard_host_t *b) { return b->ring.depth_max; }
