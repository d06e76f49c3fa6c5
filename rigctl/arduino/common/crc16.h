/* crc16.h - CRC-16/MODBUS (reflected poly 0xA001, init 0xFFFF), docs/wire-protocol.md 1.1 and 2.
 * One implementation for the AVR images (table in flash) and the host tests (table in RAM).
 * rigctl_crc16(data, n) over "123456789" is 0x4B37 (the catalogue check value). */
#ifndef RIGCTL_CRC16_H
#define RIGCTL_CRC16_H
#include <stdint.h>
#ifdef __cplusplus
extern "C" {
#endif
#define RIGCTL_CRC16_INIT 0xFFFFu
/* continue a CRC over n more bytes */
uint16_t rigctl_crc16_update(uint16_t crc, const uint8_t *data, uint16_t n);
/* CRC of n bytes from the initial value */
uint16_t rigctl_crc16(const uint8_t *data, uint16_t n);
#ifdef __cplusplus
}
#endif
#endif
