/*
 * mega_drum.cpp - Arduino Mega 2560 (ATmega2560, 16 MHz) drum controller: the hardware glue around the pure
 * logic (controller.c, modbus_slave.c, steprate.c, force_pi.c). docs/wire-protocol.md section 2.
 *
 *   UART0   Modbus RTU slave at 500000 8N1 (UBRR = 1, 16x sampling: exact), receive and transmit interrupt driven
 *   Timer4  t3.5 frame timer: restarted by every received byte, its compare match (1.75 ms) ends the frame
 *   Timer2  1 kHz control tick (CTC, /64, OCR2A = 249)
 *   Timer1  drum step generator: CTC, its compare interrupt makes one STEP pulse and loads the next period,
 *           so the acceleration ramp changes the rate only between steps
 *   Timer3  actuator (lead-screw stepper) step generator, same scheme, counts the actuator position
 *   Timer5  drum index sensor (D48 = ICP5): free running /1024 (64 us), input capture of the sensor's falling edge
 *   INT2    drum speed marks (D19): the falling edge of each of the disc's marks, timestamped on Timer5 in the ISR
 *   HX711   bit-banged in loop() whenever DOUT goes low (10 or 80 SPS, the rate timed at boot: ctl_hx711_ready),
 *           25 clocks (channel A, gain 128)
 *   EEPROM  calibration (load-cell scale, actuator steps/mm) with a magic word and CRC, the boot counter, the
 *           watchdog's "about to reset" mark
 *   WDT     120 ms, fed only by loop(): interrupt first (drivers off, step timers stopped, mark in EEPROM), then
 *           the reset; MCUSR is read and cleared and the WDT disabled in .init3, before the C runtime's init
 *   INT4    e-stop input (D2): drops the drivers' EN and stops both step timers inside the interrupt
 * Timer0 stays with the Arduino core (millis, unused here). HardwareSerial is not linked.
 *
 * Safety does not depend on loop(): the e-stop acts in its ISR, a hung loop() is ended by the watchdog within 120 ms
 * (its interrupt disables the drivers first), and after any reset the drivers stay disabled (EN high from the first
 * instructions, pulled up on the board during reset) and the controller stays NOT_HOMED until HOME.
 */
#include <Arduino.h>
#include <avr/eeprom.h>
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/sleep.h>
#include <avr/wdt.h>
#include <util/delay.h>

#include "../common/crc16.h"
#include "../common/rigctl_wire.h"
#include "controller.h"
#include "drum_config.h"
#include "modbus_slave.h"
#include "steprate.h"

/* the Modbus link's UART divisor: exact or refused at build time (a rate the clock cannot divide into drifts) */
#define MEGA_UBRR ((uint16_t)(F_CPU / (16UL * RIGCTL_DRUM_BAUD) - 1))
#if F_CPU % (16UL * RIGCTL_DRUM_BAUD) != 0
#error "RIGCTL_DRUM_BAUD is not exact at F_CPU with 16x sampling"
#endif

static ctl_t ctl;
static mb_slave_t mb;

/* ---- Modbus receive/transmit ---- */
static uint8_t rx_buf[MB_MAX_FRAME];
static volatile uint16_t rx_len;
static volatile uint8_t rx_overflow;
static volatile uint8_t frame_ready;
static uint8_t tx_buf[MB_MAX_FRAME];
static volatile uint16_t tx_len, tx_pos;

/* ---- time ---- */
static volatile uint32_t tick_ms;

/* ---- step generators ---- */
static volatile steptimer_t drum_next;   /* loaded at the next step */
static volatile uint8_t drum_running_cs; /* clock select running now, 0 = stopped */
static volatile uint16_t drum_running_ocr;
static volatile uint16_t drum_step_in_rev;
static volatile uint16_t drum_revs;
static volatile uint8_t index_pending;   /* index mark passed: raise the index output */
/* index sensor (Timer5 input capture; docs/wire-protocol.md 2.6) */
#define INDEX_LOST_STEPS ((uint32_t)DRUM_USTEPS_PER_REV * 3u / 2u) /* 1.5 revolutions without an edge: fallback */
#define INDEX_DEBOUNCE_TICKS 313u /* 20 ms of 64 us ticks: edges this close to the last are the same mark (a
                                   * revolution takes >= 98 ms even at 200 mm/s with a driver at 1/16 the steps) */
static volatile uint32_t steps_since_sensor; /* drum steps since the last sensor edge */
static volatile uint8_t sensor_live;
static volatile uint16_t t5_overflows;
static volatile uint32_t sensor_last_ticks;
static volatile uint32_t sensor_period_ticks;  /* 64 us ticks between the last two edges */
static volatile uint16_t sensor_steps;         /* drum steps between the last two edges */
static volatile uint16_t sensor_edges;
/* speed marks (INT2, timestamped on Timer5; docs/wire-protocol.md 2.6) */
#define MARK_DEBOUNCE_TICKS 78u /* 5 ms of 64 us ticks: a mark interval takes >= 196 ms at 200 mm/s */
static volatile uint32_t steps_since_mark; /* drum steps since the last mark (0 while the drum is at rest) */
static volatile uint8_t mark_fresh;        /* the last mark came while the drum was stepped: the next interval counts */
static volatile uint32_t mark_last_ticks;
static volatile uint32_t mark_period_ticks; /* 64 us ticks between the last two marks */
static volatile uint16_t mark_steps;        /* drum steps between the last two marks */
static volatile uint16_t mark_count;
static volatile steptimer_t act_next;
static volatile uint8_t act_next_dir;    /* 1 = towards the sensor */
static volatile uint8_t act_dir;
static volatile uint8_t act_running_cs;
static volatile int32_t act_steps;

