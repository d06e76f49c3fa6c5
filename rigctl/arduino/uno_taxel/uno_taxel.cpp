/*
 * uno_taxel.cpp - Arduino Uno (ATmega328P, 16 MHz) taxel streamer, docs/wire-protocol.md section 1.
 *
 * Timer1 (CTC, /8, OCR1A = 1999) interrupts at exactly 1 kHz. Each tick:
 *   - takes the previous tick's completed scan (or flags ADC_OVERRUN and repeats it if the scan is unfinished),
 *   - starts the next scan: 18 conversions walking the three 74HC4051 multiplexers (select lines D4-D6, outputs
 *     on A0-A2, taxel_frame.h has the order); each ADC-complete interrupt stores its result and selects the next
 *     input, whose conversion the Timer1 compare-B interrupt starts after a settling time (adc_select below),
 *   - when streaming, builds the frame (seq, flags, samples, CRC-16) into the free one of two frame buffers and
 *     queues it; the UART data-register-empty interrupt sends the bytes at 1,000,000 baud (U2X), so nothing
 *     ever busy-waits on the UART while sampling. A tick that finds both buffers taken drops its frame and
 *     sets TX_OVERRUN in the next one (the host sees the seq gap too).
 * Host commands (S, P, I) arrive through the UART receive interrupt and are handled in loop(); text replies are
 * sent only while the stream is stopped and the transmitter is idle. The Arduino core supplies main(), init()
 * and Timer0 (millis); HardwareSerial is not linked, the UART is driven here.
 */
#include <Arduino.h>
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/pgmspace.h>
#include <util/delay.h>

#include "../common/rigctl_wire.h"
#include "taxel_frame.h"
#include "uno_pins.h"

/* ---- sampler state (ADC ISR + tick ISR) ---- */
static volatile uint16_t adc_bank[2][RIGCTL_N_TAXELS]; /* scan in progress writes one bank, frames read the other */
static volatile uint8_t adc_write_bank;                 /* bank the running scan writes */
static volatile uint8_t adc_ready_bank = 1;            /* bank of the last completed scan */
static volatile uint8_t adc_k;                          /* next conversion of the scan, 0..18 */
static volatile uint8_t adc_in, adc_sel; /* its analog input and select value: TAXEL_SCAN_ADC/SEL(adc_k), counted
                                          * (a division by 3 costs ~80 cycles per conversion on the AVR) */
static volatile uint8_t adc_busy;                       /* a scan is running */

/* ---- stream state ----
 * The UDRE interrupt sends tx_left bytes from tx_ptr, then the queued frame buffer, if any. Frames use the two
 * buffers of tx_buf; a text reply (stream stopped) is sent the same way from flash-free RAM. */
static uint8_t tx_buf[2][RIGCTL_FRAME_SIZE];
static const uint8_t *volatile tx_ptr;
static volatile uint8_t tx_left;
static volatile int8_t tx_active = -1; /* frame buffer being sent, -1 = none */
static volatile int8_t tx_queued = -1; /* frame buffer waiting for the transmitter, -1 = none */
static volatile uint8_t tx_busy;       /* the transmitter has bytes to send */
static volatile uint8_t streaming;
static volatile uint8_t start_pending;  /* next frame is the first after START */
static volatile uint8_t tx_overrun_pending;
static volatile uint8_t sync_latched;
static volatile uint16_t seq;

/* ---- command receive ring ---- */
static volatile uint8_t rx_ring[16];
static volatile uint8_t rx_head, rx_tail;

/* Input selection and conversion start are separate: after the select lines and ADMUX change, the multiplexer's
 * common node (~25 pF) and the ADC's sample-and-hold capacitor (14 pF) charge through the taxel's own source
 * impedance (tau = 47 kOhm x 39 pF = 1.8 us without an anti-alias capacitor), so a conversion started at once samples
 * (1.5 ADC clocks = 3 us later) ~20 % of the previous input (docs/firmware.md, "Multiplexer settling"). Each
 * conversion therefore starts UNO_SETTLE_COUNTS of Timer1 (14 us) after its input was selected, from the Timer1
 * compare-B interrupt; the first input of the next scan is selected when a scan ends, and settles until the tick.
 * With the anti-alias capacitor C_aa at each input (15 nF), the node's and the sample-and-hold's charge is shared
 * with C_aa at once and recovers only through the source impedance (0.7 ms): whatever voltage they bring from the
 * previous input stays in C_aa (3 LSB of a full-scale neighbour at 47 kOhm). So before each new input they are
 * discharged to 0 V: ADMUX to the GND channel (the sample-and-hold), and, when the select lines change, the select
 * lines to Y7, tied to GND (the nodes): the charge they then take from C_aa depends on that taxel's own voltage only
 * (a gain error of 0.34 % at 47 kOhm, docs/firmware.md), not on its neighbour's. */
static inline void adc_discharge(uint8_t select_changes)
{
    if (select_changes) UNO_SEL_PORT = (uint8_t)(UNO_SEL_PORT | UNO_SEL_MASK); /* Y7: GND */
    ADMUX = (uint8_t)((1 << REFS0) | UNO_ADMUX_GND);
}

