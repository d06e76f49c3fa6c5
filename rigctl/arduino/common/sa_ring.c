/* The on-board encoder's sample ring (sa_ring.h). */
#include "sa_ring.h"

#define SLOT(i) ((uint8_t)((i) & (SA_RING_SAMPLES - 1u)))

void sa_ring_arm(sa_ring_t *r, uint8_t (*storage)[SA_RING_BYTES]) {
    r->buf = storage;
    r->head = 0;
    r->tail = 0;
    r->old = 0;
    r->head_seq = 0;
    r->skip = 0;
    r->encoding = 0;
    r->dropped = 0;
    r->depth_max = 0;
}

uint8_t sa_ring_depth(const sa_ring_t *r) {
    return (uint8_t)(r->head - r->tail);
}

uint8_t sa_ring_push(sa_ring_t *r, const uint16_t x[SA_RING_TAXELS]) {
    uint8_t h = r->head;
    r->head_seq = (uint16_t)(r->head_seq + 1u);
    if (r->encoding && r->skip) { /* before the encoding's first sample: not kept */
        r->skip = (uint16_t)(r->skip - 1u);
        return 1;
    }
    if (r->encoding && (uint8_t)(h - r->tail) >= SA_RING_SAMPLES) { /* it would overwrite one not yet encoded */
        r->dropped = (uint16_t)(r->dropped + 1u);
        return 0;
    }
    if ((uint8_t)(h - r->old) >= SA_RING_SAMPLES) r->old = (uint8_t)(h + 1u - SA_RING_SAMPLES); /* the oldest goes */
    uint8_t *s = r->buf[SLOT(h)];
    uint8_t hi0 = 0, hi1 = 0, hi2 = 0;
    for (uint8_t i = 0; i < SA_RING_TAXELS; i++) {
        uint16_t v = x[i] > 1023u ? 1023u : x[i];
        s[i] = (uint8_t)(v & 0xFFu);
        uint8_t top = (uint8_t)(v >> 8);
        if (i < 4) hi0 |= (uint8_t)(top << (2u * i));
        else if (i < 8) hi1 |= (uint8_t)(top << (2u * (i - 4u)));
        else hi2 = top;
    }
    s[9] = hi0;
    s[10] = hi1;
    s[11] = hi2;
    r->head = (uint8_t)(h + 1u);
    if (!r->encoding) r->tail = r->head; /* armed: nothing waits */
    if (r->encoding) {
        uint8_t d = (uint8_t)(r->head - r->tail);
        if (d > r->depth_max) r->depth_max = d;
    }
    return 1;
}

uint16_t sa_ring_begin(sa_ring_t *r, uint16_t from) {
    uint8_t kept = (uint8_t)(r->head - r->old);
    uint16_t back = (uint16_t)(r->head_seq - from); /* samples from `from` to the newest, inclusive */
    r->encoding = 1;
    r->skip = 0;
    if (back >= 0x8000u) { /* not sampled yet: discard until it comes (and the samples kept: their numbers go) */
        r->tail = r->head;
        r->old = r->head;
        r->skip = (uint16_t)(from - r->head_seq);
        return from;
    }
    uint16_t limit = kept < SA_RING_MAX_BACK ? kept : SA_RING_MAX_BACK;
    if (back > limit) back = limit;
    r->tail = (uint8_t)(r->head - (uint8_t)back);
    if ((uint8_t)back > r->depth_max) r->depth_max = (uint8_t)back;
    return (uint16_t)(r->head_seq - back);
}

uint8_t sa_ring_pop(sa_ring_t *r, uint16_t x[SA_RING_TAXELS]) {
    uint8_t t = r->tail;
    if (t == r->head) return 0;
    const uint8_t *s = r->buf[SLOT(t)];
    for (uint8_t i = 0; i < SA_RING_TAXELS; i++) {
        uint8_t top = i < 4 ? (uint8_t)(s[9] >> (2u * i)) : i < 8 ? (uint8_t)(s[10] >> (2u * (i - 4u))) : s[11];
        x[i] = (uint16_t)(s[i] | ((uint16_t)(top & 3u) << 8));
    }
    r->tail = (uint8_t)(t + 1u);
    return 1;
}