/* ---- safety outside loop() ---- */
static uint8_t mcusr_at_boot __attribute__((section(".noinit")));
static volatile uint8_t motion_inhibit; /* e-stop or watchdog: no step timer may run, EN stays high */

/* .init3 runs before the C runtime clears .bss and long before setup(): keep the reset cause, clear MCUSR (WDRF
 * forces WDE on, and a watchdog left running at its 16 ms reset value would reset the MCU in a loop: avr-libc,
 * <avr/wdt.h>), and put the drivers' pins in their safe state (EN high = disabled, both STEP pins low). */
extern "C" void early_init(void) __attribute__((naked, used, section(".init3")));
extern "C" void early_init(void)
{
    mcusr_at_boot = MCUSR;
    MCUSR = 0;
    wdt_disable();
    PIN_EN_PORT |= (1 << PIN_EN_BIT);
    PIN_EN_DDR |= (1 << PIN_EN_BIT);
    PIN_DRUM_STEP_PORT &= (uint8_t)~(1 << PIN_DRUM_STEP_BIT);
    PIN_DRUM_STEP_DDR |= (1 << PIN_DRUM_STEP_BIT);
    PIN_ACT_STEP_PORT &= (uint8_t)~(1 << PIN_ACT_STEP_BIT);
    PIN_ACT_STEP_DDR |= (1 << PIN_ACT_STEP_BIT);
}

/* drivers off, both step generators stopped, STEP pins low; call with interrupts off (an ISR) */
static void motion_kill(void)
{
    PIN_EN_PORT |= (1 << PIN_EN_BIT);
    TCCR1B = (1 << WGM12);
    TCCR3B = (1 << WGM32);
    drum_next.cs = 0; /* the generators' own record: stopped, so that they start from rest once allowed again */
    drum_running_cs = 0;
    act_next.cs = 0;
    act_running_cs = 0;
    PIN_DRUM_STEP_PORT &= (uint8_t)~(1 << PIN_DRUM_STEP_BIT);
    PIN_ACT_STEP_PORT &= (uint8_t)~(1 << PIN_ACT_STEP_BIT);
    motion_inhibit = 1;
}

static volatile uint8_t estop_latched;
static void estop_check_isr(void)
{
    if ((PIN_ESTOP_PIN >> PIN_ESTOP_BIT) & 1) { /* open: pressed, or the wire is broken */
        motion_kill();
        estop_latched = 1;
    }
}

ISR(INT4_vect)
{
    estop_check_isr();
}

/* the HX711's DOUT falling (data ready) only wakes loop() from its idle sleep, which reads the conversion */
EMPTY_INTERRUPT(INT5_vect)

#define EE_WDT_MARK 0xA5
static uint8_t EEMEM ee_wdt_mark;

/* the watchdog's first timeout (interrupt mode): loop() has not run for 120 ms. Make the rig safe, record the cause
 * (the stk500v2 bootloader clears MCUSR), and let the second timeout reset the MCU. */
ISR(WDT_vect)
{
    motion_kill();
    eeprom_write_byte(&ee_wdt_mark, EE_WDT_MARK);
    /* interrupt mode off, reset mode on (the hardware clears WDIE itself; simavr 1.6 does not) */
    WDTCSR = (1 << WDCE) | (1 << WDE);
    WDTCSR = (1 << WDE) | (1 << WDP1) | (1 << WDP0); /* WDTO_120MS */
    for (;;) {
    }
}

ISR(USART0_RX_vect)
{
    uint8_t status = UCSR0A; /* read before UDR0: frame error / data overrun of this byte */
    uint8_t c = UDR0;
    if (status & ((1 << FE0) | (1 << DOR0))) rx_overflow = 1; /* damaged frame: dropped at t3.5 */
    if (!frame_ready) {
        if (rx_len < MB_MAX_FRAME) rx_buf[rx_len++] = c;
        else rx_overflow = 1;
    }
    /* restart the t3.5 timer */
    TCNT4 = 0;
    TIFR4 = (1 << OCF4A);
    TCCR4B = (1 << WGM42) | (1 << CS41) | (1 << CS40); /* CTC, /64: 4 us ticks */
}

ISR(TIMER4_COMPA_vect)
{
    TCCR4B = (1 << WGM42); /* stop */
    if (rx_len > 0) {
        if (rx_overflow) {
            rx_len = 0;
            rx_overflow = 0;
        } else {
            frame_ready = 1;
        }
    }
}

ISR(USART0_UDRE_vect)
{
    UDR0 = tx_buf[tx_pos++];
    if (tx_pos >= tx_len) UCSR0B &= (uint8_t)~(1 << UDRIE0);
}

ISR(TIMER2_COMPA_vect)
{
    tick_ms++;
}