static inline void adc_select(uint8_t adc, uint8_t sel)
{
    if (adc == 0) {
        UNO_SEL_PORT = (uint8_t)((UNO_SEL_PORT & ~UNO_SEL_MASK) | (sel << UNO_SEL_SHIFT));
    }
    ADMUX = (uint8_t)((1 << REFS0) | adc);
}

static inline void adc_convert(void)
{
    ADCSRA = (uint8_t)((1 << ADEN) | (1 << ADSC) | (1 << ADIE) | UNO_ADC_PRESCALER_BITS);
}

/* start the selected conversion UNO_SETTLE_COUNTS from now (Timer1 compare B, modulo the tick) */
static inline void adc_convert_after_settling(void)
{
    uint16_t at = (uint16_t)(TCNT1 + UNO_SETTLE_COUNTS);
    if (at > UNO_TICK_TOP) at = (uint16_t)(at - (UNO_TICK_TOP + 1));
    OCR1B = at;
    TIFR1 = (1 << OCF1B);
    TIMSK1 |= (1 << OCIE1B);
}

ISR(ADC_vect)
{
    UNO_PROBE_PORT |= (1 << UNO_PROBE_SAMPLER);
    uint8_t k = adc_k;
    uint8_t in = adc_in, sel = adc_sel;
    uint16_t result = ADC; /* ADCL then ADCH: latched, so the input can change now */
    uint8_t next_k = (uint8_t)(k + 1), next_in = (uint8_t)(in + 1), next_sel = sel;
    if (next_in == TAXEL_N_MUX) {
        next_in = 0;
        next_sel++;
    }
    /* discharge the sample-and-hold (and the nodes, if the select lines change) while the result is stored (>= 1 us:
     * R_ADC x 14 pF <= 1.4 us, ATmega328P datasheet "Analog Input Circuitry"), then the next input: its settling
     * time starts there, the rest of the bookkeeping runs inside it */
    adc_discharge(next_in == 0);
    uint8_t w = adc_write_bank;
    adc_bank[w][in * TAXEL_PER_MUX + sel] = result; /* TAXEL_SCAN_TAXEL(k) */
    _delay_us(1);
    if (next_k < RIGCTL_N_TAXELS) {
        adc_select(next_in, next_sel);
        adc_convert_after_settling();
    } else {
        adc_select(0, 0); /* the next scan's first input settles until the tick */
    }
    if (next_k < RIGCTL_N_TAXELS) {
        adc_k = next_k;
        adc_in = next_in;
        adc_sel = next_sel;
    } else {
        adc_ready_bank = w;
        adc_write_bank = (uint8_t)(w ^ 1);
        adc_busy = 0;
        adc_in = adc_sel = 0;
    }
    UNO_PROBE_PORT &= (uint8_t)~(1 << UNO_PROBE_SAMPLER);
}

ISR(TIMER1_COMPB_vect)
{
    UNO_PROBE_PORT |= (1 << UNO_PROBE_SAMPLER);
    TIMSK1 &= (uint8_t)~(1 << OCIE1B);
    adc_convert();
    UNO_PROBE_PORT &= (uint8_t)~(1 << UNO_PROBE_SAMPLER);
}

ISR(INT0_vect)
{
    sync_latched = 1;
}

ISR(TIMER1_COMPA_vect)
{
    UNO_PROBE_PORT |= (1 << UNO_PROBE_SAMPLER);
    uint8_t flags = 0;
    if (adc_busy) {
        flags |= RIGCTL_FLAG_ADC_OVERRUN; /* the running scan keeps going; this frame repeats the last one */
    } else {
        adc_busy = 1;
        adc_k = 0;
        adc_convert(); /* input 0 was selected when the last scan ended */
    }
    if (streaming) {
        if (sync_latched) {
            sync_latched = 0;
            flags |= RIGCTL_FLAG_SYNC_IN;
        }
        if (start_pending) {
            start_pending = 0;
            flags |= RIGCTL_FLAG_STREAMING_START;
        }
        if (tx_queued >= 0) {
            tx_overrun_pending = 1; /* both buffers taken: drop this frame */
        } else {
            if (tx_overrun_pending) {
                tx_overrun_pending = 0;
                flags |= RIGCTL_FLAG_TX_OVERRUN;
            }
            int8_t b = (tx_active == 0) ? 1 : 0;
            taxel_frame_build(tx_buf[b], seq, flags, (const uint16_t *)adc_bank[adc_ready_bank]);
            if (!tx_busy) {
                tx_active = b;
                tx_ptr = tx_buf[b];
                tx_left = RIGCTL_FRAME_SIZE;
                tx_busy = 1;
                UCSR0B |= (1 << UDRIE0);
            } else {
                tx_queued = b;
            }
        }
        seq++;
    }
    UNO_PROBE_PORT &= (uint8_t)~(1 << UNO_PROBE_SAMPLER);
}

