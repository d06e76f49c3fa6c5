/*
 * sa_bench.c - the on-board SA encoder (common/sa_encoder.c) on the AVR core, fed and read by the simavr stream
 * harness (simavr/sa_stream.c), for the HIL comparison with the host encoder and the cycle budget
 * (tests/firmware/test_fw_sa_encoder.py, docs/firmware.md "The on-board SA encoder"). Built for the ATmega328P
 * (build/sa_bench_uno.elf) and the ATmega2560 (build/sa_bench_mega.elf); never flashed.
 *
 * Byte streams through general-purpose I/O registers (no UART, so nothing but the encoder runs): each read of
 * GPIOR2 takes the harness's next input byte, each write of GPIOR0 gives it an output byte, and writes of GPIOR1
 * mark the cycle counter (1 = a step starts, 2 = it ended; 3, 4 = the same around a speed: sa_speed scales the
 * windows waiting for it). Input, little-endian:
 *   9 x uint16 minimum count, 9 x uint16 maximum count (sa_init, k = 100), then commands:
 *   'x' + 9 x uint16 ADC counts   one 1 ms sample: sa_step; output: the spike mask, uint16
 *   's' + uint16 speed_cmm_s      sa_speed (the next window's mean speed, 0.01 mm/s)
 *   'f' + uint16 speed_cmm_s      sa_finish; output: counts 9 x 20 x uint16, held_windows uint16
 *   anything else                 stop (cli; sleep: the harness exits)
 */
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/sleep.h>

#include "../common/sa_encoder.h"

static sa_encoder_t enc;

static uint16_t in16(void)
{
    uint8_t lo = GPIOR2;
    return (uint16_t)(lo | ((uint16_t)GPIOR2 << 8));
}

static void out16(uint16_t v)
{
    GPIOR0 = (uint8_t)v;
    GPIOR0 = (uint8_t)(v >> 8);
}

int main(void)
{
    uint16_t lo[SA_N_TAXELS], hi[SA_N_TAXELS], x[SA_N_TAXELS];
    for (uint8_t i = 0; i < SA_N_TAXELS; i++) lo[i] = in16();
    for (uint8_t i = 0; i < SA_N_TAXELS; i++) hi[i] = in16();
    sa_init(&enc, lo, hi, 100);
    for (;;) {
        uint8_t cmd = GPIOR2;
        if (cmd == 'x') {
            for (uint8_t i = 0; i < SA_N_TAXELS; i++) x[i] = in16();
            GPIOR1 = 1;
            uint16_t m = sa_step(&enc, x);
            GPIOR1 = 2;
            out16(m);
        } else if (cmd == 's') {
            uint16_t s = in16();
            GPIOR1 = 3;
            sa_speed(&enc, s);
            GPIOR1 = 4;
        } else if (cmd == 'f') {
            sa_finish(&enc, in16());
            for (uint8_t i = 0; i < SA_N_TAXELS; i++)
                for (uint8_t k = 0; k < SA_N_WINDOWS; k++) out16(enc.counts[i][k]);
            out16((uint16_t)enc.held_windows);
        } else {
            break;
        }
    }
    cli();
    sleep_cpu();
    return 0;
}