ISR(TIMER1_COMPA_vect)
{
    PIN_DRUM_STEP_PORT |= (1 << PIN_DRUM_STEP_BIT);
    uint16_t s = drum_step_in_rev + 1;
    uint32_t ss = steps_since_sensor + 1;
    steps_since_sensor = ss;
    steps_since_mark++;
    if (sensor_live && ss > INDEX_LOST_STEPS) sensor_live = 0; /* no edge for 1.5 revolutions: the step count */
    if (s >= DRUM_USTEPS_PER_REV) {
        s = 0;
        if (!sensor_live) { /* fallback: the step count marks the index */
            drum_revs++;
            PIN_INDEX_PORT |= (1 << PIN_INDEX_BIT);
            index_pending = 1;
        }
    }
    drum_step_in_rev = s;
    uint8_t cs = drum_next.cs;
    if (cs) {
        OCR1A = drum_next.ocr;
        drum_running_ocr = drum_next.ocr;
    }
    TCCR1B = (uint8_t)((1 << WGM12) | cs);
    drum_running_cs = cs;
    PIN_DRUM_STEP_PORT &= (uint8_t)~(1 << PIN_DRUM_STEP_BIT); /* >= 2 us pulse */
}

ISR(TIMER5_OVF_vect)
{
    t5_overflows++;
}

/* the index sensor's falling edge: the real index mark */
ISR(TIMER5_CAPT_vect)
{
    uint16_t icr = ICR5;
    uint32_t ovf = t5_overflows;
    if ((TIFR5 & (1 << TOV5)) && icr < 0x8000u) ovf++; /* an overflow not yet counted came before the capture */
    uint32_t t = (ovf << 16) | icr;
    if (sensor_edges && t - sensor_last_ticks < INDEX_DEBOUNCE_TICKS) return; /* contact bounce of the same mark */
    uint32_t steps = steps_since_sensor;
    if (sensor_edges) {
        sensor_period_ticks = t - sensor_last_ticks;
        sensor_steps = steps > 0xFFFFu ? 0xFFFFu : (uint16_t)steps;
    }
    sensor_last_ticks = t;
    sensor_edges++;
    steps_since_sensor = 0;
    sensor_live = 1;
    drum_revs++;
    PIN_INDEX_PORT |= (1 << PIN_INDEX_BIT);
    index_pending = 1;
}

/* Timer5's 32-bit count now (64 us ticks); call with interrupts off */
static uint32_t timer5_ticks(void)
{
    uint16_t tc = TCNT5;
    uint32_t ovf = t5_overflows;
    if ((TIFR5 & (1 << TOV5)) && tc < 0x8000u) ovf++; /* an overflow not yet counted came before the read */
    return (ovf << 16) | tc;
}

/* a speed mark's falling edge: the drum turned 1 / DRUM_MARKS_PER_REV of a revolution since the last one */
ISR(INT2_vect)
{
    uint32_t t = timer5_ticks();
    if (mark_count && t - mark_last_ticks < MARK_DEBOUNCE_TICKS) return; /* bounce of the same mark */
    uint32_t steps = steps_since_mark;
    if (mark_fresh && steps) {
        mark_period_ticks = t - mark_last_ticks;
        mark_steps = steps > 0xFFFFu ? 0xFFFFu : (uint16_t)steps;
    }
    mark_fresh = steps != 0;
    mark_last_ticks = t;
    steps_since_mark = 0;
    mark_count++;
}

static void index_sensor_setup(void)
{
    PIN_MARK_SENSOR_PORT |= (1 << PIN_MARK_SENSOR_BIT); /* pull-up: open-collector sensor */
    EICRA = (uint8_t)((EICRA & ~((1 << ISC21) | (1 << ISC20))) | (1 << ISC21)); /* INT2 falling edge */
    EIFR = (1 << INTF2);
    EIMSK |= (1 << INT2);
    PIN_INDEX_SENSOR_PORT |= (1 << PIN_INDEX_SENSOR_BIT); /* pull-up: open-collector sensor */
    TCCR5A = 0;
    TCCR5B = (1 << ICNC5) | (1 << CS52) | (1 << CS50); /* normal mode, noise canceler, falling edge, /1024 */
    TIFR5 = (1 << ICF5) | (1 << TOV5);
    TIMSK5 = (1 << ICIE5) | (1 << TOIE5);
}

/* what the controller reports of the index (call with interrupts off) */
static void index_to_controller(void)
{
    ctl.index_source = sensor_live ? RIGCTL_INDEX_SOURCE_SENSOR : RIGCTL_INDEX_SOURCE_STEPS;
    ctl.drum_step_in_rev = sensor_live ? (uint16_t)(steps_since_sensor % DRUM_USTEPS_PER_REV) : drum_step_in_rev;
    ctl.drum_revolutions = drum_revs;
    if (sensor_edges >= 2) {
        uint32_t ms = (sensor_period_ticks * 64u + 500u) / 1000u;
        ctl.index_period_ms = ms > 0xFFFFu ? 0xFFFFu : (uint16_t)ms;
        ctl.index_steps = sensor_steps;
    }
    ctl.index_count = sensor_edges;
    /* speed marks: the interval's period and steps; the slip check while the drum is stepped, armed from power-up
     * (a missing or unplugged disc sensor latches at the first RUN) and re-armed at rest (the first interval after
     * a start runs from the start: never late, and not reported) */
    uint32_t p = (mark_period_ticks * 64u + 50u) / 100u;
    ctl.mark_period_0p1ms = p > 0xFFFFu ? 0xFFFFu : (uint16_t)p;
    ctl.mark_steps = mark_steps;
    ctl.mark_count = mark_count;
    if (!drum_running_cs) {
        steps_since_mark = 0;
        mark_fresh = 0;
    } else if (steps_since_mark > DRUM_SLIP_STEPS) {
        ctl.drum_slip = 1;
        steps_since_mark = 0; /* re-armed: the deceleration that follows (< 1 interval) does not latch it again */
        mark_fresh = 0;
    }
}

