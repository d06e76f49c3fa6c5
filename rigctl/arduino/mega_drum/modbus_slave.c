/* modbus_slave.c - see modbus_slave.h */
#include "modbus_slave.h"
#include "../common/crc16.h"
#include "../common/rigctl_wire.h"

static uint16_t be16(const uint8_t *p)
{
    return (uint16_t)(((uint16_t)p[0] << 8) | p[1]);
}

static uint16_t finish(uint8_t *resp, uint16_t n)
{
    uint16_t crc = rigctl_crc16(resp, n);
    resp[n] = (uint8_t)crc;
    resp[n + 1] = (uint8_t)(crc >> 8);
    return (uint16_t)(n + 2);
}

static uint16_t exception(uint8_t *resp, uint8_t id, uint8_t fc, uint8_t code)
{
    resp[0] = id;
    resp[1] = (uint8_t)(fc | 0x80);
    resp[2] = code;
    return finish(resp, 3);
}

uint8_t mb_handle(const mb_slave_t *s, const uint8_t *req, uint16_t len, uint8_t *resp, uint16_t *resp_len)
{
    uint8_t id, fc, ex = 0;
    uint16_t crc, start, count, i, n = 0;
    *resp_len = 0;
    if (len < 4 || len > MB_MAX_FRAME) return MB_IGNORED;
    crc = rigctl_crc16(req, (uint16_t)(len - 2));
    if (req[len - 2] != (uint8_t)crc || req[len - 1] != (uint8_t)(crc >> 8)) return MB_IGNORED;
    id = req[0];
    if (id != s->device_id && id != 0) return MB_IGNORED;
    fc = req[1];
    len = (uint16_t)(len - 2); /* PDU + address, without CRC */

    switch (fc) {
    case RIGCTL_MB_FC_READ_HOLDING:
    case RIGCTL_MB_FC_READ_INPUT: {
        uint16_t limit = fc == RIGCTL_MB_FC_READ_HOLDING ? s->n_holding : s->n_input;
        if (id == 0) return MB_IGNORED; /* reads are never broadcast */
        if (len != 6) { ex = RIGCTL_MB_EX_ILLEGAL_VALUE; break; }
        start = be16(req + 2);
        count = be16(req + 4);
        if (count < 1 || count > 125) { ex = RIGCTL_MB_EX_ILLEGAL_VALUE; break; }
        if ((uint32_t)start + count > limit) { ex = RIGCTL_MB_EX_ILLEGAL_ADDRESS; break; }
        resp[0] = id;
        resp[1] = fc;
        resp[2] = (uint8_t)(2 * count);
        n = 3;
        for (i = 0; i < count; i++) {
            uint16_t v = fc == RIGCTL_MB_FC_READ_HOLDING ? s->read_holding(s->ctx, (uint16_t)(start + i))
                                                         : s->read_input(s->ctx, (uint16_t)(start + i));
            resp[n++] = (uint8_t)(v >> 8);
            resp[n++] = (uint8_t)v;
        }
        break;
    }
    case RIGCTL_MB_FC_WRITE_SINGLE: {
        uint16_t v;
        if (len != 6) { ex = RIGCTL_MB_EX_ILLEGAL_VALUE; break; }
        start = be16(req + 2);
        v = be16(req + 4);
        if (start >= s->n_holding) { ex = RIGCTL_MB_EX_ILLEGAL_ADDRESS; break; }
        ex = s->write_holding(s->ctx, start, 1, &v);
        if (ex) break;
        for (i = 0; i < 6; i++) resp[i] = req[i];
        n = 6;
        break;
    }
    case RIGCTL_MB_FC_WRITE_MULTIPLE: {
        uint16_t values[123];
        if (len < 7) { ex = RIGCTL_MB_EX_ILLEGAL_VALUE; break; }
        start = be16(req + 2);
        count = be16(req + 4);
        if (count < 1 || count > 123 || req[6] != 2 * count || len != 7 + 2 * count) {
            ex = RIGCTL_MB_EX_ILLEGAL_VALUE;
            break;
        }
        if ((uint32_t)start + count > s->n_holding) { ex = RIGCTL_MB_EX_ILLEGAL_ADDRESS; break; }
        for (i = 0; i < count; i++) values[i] = be16(req + 7 + 2 * i);
        ex = s->write_holding(s->ctx, start, count, values);
        if (ex) break;
        for (i = 0; i < 6; i++) resp[i] = req[i];
        n = 6;
        break;
    }
    default:
        ex = RIGCTL_MB_EX_ILLEGAL_FUNCTION;
        break;
    }
    if (id == 0) return MB_BROADCAST; /* broadcasts never get a reply, not even an exception */
    *resp_len = ex ? exception(resp, id, fc, ex) : finish(resp, n);
    return MB_ADDRESSED;
}
