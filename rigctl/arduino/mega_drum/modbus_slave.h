/* modbus_slave.h - Modbus RTU request handler (function codes 03, 04, 06, 16; exceptions 01/02/03), pure:
 * takes one complete frame (delimited by t3.5 silence by the caller) and builds the response.
 * docs/wire-protocol.md section 2. */
#ifndef MODBUS_SLAVE_H
#define MODBUS_SLAVE_H
#include <stdint.h>
#ifdef __cplusplus
extern "C" {
#endif

#define MB_MAX_FRAME 256

typedef struct {
    uint8_t device_id;
    uint16_t n_holding;
    uint16_t n_input;
    void *ctx;
    uint16_t (*read_holding)(void *ctx, uint16_t addr);
    uint16_t (*read_input)(void *ctx, uint16_t addr);
    /* write n registers from start (values in host order); all or nothing: returns 0, or an exception code
     * (RIGCTL_MB_EX_ILLEGAL_VALUE) with nothing changed */
    uint8_t (*write_holding)(void *ctx, uint16_t start, uint16_t n, const uint16_t *values);
} mb_slave_t;

/* outcome of mb_handle */
#define MB_IGNORED    0 /* too short, bad CRC or another device: no reply */
#define MB_ADDRESSED  1 /* a valid request for this device (feeds the watchdog) */
#define MB_BROADCAST  2 /* a valid broadcast (device 0): executed, no reply */

/* Handle one frame req[0..len). Writes the reply into resp (up to MB_MAX_FRAME bytes) and its length into
 * *resp_len (0 = no reply). Returns MB_IGNORED, MB_ADDRESSED or MB_BROADCAST. A malformed request for this
 * device (wrong length for its function) gets exception 03; unknown functions get 01. */
uint8_t mb_handle(const mb_slave_t *s, const uint8_t *req, uint16_t len, uint8_t *resp, uint16_t *resp_len);

#ifdef __cplusplus
}
#endif
#endif