ISR(TIMER3_COMPA_vect)
{
    PIN_ACT_STEP_PORT |= (1 << PIN_ACT_STEP_BIT);
    act_steps += act_dir ? 1 : -1;
    uint8_t cs = act_next.cs;
    if (cs) OCR3A = act_next.ocr;
    TCCR3B = (uint8_t)((1 << WGM32) | cs);
    act_running_cs = cs;
    _delay_us(1);
    PIN_ACT_STEP_PORT &= (uint8_t)~(1 << PIN_ACT_STEP_BIT);
    /* direction for the next step, set well before its pulse */
    act_dir = act_next_dir;
    if (act_dir) PIN_ACT_DIR_PORT |= (1 << PIN_ACT_DIR_BIT);
    else PIN_ACT_DIR_PORT &= (uint8_t)~(1 << PIN_ACT_DIR_BIT);
}

/* ---- EEPROM calibration ---- */
/* firmware 1.0's record (16-bit scale), still read so that an upgrade keeps its calibration */
struct calib_v1_t {
    uint16_t magic;
    uint16_t loadcell_scale_x100;
    uint16_t actuator_steps_per_mm;
    uint16_t crc;
};
#define CALIB_V1_MAGIC 0x5243 /* "RC" */
static calib_v1_t EEMEM ee_calib;
/* firmware 1.1: the signed 32-bit scale */
struct calib_t {
    uint16_t magic;
    int32_t loadcell_scale_x100;
    uint16_t actuator_steps_per_mm;
    uint16_t crc;
};
#define CALIB_MAGIC 0x5253 /* "RS" */
static calib_t EEMEM ee_calib2;
/* firmware 1.2: the tare's raw zero too (spec 2.11: HOME's sign-free direction check after a reset) */
struct calib3_t {
    uint16_t magic;
    int32_t loadcell_scale_x100;
    uint16_t actuator_steps_per_mm;
    int32_t zero_raw;
    uint16_t crc;
};
#define CALIB3_MAGIC 0x525A /* "RZ" */
#define CALIB_NO_ZERO INT32_MIN
static calib3_t EEMEM ee_calib3;
/* firmware 1.5: the contact's stiffness stored with the calibration too (spec 2.12: the reading's scale checked
 * against it at every probe; 0: none) */
struct calib4_t {
    uint16_t magic;
    int32_t loadcell_scale_x100;
    uint16_t actuator_steps_per_mm;
    int32_t zero_raw;
    uint16_t stiffness_g_mm;
    uint16_t crc;
};
#define CALIB4_MAGIC 0x524B /* "RK" */
static calib4_t EEMEM ee_calib4;
static uint16_t EEMEM ee_boot_count;

/* BOOT_COUNT (spec 2.7): EEPROM is written only at a cold boot (power-on or brown-out, or RAM lost); a warm reset
 * (reset pin, the DTR of a port opening, the watchdog) counts in RAM, which survives it. The high byte counts cold
 * boots (EEPROM), the low byte warm resets since (0 = this is a cold boot): every reset changes the value. */
#define WARM_MAGIC 0x5752 /* "WR" */
static struct {
    uint16_t magic, cold, warm;
    uint16_t away; /* the warm-boot record (spec 2.7, issue 76): the controller's `away` at the reset */
    uint16_t check;
} warm_boot __attribute__((section(".noinit")));

static uint16_t warm_check(void)
{
    return (uint16_t)(warm_boot.magic ^ warm_boot.cold ^ warm_boot.warm ^ warm_boot.away ^ 0xA55A);
}

/* the RAM survived the reset (not a power-on or brown-out, and the record's check holds) */
static uint8_t warm_record_valid(void)
{
    return !(mcusr_at_boot & (RIGCTL_RESET_POWER_ON | RIGCTL_RESET_BROWN_OUT)) && warm_boot.magic == WARM_MAGIC &&
           warm_boot.check == warm_check();
}

/* the controller's `away` into the record (every tick; RAM only) */
static void warm_record_away(uint8_t away)
{
    if (warm_boot.away != away) {
        warm_boot.away = away;
        warm_boot.check = warm_check();
    }
}

static uint16_t boot_count(void)
{
    if (!warm_record_valid()) {
        warm_boot.cold = (uint16_t)(eeprom_read_word(&ee_boot_count) + 1); /* erased EEPROM 0xFFFF: first boot 0 */
        eeprom_update_word(&ee_boot_count, warm_boot.cold);
        warm_boot.warm = 0;
        warm_boot.away = 0; /* RAM lost: a cold boot's own check decides (ctl_boot) */
        warm_boot.magic = WARM_MAGIC;
    } else {
        warm_boot.warm++;
    }
    warm_boot.check = warm_check();
    return (uint16_t)((warm_boot.cold << 8) | (warm_boot.warm & 0xFF));
}

/* the EEPROM safety record (firmware 1.5, spec 2.7): the RESET latch held across power cycles and the load ratchet
 * (spec 2.11); written only when the controller's copy changes: at a latch and at its clearing, never per press */
struct safety_rec_t {
    uint16_t magic;
    uint8_t reset_held;
    int16_t ratchet_g;
    uint16_t crc;
};
#define SAFETY_MAGIC 0x5346 /* "SF" */
static safety_rec_t EEMEM ee_safety;
static safety_rec_t safety_written; /* what the EEPROM holds now */

