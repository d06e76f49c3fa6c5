/*
 * sa_stream.c - runs a stream image (sa_bench/sa_bench.c) under simavr: stdin bytes are served to the firmware's
 * reads of GPIOR2 (0 once stdin is exhausted), its writes of GPIOR0 go to stdout, and its writes of GPIOR1 mark
 * the cycle counter: the cycles from each mark 1 to the next mark 2 are summed, and at the end one line
 * "CYCLES steps=N mean=M max=X total=T" goes to stderr; marks 3 and 4 likewise (the speeds: sa_speed, which scales
 * the windows), reported as "SPEEDS n=N mean=M max=X". Not paced: simulated time runs as fast as the host can.
 *
 *   sa_stream MCU FIRMWARE.elf < input > output        (MCU: atmega328p | atmega2560; 16 MHz)
 */
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <unistd.h>

#include "sim_avr.h"
#include "sim_elf.h"

#define GPIOR0_ADDR 0x3E /* data-space addresses, the same on the ATmega328P and the ATmega2560 */
#define GPIOR1_ADDR 0x4A
#define GPIOR2_ADDR 0x4B

static uint8_t *in_buf;
static size_t in_len, in_pos;
static FILE *out; /* the firmware's bytes: the real stdout (simavr logs its loading on stdout, moved to stderr) */
static uint64_t mark_at, steps, total, worst;
static uint64_t speed_at, speeds, speed_total, speed_worst;

static uint8_t read_in(struct avr_t *avr, avr_io_addr_t addr, void *param)
{
    (void)avr; (void)addr; (void)param;
    return in_pos < in_len ? in_buf[in_pos++] : 0;
}

static void write_out(struct avr_t *avr, avr_io_addr_t addr, uint8_t v, void *param)
{
    (void)avr; (void)addr; (void)param;
    fputc(v, out);
}

static void write_mark(struct avr_t *avr, avr_io_addr_t addr, uint8_t v, void *param)
{
    (void)addr; (void)param;
    if (v == 1) {
        mark_at = avr->cycle;
    } else if (v == 2) {
        uint64_t c = avr->cycle - mark_at;
        steps++;
        total += c;
        if (c > worst) worst = c;
    } else if (v == 3) {
        speed_at = avr->cycle;
    } else if (v == 4) {
        uint64_t c = avr->cycle - speed_at;
        speeds++;
        speed_total += c;
        if (c > speed_worst) speed_worst = c;
    }
}

int main(int argc, char **argv)
{
    if (argc != 3) {
        fprintf(stderr, "usage: sa_stream MCU FIRMWARE.elf < input > output\n");
        return 2;
    }
    int out_fd = dup(1);
    if (out_fd < 0 || dup2(2, 1) < 0 || !(out = fdopen(out_fd, "wb"))) {
        perror("sa_stream");
        return 1;
    }
    size_t cap = 1 << 20;
    in_buf = malloc(cap);
    size_t got;
    while (in_buf && (got = fread(in_buf + in_len, 1, cap - in_len, stdin)) > 0) {
        in_len += got;
        if (in_len == cap) in_buf = realloc(in_buf, cap *= 2);
    }
    elf_firmware_t fw = {{0}};
    if (!in_buf || elf_read_firmware(argv[2], &fw) != 0) {
        fprintf(stderr, "sa_stream: cannot read %s\n", argv[2]);
        return 1;
    }
    avr_t *avr = avr_make_mcu_by_name(argv[1]);
    if (!avr) {
        fprintf(stderr, "sa_stream: unknown MCU %s\n", argv[1]);
        return 1;
    }
    avr_init(avr);
    avr->frequency = 16000000;
    avr->log = 0;
    avr_load_firmware(avr, &fw);
    avr_register_io_read(avr, GPIOR2_ADDR, read_in, NULL);
    avr_register_io_write(avr, GPIOR0_ADDR, write_out, NULL);
    avr_register_io_write(avr, GPIOR1_ADDR, write_mark, NULL);
    int state;
    do {
        state = avr_run(avr);
    } while (state != cpu_Done && state != cpu_Crashed);
    fflush(out);
    fprintf(stderr, "CYCLES steps=%llu mean=%llu max=%llu total=%llu\n", (unsigned long long)steps,
            (unsigned long long)(steps ? total / steps : 0), (unsigned long long)worst, (unsigned long long)total);
    fprintf(stderr, "SPEEDS n=%llu mean=%llu max=%llu\n", (unsigned long long)speeds,
            (unsigned long long)(speeds ? speed_total / speeds : 0), (unsigned long long)speed_worst);
    return state == cpu_Crashed;
}
