/* taxel_frame.h - pure logic of the Uno taxel streamer (no AVR registers): the frame builder of
 * docs/wire-protocol.md 1.1 and the multiplexer scan order. Compiled into the Uno image and the host tests. */
#ifndef TAXEL_FRAME_H
#define TAXEL_FRAME_H
#include <stdint.h>
#include "../common/rigctl_wire.h"
#ifdef __cplusplus
extern "C" {
#endif

/* Wiring (docs/firmware.md): three 74HC4051 8:1 analog multiplexers share the select lines S0-S2.
 * Mux m (0..2) feeds analog input A<m> and carries taxels 6*m .. 6*m+5 on its inputs Y0..Y5.
 * Conversion k (0..17) of a tick's scan reads analog input TAXEL_SCAN_ADC(k) with select value TAXEL_SCAN_SEL(k);
 * the select lines change only before every third conversion (k % 3 == 0). */
#define TAXEL_N_MUX            3
#define TAXEL_PER_MUX          6
#define TAXEL_SCAN_ADC(k)      ((uint8_t)((k) % TAXEL_N_MUX))
#define TAXEL_SCAN_SEL(k)      ((uint8_t)((k) / TAXEL_N_MUX))
#define TAXEL_SCAN_TAXEL(k)    ((uint8_t)(TAXEL_SCAN_ADC(k) * TAXEL_PER_MUX + TAXEL_SCAN_SEL(k)))

/* Build one 43-byte frame: sync, seq (LE), flags, 18 samples (LE uint16, channel 0 first), CRC-16/MODBUS over
 * bytes 2..40 (LE). samples are ADC counts 0-1023 (higher bits are sent as they are). */
void taxel_frame_build(uint8_t *out, uint16_t seq, uint8_t flags, const uint16_t *samples);

/* The encoder image's frames (docs/wire-protocol.md 1.5). A spike frame: sync, seq of its first sample, n (1-10)
 * samples, flags, the 10 spike masks (bit i = taxel i spiked; masks past n are 0), CRC-16 over bytes 2..25. */
void spike_frame_build(uint8_t *out, uint16_t seq, uint8_t n, uint8_t flags, const uint16_t *masks);
/* The counts frame's 11-byte head (sync, samples, held, dropped, queue_max); returns the CRC-16 over its bytes 2..10
 * and the 360 bytes of counts (uint16[9][20], little-endian in memory on the AVR and sent from there), which
 * follow it, and the CRC after them (crc_out, 2 bytes LE). */
void counts_frame_head(uint8_t *head, uint32_t samples, uint16_t held, uint16_t dropped, uint8_t queue_max,
                       const uint16_t *counts, uint8_t *crc_out);

#ifdef __cplusplus
}
#endif
#endif