static void safety_load(void)
{
    eeprom_read_block(&safety_written, &ee_safety, sizeof(safety_written));
    if (safety_written.magic != SAFETY_MAGIC ||
        safety_written.crc != rigctl_crc16((const uint8_t *)&safety_written, sizeof(safety_written) - 2)) {
        safety_written.magic = SAFETY_MAGIC; /* none (erased, or a brown-out while writing it): nothing held */
        safety_written.reset_held = 0;
        safety_written.ratchet_g = 0;
        safety_written.crc = 0; /* never matches: the first change writes a whole record */
    }
}

static void safety_save(void)
{
    if (ctl.ee_reset_held == safety_written.reset_held && ctl.ee_ratchet_g == safety_written.ratchet_g &&
        safety_written.crc == rigctl_crc16((const uint8_t *)&safety_written, sizeof(safety_written) - 2))
        return;
    if (!safety_written.crc && !ctl.ee_reset_held && !ctl.ee_ratchet_g) return; /* none stored, none to store */
    safety_written.magic = SAFETY_MAGIC;
    safety_written.reset_held = ctl.ee_reset_held;
    safety_written.ratchet_g = ctl.ee_ratchet_g;
    safety_written.crc = rigctl_crc16((const uint8_t *)&safety_written, sizeof(safety_written) - 2);
    eeprom_update_block(&safety_written, &ee_safety, sizeof(safety_written));
}

/* returns 1 if a valid record was found; else scale and steps are 0 (the controller's defaults); *zero is the stored
 * tare zero (CALIB_NO_ZERO: none, an older record), *stiffness the contact's stored with it (0: none, an older record) */
static uint8_t calib_load(int32_t *scale, uint16_t *steps, int32_t *zero, uint16_t *stiffness)
{
    calib4_t c4;
    calib3_t c3;
    calib_t c;
    calib_v1_t v1;
    *zero = CALIB_NO_ZERO;
    *stiffness = 0;
    eeprom_read_block(&c4, &ee_calib4, sizeof(c4));
    if (c4.magic == CALIB4_MAGIC && c4.crc == rigctl_crc16((const uint8_t *)&c4, sizeof(c4) - 2) &&
        c4.loadcell_scale_x100 && c4.actuator_steps_per_mm) {
        *scale = c4.loadcell_scale_x100;
        *steps = c4.actuator_steps_per_mm;
        *zero = c4.zero_raw;
        *stiffness = c4.stiffness_g_mm;
        return 1;
    }
    eeprom_read_block(&c3, &ee_calib3, sizeof(c3));
    if (c3.magic == CALIB3_MAGIC && c3.crc == rigctl_crc16((const uint8_t *)&c3, sizeof(c3) - 2) &&
        c3.loadcell_scale_x100 && c3.actuator_steps_per_mm) {
        *scale = c3.loadcell_scale_x100;
        *steps = c3.actuator_steps_per_mm;
        *zero = c3.zero_raw;
        return 1;
    }
    eeprom_read_block(&c, &ee_calib2, sizeof(c));
    if (c.magic == CALIB_MAGIC && c.crc == rigctl_crc16((const uint8_t *)&c, sizeof(c) - 2) &&
        c.loadcell_scale_x100 && c.actuator_steps_per_mm) {
        *scale = c.loadcell_scale_x100;
        *steps = c.actuator_steps_per_mm;
        return 1;
    }
    eeprom_read_block(&v1, &ee_calib, sizeof(v1));
    if (v1.magic == CALIB_V1_MAGIC && v1.crc == rigctl_crc16((const uint8_t *)&v1, 6) && v1.loadcell_scale_x100 &&
        v1.actuator_steps_per_mm) {
        *scale = v1.loadcell_scale_x100;
        *steps = v1.actuator_steps_per_mm;
        return 1;
    }
    *scale = 0;
    *steps = 0;
    return 0;
}

/* the record with the tare in force (or the zero stored before, if no tare was taken since the reset) */
static void calib_save(void)
{
    calib4_t c;
    c.magic = CALIB4_MAGIC;
    c.loadcell_scale_x100 = ctl_scale_x100(&ctl);
    c.actuator_steps_per_mm = ctl.hreg[RIGCTL_HREG_ACTUATOR_STEPS_PER_MM];
    c.zero_raw = ctl.tared ? ctl.tare_offset : ctl.zero_valid ? ctl.zero_raw : CALIB_NO_ZERO;
    c.stiffness_g_mm = ctl.hreg[RIGCTL_HREG_CALIBRATION_STIFFNESS_G_PER_MM];
    c.crc = rigctl_crc16((const uint8_t *)&c, sizeof(c) - 2);
    eeprom_update_block(&c, &ee_calib4, sizeof(c));
    ctl.zero_raw = c.zero_raw;
    ctl.zero_valid = c.zero_raw != CALIB_NO_ZERO;
    ctl.calib_defaults = 0;
}

/* ---- HX711 ---- */
static int32_t hx711_read(void)
{
    uint32_t v = 0;
    for (uint8_t i = 0; i < 25; i++) {
        cli(); /* SCK high must stay short (< 60 us powers the HX711 down) */
        PIN_HX_SCK_PORT |= (1 << PIN_HX_SCK_BIT);
        _delay_us(1);
        uint8_t bit = (PIN_HX_DOUT_PIN >> PIN_HX_DOUT_BIT) & 1;
        PIN_HX_SCK_PORT &= (uint8_t)~(1 << PIN_HX_SCK_BIT);
        sei();
        if (i < 24) v = (v << 1) | bit;
        _delay_us(1);
    }
    if (v & 0x800000UL) v |= 0xFF000000UL; /* sign-extend 24 -> 32 bits */
    return (int32_t)v;
}

