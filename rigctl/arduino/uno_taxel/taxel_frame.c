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
