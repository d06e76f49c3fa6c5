/* taxel_frame.c - the frame builder (docs/wire-protocol.md 1.1); see taxel_frame.h. */
#include "taxel_frame.h"
#include "../common/crc16.h"

void taxel_frame_build(uint8_t *out, uint16_t seq, uint8_t flags, const uint16_t *samples)
{
    uint8_t i;
    uint8_t *p = out + RIGCTL_FRAME_SAMPLES_OFFSET;
    uint16_t crc;
    out[RIGCTL_FRAME_SYNC_OFFSET] = RIGCTL_FRAME_SYNC0;
    out[RIGCTL_FRAME_SYNC_OFFSET + 1] = RIGCTL_FRAME_SYNC1;
    out[RIGCTL_FRAME_SEQ_OFFSET] = (uint8_t)seq;
    out[RIGCTL_FRAME_SEQ_OFFSET + 1] = (uint8_t)(seq >> 8);
    out[RIGCTL_FRAME_FLAGS_OFFSET] = flags;
    for (i = 0; i < RIGCTL_N_TAXELS; i++) {
        *p++ = (uint8_t)samples[i];
        *p++ = (uint8_t)(samples[i] >> 8);
    }
    crc = rigctl_crc16(out + RIGCTL_FRAME_CRC_START, RIGCTL_FRAME_CRC_OFFSET - RIGCTL_FRAME_CRC_START);
    out[RIGCTL_FRAME_CRC_OFFSET] = (uint8_t)crc;
    out[RIGCTL_FRAME_CRC_OFFSET + 1] = (uint8_t)(crc >> 8);
}

void spike_frame_build(uint8_t *out, uint16_t seq, uint8_t n, uint8_t flags, const uint16_t *masks)
{
    uint8_t i;
    uint8_t *p = out + RIGCTL_SPIKE_MASKS_OFFSET;
    uint16_t crc;
    out[0] = RIGCTL_SPIKE_SYNC0;
    out[1] = RIGCTL_SPIKE_SYNC1;
    out[RIGCTL_SPIKE_SEQ_OFFSET] = (uint8_t)seq;
    out[RIGCTL_SPIKE_SEQ_OFFSET + 1] = (uint8_t)(seq >> 8);
    out[RIGCTL_SPIKE_N_OFFSET] = n;
    out[RIGCTL_SPIKE_FLAGS_OFFSET] = flags;
    for (i = 0; i < RIGCTL_SPIKE_MASKS; i++) {
        uint16_t m = i < n ? masks[i] : 0u;
        *p++ = (uint8_t)m;
        *p++ = (uint8_t)(m >> 8);
    }
    crc = rigctl_crc16(out + RIGCTL_SPIKE_CRC_START, RIGCTL_SPIKE_CRC_OFFSET - RIGCTL_SPIKE_CRC_START);
    out[RIGCTL_SPIKE_CRC_OFFSET] = (uint8_t)crc;
    out[RIGCTL_SPIKE_CRC_OFFSET + 1] = (uint8_t)(crc >> 8);
}

void counts_frame_head(uint8_t *head, uint32_t samples, uint16_t held, uint16_t dropped, uint8_t queue_max,
                       const uint16_t *counts, uint8_t *crc_out)
{
    uint8_t i;
    uint16_t crc;
    head[0] = RIGCTL_COUNTS_SYNC0;
    head[1] = RIGCTL_COUNTS_SYNC1;
    for (i = 0; i < 4; i++) head[RIGCTL_COUNTS_SAMPLES_OFFSET + i] = (uint8_t)(samples >> (8 * i));
    head[RIGCTL_COUNTS_HELD_OFFSET] = (uint8_t)held;
    head[RIGCTL_COUNTS_HELD_OFFSET + 1] = (uint8_t)(held >> 8);
    head[RIGCTL_COUNTS_DROPPED_OFFSET] = (uint8_t)dropped;
    head[RIGCTL_COUNTS_DROPPED_OFFSET + 1] = (uint8_t)(dropped >> 8);
    head[RIGCTL_COUNTS_QUEUE_MAX_OFFSET] = queue_max;
    crc = rigctl_crc16(head + RIGCTL_COUNTS_CRC_START, RIGCTL_COUNTS_COUNTS_OFFSET - RIGCTL_COUNTS_CRC_START);
    for (i = 0; i < RIGCTL_ENC_N_TAXELS * RIGCTL_ENC_N_WINDOWS; i++) {
        uint8_t le[2];
        le[0] = (uint8_t)counts[i];
        le[1] = (uint8_t)(counts[i] >> 8);
        crc = rigctl_crc16_update(crc, le, 2);
    }
    crc_out[0] = (uint8_t)crc;
    crc_out[1] = (uint8_t)(crc >> 8);
}