/* ---- applying the controller's outputs ---- */
/* A 16-bit step timer in CTC mode (Timer1 or Timer3). */
struct step_timer_regs {
    volatile uint16_t *ocr;
    volatile uint16_t *tcnt;
    volatile uint8_t *tccrb;
    volatile uint8_t *tifr;
    uint8_t wgm;  /* the CTC bit of TCCRnB */
    uint8_t ocf;  /* the compare flag bit of TIFRn */
};
static const step_timer_regs drum_timer = {&OCR1A, &TCNT1, &TCCR1B, &TIFR1, (1 << WGM12), (1 << OCF1A)};
static const step_timer_regs act_timer = {&OCR3A, &TCNT3, &TCCR3B, &TIFR3, (1 << WGM32), (1 << OCF3A)};

/* Retime a running (or stopped) step timer at once, so the rate follows the 1 kHz ramp instead of waiting out a
 * long period (at the start of a ramp the first period would be hundreds of ms). Call with interrupts off.
 * Same prescaler: the new period applies to the step in progress (if it has already run longer, the step comes on
 * the next timer tick). Other prescaler, or starting from rest: the period restarts now. Stopping is left to the
 * compare interrupt (cs = 0 in `next`), so a step in progress is finished. */
static void step_timer_retime(const step_timer_regs *r, volatile uint8_t *running_cs, const steptimer_t *t)
{
    if (!t->cs) return;
    if (*running_cs == t->cs) {
        uint16_t now = *r->tcnt;
        *r->ocr = t->ocr;
        if (now >= t->ocr) *r->tcnt = t->ocr ? (uint16_t)(t->ocr - 1) : 0;
    } else {
        *r->ocr = t->ocr;
        *r->tcnt = 0;
        *r->tifr = r->ocf;
        *r->tccrb = (uint8_t)(r->wgm | t->cs);
        *running_cs = t->cs;
    }
}

/* loop() applies both step rates every 1 kHz tick (and the actuator's at each HX711 reading), mostly unchanged: each
 * float computation is remembered with its input and redone only when that changes (the same result, without
 * ~1000-3000 cycles of soft-float a tick; a NaN key never matches, so the first call computes) */
static void drum_apply(float v_mm_s)
{
    static float memo_v = NAN;
    static steptimer_t memo_t;
    if (!(v_mm_s == memo_v)) {
        steprate_timer(steprate_hz_from_mm_s(v_mm_s, DRUM_DIAMETER_MM, DRUM_USTEPS_PER_REV), F_CPU, &memo_t);
        memo_v = v_mm_s;
    }
    steptimer_t t = memo_t;
    cli();
    if (motion_inhibit) t.cs = 0; /* e-stop: the timers stay stopped whatever loop() asks */
    drum_next.cs = t.cs;
    drum_next.ocr = t.ocr;
    if (t.cs && (t.cs != drum_running_cs || t.ocr != drum_running_ocr)) {
        step_timer_retime(&drum_timer, &drum_running_cs, &t);
        drum_running_ocr = t.ocr;
    }
    sei();
}

static float drum_actual_mm_s(void)
{
    steptimer_t t;
    cli();
    t.cs = drum_running_cs;
    t.ocr = drum_running_ocr;
    sei();
    static steptimer_t memo_t = {0xFF, 0}; /* no timer setting: the first call computes */
    static float memo_mm_s;
    if (t.cs != memo_t.cs || t.ocr != memo_t.ocr) {
        memo_mm_s = steprate_mm_s_from_hz(steprate_timer_hz(&t, F_CPU), DRUM_DIAMETER_MM, DRUM_USTEPS_PER_REV);
        memo_t = t;
    }
    return memo_mm_s;
}

/* The actuator's step generator follows the commanded velocity at once. A stop or a reversal (STOP, a fault, the host
 * watchdog: the back-off) drops the step counting down in the old direction: the timer stops now, DIR is set, and the
 * new direction's period starts from rest, so its first step comes one period (0.5 ms at the back-off speed) after
 * the command, never a step towards the sensor after it (issue 39: the old period, up to 4.2 s at the slowest rate,
 * used to run out first). The DIR set-up time before the next STEP edge (A4988: 200 ns) is a whole period. */
static void act_apply(float v_mm_s)
{
    steptimer_t t;
    uint8_t dir = v_mm_s > 0.0f;
    float f = (v_mm_s < 0 ? -v_mm_s : v_mm_s) * (float)ctl.hreg[RIGCTL_HREG_ACTUATOR_STEPS_PER_MM];
    static float memo_f = NAN; /* drum_apply: the step rate's timer setting remembered */
    static steptimer_t memo_t;
    if (!(f == memo_f)) {
        steprate_timer(f, F_CPU, &memo_t);
        memo_f = f;
    }
    t = memo_t;
    cli();
    if (motion_inhibit) t.cs = 0;
    act_next.cs = t.cs;
    act_next.ocr = t.ocr;
    act_next_dir = dir;
    if (act_running_cs && (!t.cs || dir != act_dir)) { /* stop or reversal: the pending step is dropped */
        TCCR3B = (1 << WGM32);
        TIFR3 = (1 << OCF3A);
        act_running_cs = 0;
    }
    if (t.cs && !act_running_cs) { /* from rest: set the direction before the first step */
        act_dir = dir;
        if (dir) PIN_ACT_DIR_PORT |= (1 << PIN_ACT_DIR_BIT);
        else PIN_ACT_DIR_PORT &= (uint8_t)~(1 << PIN_ACT_DIR_BIT);
    }
    if (t.cs) step_timer_retime(&act_timer, &act_running_cs, &t);
    sei();
}