ISR(USART_UDRE_vect)
{
    UNO_PROBE_PORT |= (1 << UNO_PROBE_TX);
    UDR0 = *tx_ptr++;
    if (--tx_left == 0) {
        if (tx_queued >= 0) {
            tx_active = tx_queued;
            tx_queued = -1;
            tx_ptr = tx_buf[tx_active];
            tx_left = RIGCTL_FRAME_SIZE;
        } else {
            tx_active = -1;
            tx_busy = 0;
            UCSR0B &= (uint8_t)~(1 << UDRIE0);
        }
    }
    UNO_PROBE_PORT &= (uint8_t)~(1 << UNO_PROBE_TX);
}

ISR(USART_RX_vect)
{
    uint8_t status = UCSR0A; /* read before UDR0: frame error / data overrun of this byte */
    uint8_t c = UDR0;
    if (status & ((1 << FE0) | (1 << DOR0))) return;
    uint8_t next = (uint8_t)((rx_head + 1) & 15);
    if (next != rx_tail) {
        rx_ring[rx_head] = c;
        rx_head = next;
    }
}

static uint8_t text_buf[96];

/* build=<the sources' digest> (docs/wire-protocol.md 1.4): given by the build (make BUILD_ID=..., as rigctl's firmware
 * builds do), so that the host can tell a board flashed from other sources with the same version */
#ifdef RIGCTL_BUILD_ID
#define RIGCTL_BUILD_FIELD " build=" RIGCTL_BUILD_ID
#else
#define RIGCTL_BUILD_FIELD ""
#endif
static const char banner_P[] PROGMEM = RIGCTL_UNO_BANNER RIGCTL_BUILD_FIELD;
static const char identity_P[] PROGMEM = RIGCTL_UNO_IDENTITY RIGCTL_BUILD_FIELD;

/* send a text line (in flash) through the transmit interrupt (the stream must be stopped); returns when it is out */
static void send_line_P(const char *s)
{
    uint8_t n = 0;
    char c;
    while ((c = (char)pgm_read_byte(s++)) != 0 && n < sizeof(text_buf) - 1) text_buf[n++] = (uint8_t)c;
    text_buf[n++] = '\n';
    while (tx_busy) {
    }
    cli();
    tx_active = -1;
    tx_ptr = text_buf;
    tx_left = n;
    tx_busy = 1;
    UCSR0B |= (1 << UDRIE0);
    sei();
    while (tx_busy) {
    }
}

static void stop_and_drain(void)
{
    streaming = 0;
    while (tx_busy) {
    }
}

void setup(void)
{
    cli();
    /* UART0: 1,000,000 baud 8N1 with U2X (16 MHz / (8 * (1 + 1))), receive interrupt on */
    UCSR0A = (1 << U2X0);
    UBRR0 = 1;
    UCSR0C = (1 << UCSZ01) | (1 << UCSZ00);
    UCSR0B = (1 << RXEN0) | (1 << TXEN0) | (1 << RXCIE0);
    /* mux select lines and timing probes as outputs */
    UNO_SEL_DDR |= UNO_SEL_MASK;
    UNO_PROBE_DDR |= (1 << UNO_PROBE_SAMPLER) | (1 << UNO_PROBE_TX);
    /* analog inputs A0-A2: digital input buffers off */
    DIDR0 = (1 << ADC0D) | (1 << ADC1D) | (1 << ADC2D);
    ADCSRA = (uint8_t)((1 << ADEN) | UNO_ADC_PRESCALER_BITS);
    adc_select(0, 0);
    /* sync-in D2 (INT0): input, rising edge */
    DDRD &= (uint8_t)~(1 << PD2);
    EICRA = (1 << ISC01) | (1 << ISC00);
    EIFR = (1 << INTF0);
    EIMSK = (1 << INT0);
    /* Timer1: CTC on OCR1A, clk/8 -> 2 MHz (0.5 us per count), OCR1A = 1999 -> exactly 1000 Hz; compare B times
     * each conversion's settling */
    TCCR1A = 0;
    TCCR1B = (1 << WGM12) | (1 << CS11);
    TCNT1 = 0;
    OCR1A = UNO_TICK_TOP;
    TIFR1 = (1 << OCF1A);
    TIMSK1 = (1 << OCIE1A);
    sei();
    send_line_P(banner_P);
}

void loop(void)
{
    /* receiver status poll: besides the RX interrupt, this read is what tells simavr's UART model (and its pty
     * bridge) that the receiver has room, so host bytes flow in */
    (void)UCSR0A;
    while (rx_tail != rx_head) {
        uint8_t c = rx_ring[rx_tail];
        rx_tail = (uint8_t)((rx_tail + 1) & 15);
        if (c == RIGCTL_UNO_CMD_START) {
            cli();
            seq = 0;
            sync_latched = 0;
            tx_overrun_pending = 0;
            start_pending = 1;
            streaming = 1;
            sei();
        } else if (c == RIGCTL_UNO_CMD_STOP) {
            streaming = 0;
        } else if (c == RIGCTL_UNO_CMD_IDENTIFY) {
            stop_and_drain();
            send_line_P(identity_P);
        }
    }
}