static void modbus_poll(void)
{
    uint16_t n;
    if (!frame_ready) return;
    uint8_t r = mb_handle(&mb, rx_buf, rx_len, tx_buf, &n);
    if (r != MB_IGNORED) ctl_feed_watchdog(&ctl);
    cli();
    rx_len = 0;
    frame_ready = 0;
    sei();
    if (n) {
        while (UCSR0B & (1 << UDRIE0)) {
        }
        tx_len = n;
        tx_pos = 0;
        UCSR0B |= (1 << UDRIE0);
    }
}

static uint16_t reset_cause(void)
{
    uint16_t cause = mcusr_at_boot & (RIGCTL_RESET_POWER_ON | RIGCTL_RESET_EXTERNAL | RIGCTL_RESET_BROWN_OUT |
                                      RIGCTL_RESET_WATCHDOG);
    if (eeprom_read_byte(&ee_wdt_mark) == EE_WDT_MARK) { /* our watchdog interrupt ran just before this reset */
        cause |= RIGCTL_RESET_WATCHDOG;
        eeprom_write_byte(&ee_wdt_mark, 0xFF);
    }
    return cause;
}

void setup(void)
{
    int32_t scale, zero;
    uint16_t steps, stiffness;
    cli();
    uint8_t calib_ok = calib_load(&scale, &steps, &zero, &stiffness);
    ctl_init(&ctl, scale, steps);
    ctl.hreg[RIGCTL_HREG_CALIBRATION_STIFFNESS_G_PER_MM] = stiffness; /* spec 2.12 */
    ctl.calib_defaults = !calib_ok;
    ctl.zero_raw = zero;
    ctl.zero_valid = calib_ok && zero != CALIB_NO_ZERO;
    ctl.reset_cause = reset_cause();
    uint8_t warm = warm_record_valid(), was_away = warm && warm_boot.away;
    ctl.boot_count = boot_count();
    safety_load();
    ctl_boot(&ctl, warm, was_away, safety_written.reset_held, safety_written.ratchet_g);
    ctl_bind_modbus(&ctl, &mb);

    /* pins */
    PIN_DRUM_STEP_DDR |= (1 << PIN_DRUM_STEP_BIT) | (1 << PIN_DRUM_DIR_BIT);
    PIN_DRUM_STEP_PORT |= (1 << PIN_DRUM_DIR_BIT); /* the drum always turns forwards */
    PIN_ACT_STEP_DDR |= (1 << PIN_ACT_STEP_BIT);
    PIN_ACT_DIR_DDR |= (1 << PIN_ACT_DIR_BIT);
    PIN_HOME_PORT |= (1 << PIN_HOME_BIT); /* pull-up */
    PIN_HX_SCK_DDR |= (1 << PIN_HX_SCK_BIT);
    PIN_HX_DOUT_PORT |= (1 << PIN_HX_DOUT_BIT); /* pull-up: a broken DOUT wire reads "not ready" (LOADCELL_TIMEOUT) */
    PIN_INDEX_DDR |= (1 << PIN_INDEX_BIT);
    /* e-stop: pull-up, INT4 on any edge; an input already open at boot latches at once */
    PIN_ESTOP_PORT |= (1 << PIN_ESTOP_BIT);
    EICRB = (uint8_t)((EICRB & ~((1 << ISC41) | (1 << ISC40))) | (1 << ISC40));
    EIFR = (1 << INTF4);
    EIMSK |= (1 << INT4);
    _delay_us(10); /* the pull-up charges the input */
    estop_check_isr();

    /* UART0 500000 8N1: UBRR = F_CPU / (16 x baud) - 1 = 1, exact (115200 would be UBRR 16 with U2X: +2.1 %) */
    UCSR0A = 0;
    UBRR0 = MEGA_UBRR;
    UCSR0C = (1 << UCSZ01) | (1 << UCSZ00);
    UCSR0B = (1 << RXEN0) | (1 << TXEN0) | (1 << RXCIE0);
    /* Timer4: t3.5 = 1.75 ms = 437.5 ticks of 4 us */
    TCCR4A = 0;
    TCCR4B = (1 << WGM42);
    OCR4A = (uint16_t)(RIGCTL_MB_T35_US / 4);
    TIMSK4 = (1 << OCIE4A);
    /* Timer2: 1 kHz control tick */
    TCCR2A = (1 << WGM21);
    TCCR2B = (1 << CS22);
    OCR2A = 249;
    TIMSK2 = (1 << OCIE2A);
    /* Timer1, Timer3: step generators, stopped */
    TCCR1A = 0;
    TCCR1B = (1 << WGM12);
    TIMSK1 = (1 << OCIE1A);
    TCCR3A = 0;
    TCCR3B = (1 << WGM32);
    TIMSK3 = (1 << OCIE3A);
    index_sensor_setup();
    /* HX711 DOUT (PE5 = INT5) falling: wakes loop() from its idle sleep when a conversion is ready (the ISR does
     * nothing; loop() reads it, as before) */
    EICRB = (uint8_t)((EICRB & ~((1 << ISC51) | (1 << ISC50))) | (1 << ISC51));
    EIFR = (1 << INTF5);
    EIMSK |= (1 << INT5);
    set_sleep_mode(SLEEP_MODE_IDLE);
    /* AVR watchdog, 120 ms, interrupt then reset (WDIE + WDE); fed only at the top of loop() */
    wdt_enable(WDTO_120MS);
    WDTCSR |= (1 << WDIE);
    sei();
}

void loop(void)
{
    static uint32_t done_ms;
    static uint32_t index_on_ms;
    static uint8_t index_on;

    wdt_reset();
#ifdef RIGCTL_TEST_HOOKS
    if ((PIN_TEST_HANG_PIN >> PIN_TEST_HANG_BIT) & 1) { /* test image only: a hung loop() for the watchdog test */
        for (;;) {
        }
    }
#endif

    /* receiver status poll (see uno_taxel.cpp): lets simavr's UART model deliver host bytes */
    (void)UCSR0A;
    modbus_poll();

    uint32_t now;
    cli();
    now = tick_ms;
    sei();
    while (done_ms != now) {
        done_ms++;
        cli();
        ctl.act_pos_steps = act_steps;
        index_to_controller();
        uint8_t idx = index_pending;
        index_pending = 0;
        sei();
        if (idx) {
            index_on = 1;
            index_on_ms = done_ms;
        } else if (index_on && done_ms - index_on_ms >= RIGCTL_INDEX_PULSE_MS) {
            index_on = 0;
            PIN_INDEX_PORT &= (uint8_t)~(1 << PIN_INDEX_BIT);
        }
        ctl.home_switch = !((PIN_HOME_PIN >> PIN_HOME_BIT) & 1);
        ctl.estop_open = (PIN_ESTOP_PIN >> PIN_ESTOP_BIT) & 1;
        if (estop_latched && !(ctl.faults & RIGCTL_FAULT_ESTOP) && !ctl.estop_release) ctl_estop(&ctl);
        ctl.drum_actual_mm_s = drum_actual_mm_s();
        ctl_tick(&ctl, done_ms);
        warm_record_away(ctl.away);
        if (ctl.zero_position) {
            /* home found: the actuator stops at the switch at once (its step timer stopped with the zero, in one
             * critical section: a step left to the next compare interrupt, or one that came between the zero and
             * act_apply(0), would leave ACTUATOR_POSITION at -1 or -2 steps after HOME) */
            cli();
            act_next.cs = 0;
            TCCR3B = (1 << WGM32);
            TIFR3 = (1 << OCF3A);
            act_running_cs = 0;
            act_steps = 0;
            sei();
            ctl.zero_position = 0;
        }
        if (ctl.estop_release) { /* CLEAR_FAULT with the input closed again: motion allowed again */
            cli();
            estop_latched = 0;
            motion_inhibit = 0;
            sei();
            ctl.estop_release = 0;
        }
        drum_apply(ctl.drum_cmd_mm_s);
        act_apply(ctl.act_vel_mm_s);
        cli();
        /* a step generator finishing its last step keeps the drivers on until it stops (a step made with the
         * drivers off is lost, and the step count would no longer be the position) */
        if ((ctl.drivers_on || act_running_cs || drum_running_cs) && !motion_inhibit)
            PIN_EN_PORT &= (uint8_t)~(1 << PIN_EN_BIT);
        else PIN_EN_PORT |= (1 << PIN_EN_BIT);
        /* STATUS_FLAGS reports the EN line as read back on its pin, not the output latch (issue 75: a line shorted
         * active read "disabled" while the motor held full current); a nop before reading back a pin just written
         * (ATmega2560 datasheet 13.2.4, the input synchroniser) */
        __asm__ __volatile__("nop");
        ctl.drivers_on = !((PIN_EN_PIN >> PIN_EN_BIT) & 1);
        sei();
    }

    if (!((PIN_HX_DOUT_PIN >> PIN_HX_DOUT_BIT) & 1)) {
        ctl_hx711_ready(&ctl, micros());
        ctl_loadcell(&ctl, hx711_read());
        act_apply(ctl.act_vel_mm_s);
    }
    if (ctl.save_calibration) {
        calib_save();
        ctl.save_calibration = 0;
    }
    safety_save(); /* the safety record, when the controller's copy changed (a latch, its clearing) */

    /* nothing left to do until an interrupt: idle sleep (ATmega2560 datasheet 11.2: the CPU stops, the timers, the
     * UARTs and the external interrupts run on, and any enabled interrupt wakes it, 5 cycles later than an awake CPU
     * would take it, 7.8.1): the 1 kHz tick, a Modbus frame's end (Timer4), the HX711's DOUT (INT5), a step, a byte.
     * Checked with interrupts off and SLEEP right after SEI (the instruction after SEI runs before any interrupt), so
     * an interrupt that comes after the check wakes the CPU at once instead of being slept past. The watchdog is fed
     * at the top of every pass: at least once a tick. (Idle mode also starts a conversion of the ADC the Arduino core
     * enables, 11.2: this sketch reads no analog input and takes no ADC interrupt. The Uno, whose sampler does,
     * sleeps only with its ADC off, its stream stopped.) */
    cli();
    if (tick_ms == done_ms && !frame_ready && ((PIN_HX_DOUT_PIN >> PIN_HX_DOUT_BIT) & 1)) {
        sleep_enable();
        sei();
        sleep_cpu();
        sleep_disable();
    }
    sei();
}
