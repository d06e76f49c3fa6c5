/*
 * uno_taxel.cpp - Arduino Uno (ATmega328P, 16 MHz) taxel streamer, docs/wire-protocol.md section 1.
 *
 * Timer1 (CTC, /8, OCR1A = 1999) interrupts at exactly 1 kHz. Each tick while streaming:
 *   - takes the previous tick's completed scan (or flags ADC_OVERRUN and repeats it if the scan is unfinished),
 *   - starts the next scan: 18 conversions walking the three 74HC4051 multiplexers (select lines D4-D6, outputs
 *     on A0-A2, taxel_frame.h has the order); each ADC-complete interrupt stores its result and selects the next
 *     input, whose conversion the Timer1 compare-B interrupt starts after a settling time (adc_select below),
 *   - when streaming, builds the frame (seq, flags, samples, CRC-16) into the free one of two frame buffers and
 *     queues it; the UART data-register-empty interrupt sends the bytes at 1,000,000 baud (U2X), so nothing
 *     ever busy-waits on the UART while sampling. A tick that finds both buffers taken drops its frame and
 *     sets TX_OVERRUN in the next one (the host sees the seq gap too).
 * While the stream is stopped nothing reads a scan: the tick starts none and switches the ADC off once the last one is
 * over, and loop() sleeps (idle mode) between interrupts; START switches the ADC on again at the next tick, whose
 * scan the first frame carries one tick later (adc_primed). Host commands (S, P, I) arrive through the UART receive
 * interrupt and are handled in loop(); text replies are sent only while the stream is stopped and the transmitter is
 * idle. The Arduino core supplies main(), init() and Timer0 (millis); HardwareSerial is not linked, the UART is
 * driven here.
 *
 * Built with -DUNO_SA_ENCODER (the uno_encoder image, docs/firmware.md "The encoder in the Uno image"), the sketch
 * also runs the SA encoder (common/sa_encoder.c, integer kernel) on the 9 top-layer taxels of every sample while
 * encoding (E): the tick queues them (ENC_QUEUE deep) instead of building a taxel frame, loop() encodes them and
 * sends a spike frame every 10 samples, scales each 100 ms window when the host sends its speed (V), and sends the
 * window counts at the end of a scan (F) (docs/wire-protocol.md 1.5). S still streams taxel frames as above.
 */
#include <Arduino.h>
#include <avr/interrupt.h>
#include <avr/io.h>
#include <avr/pgmspace.h>
#include <avr/sleep.h>
#include <util/delay.h>

#include "../common/crc16.h"
#include "../common/rigctl_wire.h"
#include "taxel_frame.h"
#include "uno_pins.h"
#ifdef UNO_SA_ENCODER
#include "../common/sa_encoder.h"
#include "../common/sa_ring.h"
#endif

/* ---- sampler state (ADC ISR + tick ISR) ---- */
static volatile uint16_t adc_bank[2][RIGCTL_N_TAXELS]; /* scan in progress writes one bank, frames read the other */
static volatile uint8_t adc_write_bank;                 /* bank the running scan writes */
static volatile uint8_t adc_ready_bank = 1;            /* bank of the last completed scan */
static volatile uint8_t adc_k;                          /* next conversion of the scan, 0..18 */
static volatile uint8_t adc_in, adc_sel; /* its analog input and select value: TAXEL_SCAN_ADC/SEL(adc_k), counted
                                          * (a division by 3 costs ~80 cycles per conversion on the AVR) */
static volatile uint8_t adc_busy;                       /* a scan is running */
static volatile uint8_t adc_primed; /* a scan has completed since the ADC was switched on: adc_ready_bank holds one */

/* ---- stream state ----
 * The UDRE interrupt sends tx_left bytes from tx_ptr, then the next block of its queue (TX_QUEUE deep), if any.
 * Each block belongs to a buffer (an owner bit): the bit is set in tx_owned while the block waits or is sent, so a
 * buffer is rewritten only when its bit is clear. Frames use the two buffers of tx_buf; a text reply (stream
 * stopped) is sent the same way from RAM. */
#define TX_QUEUE 8 /* a power of 2 */
#define TX_RAW0 0x01
#define TX_RAW1 0x02
#define TX_TEXT 0x04
#define TX_SPIKE0 0x08
#define TX_SPIKE1 0x10
#define TX_COUNTS 0x20
#ifdef UNO_SA_ENCODER
/* the taxel frames' buffers and the text reply's are idle while the encoder is armed or encodes (ARM waits for the
 * transmitter; START and IDENTIFY end the encoder's scan first): the sample ring lives in their place (its 384 bytes
 * would not fit beside them: docs/firmware.md, "The encoder in the Uno image") */
static union {
    struct {
        uint8_t frames[2][RIGCTL_FRAME_SIZE];
        uint8_t text[96];
    } stream;
    uint8_t ring[SA_RING_SAMPLES][SA_RING_BYTES];
} shared_buf;
#define tx_buf (shared_buf.stream.frames)
#define text_buf (shared_buf.stream.text)
#else
static uint8_t tx_buf[2][RIGCTL_FRAME_SIZE];
static uint8_t text_buf[96];
#endif
static const uint8_t *volatile tx_ptr;
static volatile uint16_t tx_left;
static volatile uint8_t tx_owner;      /* owner bit of the block being sent */
static volatile uint8_t tx_owned;      /* owner bits of the blocks queued or being sent */
static const uint8_t *tx_q_ptr[TX_QUEUE];
static uint16_t tx_q_len[TX_QUEUE];
static uint8_t tx_q_owner[TX_QUEUE];
static volatile uint8_t tx_q_head, tx_q_tail;
static volatile uint8_t tx_busy;       /* the transmitter has bytes to send */
static volatile uint8_t streaming;
static volatile uint8_t start_pending;  /* next frame is the first after START */
static volatile uint8_t tx_overrun_pending;
static volatile uint8_t sync_latched;
static volatile uint16_t seq;

/* ---- command receive ring ----
 * The RX interrupt drops a byte that finds the ring full. The streamer's loop() takes its one-byte commands at once.
 * The encoder's loop() is away from the ring for up to ~1.7 ms (a sample whose step holds a window: ~15,000 cycles,
 * ~26,700 with the interrupts), while the host's bytes keep coming at the line rate (~100 a ms): a 64-byte ring, read
 * after the whole sample queue, lost the tail of a host's burst of SPEEDs (a host catching up after a stall) and the
 * STOP after it (or the parser, which counts payload bytes, took the STOP as one), and the stream never stopped. The
 * encoder's ring holds 255 bytes, 1.5 times what that stretch lets in, and its loop() reads it between every two
 * samples it encodes (docs/wire-protocol.md 1.5: what a host may send). */
#ifdef UNO_SA_ENCODER
static volatile uint8_t rx_ring[256]; /* indices wrap as uint8_t */
#define RX_MASK 255
#else
static volatile uint8_t rx_ring[64];
#define RX_MASK 63
#endif
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

/* queue a block for the transmitter (interrupts off: from an interrupt, or inside cli/sei) */
static void tx_push_locked(const uint8_t *p, uint16_t n, uint8_t owner)
{
    tx_owned |= owner;
    if (!tx_busy) {
        tx_ptr = p;
        tx_left = n;
        tx_owner = owner;
        tx_busy = 1;
        UCSR0B |= (1 << UDRIE0);
    } else {
        uint8_t t = tx_q_tail;
        tx_q_ptr[t] = p;
        tx_q_len[t] = n;
        tx_q_owner[t] = owner;
        tx_q_tail = (uint8_t)((t + 1) & (TX_QUEUE - 1));
    }
}

#ifdef UNO_SA_ENCODER
/* ---- encoder state: the tick puts the top layer's samples into the ring (common/sa_ring.c), loop() encodes them
 * from the sample ENCODE names ---- */
static sa_ring_t ring;
static volatile uint8_t encoding;       /* the stream feeds the ring (ARM, then ENCODE) */
static volatile uint8_t enc_tick_flags; /* spike frame flags the tick latched (DROPPED, SYNC_IN) */
static volatile uint8_t enc_first;      /* the next sample is sample 0 of the ring (ARM's): the marker pin goes high */

/* the tick's part: the completed scan's taxels 0-8 into the ring (the sample a taxel frame of this tick would
 * carry); the marker pin (D11) is high from the tick that takes ARM's first sample to the next tick */
static inline void enc_enqueue(const uint16_t *scan, uint8_t frame_flags)
{
    if (enc_first) {
        enc_first = 0;
        UNO_PROBE_PORT |= (1 << UNO_PROBE_MARK);
    } else {
        UNO_PROBE_PORT &= (uint8_t)~(1 << UNO_PROBE_MARK);
    }
    if (frame_flags & RIGCTL_FLAG_SYNC_IN) enc_tick_flags |= RIGCTL_SPIKE_FLAG_SYNC_IN;
    if (!sa_ring_push(&ring, scan)) enc_tick_flags |= RIGCTL_SPIKE_FLAG_DROPPED;
}
#endif

/* the sampler's probe inside an interrupt that may have interrupted the tick's frame building (probe already high) */
#define SAMPLER_PROBE_ENTER() uint8_t probe_was = UNO_PROBE_PORT & (1 << UNO_PROBE_SAMPLER); \
    UNO_PROBE_PORT |= (1 << UNO_PROBE_SAMPLER)
#define SAMPLER_PROBE_LEAVE() if (!probe_was) UNO_PROBE_PORT &= (uint8_t)~(1 << UNO_PROBE_SAMPLER)

ISR(ADC_vect)
{
    SAMPLER_PROBE_ENTER();
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
        adc_primed = 1;
        adc_in = adc_sel = 0;
    }
    SAMPLER_PROBE_LEAVE();
}

/* Timer1 compare B: start the selected conversion (adc_convert) and disable itself (TIMSK1 back to the tick's
 * OCIE1A alone). Naked: two constant stores through one register, SREG untouched, so it costs ~20 cycles with its
 * entry and exit instead of the ~90 of a compiled one (18 a tick); no probe (the harness counts its cycles with the
 * interrupts-off time) */
ISR(TIMER1_COMPB_vect, ISR_NAKED)
{
    __asm__ __volatile__("push r24"        "\n\t"
                         "ldi r24, %[start]" "\n\t"
                         "sts %[adcsra], r24" "\n\t"
                         "ldi r24, %[tick]" "\n\t"
                         "sts %[timsk1], r24" "\n\t"
                         "pop r24"          "\n\t"
                         "reti"
                         :
                         : [start] "n"((uint8_t)((1 << ADEN) | (1 << ADSC) | (1 << ADIE) | UNO_ADC_PRESCALER_BITS)),
                           [adcsra] "n"(_SFR_MEM_ADDR(ADCSRA)), [tick] "n"((uint8_t)(1 << OCIE1A)),
                           [timsk1] "n"(_SFR_MEM_ADDR(TIMSK1)));
}

ISR(INT0_vect)
{
    sync_latched = 1;
}

ISR(TIMER1_COMPA_vect)
{
    UNO_PROBE_PORT |= (1 << UNO_PROBE_SAMPLER);
    uint8_t flags = 0;
    if (!streaming) {
        /* stopped: no frame and no sample to queue, so no scan. Once the last one is over the ADC goes off (ADEN
         * 0, ADIE 0): loop() then sleeps, and idle mode starts a conversion of an enabled ADC (ATmega328P datasheet,
         * "Idle Mode"), which would come between the timed ones. ADMUX and the select lines keep input 0 */
        if (!adc_busy) {
            ADCSRA = UNO_ADC_PRESCALER_BITS;
            adc_primed = 0;
        }
        UNO_PROBE_PORT &= (uint8_t)~(1 << UNO_PROBE_SAMPLER);
        return;
    }
    if (adc_busy) {
        flags |= RIGCTL_FLAG_ADC_OVERRUN; /* the running scan keeps going; this frame repeats the last one */
    } else {
        adc_busy = 1;
        adc_k = 0;
        adc_convert(); /* input 0 was selected when the last scan ended; switches the ADC on if it was off (its
                        * first conversion then takes 25 ADC clocks instead of 13: the scan ~24 us longer) */
    }
    if (!adc_primed) {
        /* the first scan since the ADC went on is running: the first frame (seq 0, STREAMING_START) carries it at
         * the next tick */
        UNO_PROBE_PORT &= (uint8_t)~(1 << UNO_PROBE_SAMPLER);
        return;
    }
    if (sync_latched) {
        sync_latched = 0;
        flags |= RIGCTL_FLAG_SYNC_IN;
    }
    if (start_pending) {
        start_pending = 0;
        flags |= RIGCTL_FLAG_STREAMING_START;
    }
    uint16_t s = seq++;
    const uint16_t *ready = (const uint16_t *)adc_bank[adc_ready_bank]; /* the running scan writes the other */
#ifdef UNO_SA_ENCODER
    if (encoding) { /* the encoder's sample instead of a taxel frame: loop() sends spike frames */
        enc_enqueue(ready, flags);
        UNO_PROBE_PORT &= (uint8_t)~(1 << UNO_PROBE_SAMPLER);
        return;
    }
#endif
    uint8_t owned = tx_owned; /* the transmitter only frees buffers: a free one stays free */
    /* the frame is built with interrupts enabled, so that the scan's ADC and compare-B interrupts run on time
     * (the first conversion ends 26 us after the tick, the frame and its CRC take ~75 us); the tick cannot
     * come again before it is done (a ms) */
    sei();
    if ((owned & (TX_RAW0 | TX_RAW1)) == (TX_RAW0 | TX_RAW1)) {
        tx_overrun_pending = 1; /* both buffers taken: drop this frame */
    } else {
        if (tx_overrun_pending) {
            tx_overrun_pending = 0;
            flags |= RIGCTL_FLAG_TX_OVERRUN;
        }
        uint8_t b = (owned & TX_RAW0) ? 1 : 0;
        taxel_frame_build(tx_buf[b], s, flags, ready);
        cli();
        tx_push_locked(tx_buf[b], RIGCTL_FRAME_SIZE, b ? TX_RAW1 : TX_RAW0);
        sei();
    }
    cli();
    UNO_PROBE_PORT &= (uint8_t)~(1 << UNO_PROBE_SAMPLER);
}

ISR(USART_UDRE_vect)
{
    UNO_PROBE_PORT |= (1 << UNO_PROBE_TX);
    UDR0 = *tx_ptr++;
    if (--tx_left == 0) {
        tx_owned &= (uint8_t)~tx_owner;
        uint8_t h = tx_q_head;
        if (h != tx_q_tail) {
            tx_ptr = tx_q_ptr[h];
            tx_left = tx_q_len[h];
            tx_owner = tx_q_owner[h];
            tx_q_head = (uint8_t)((h + 1) & (TX_QUEUE - 1));
        } else {
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
    uint8_t next = (uint8_t)((rx_head + 1) & RX_MASK);
    if (next != rx_tail) {
        rx_ring[rx_head] = c;
        rx_head = next;
    }
}

/* build=<the sources' digest> (docs/wire-protocol.md 1.4): given by the build (make BUILD_ID=..., as rigctl's firmware
 * builds do), so that the host can tell a board flashed from other sources with the same version */
#ifdef RIGCTL_BUILD_ID
#define RIGCTL_BUILD_FIELD " build=" RIGCTL_BUILD_ID
#else
#define RIGCTL_BUILD_FIELD ""
#endif
#ifdef UNO_SA_ENCODER
#define UNO_ENC_FIELD RIGCTL_UNO_ENC_FIELD
#else
#define UNO_ENC_FIELD ""
#endif
static const char banner_P[] PROGMEM = RIGCTL_UNO_BANNER UNO_ENC_FIELD RIGCTL_BUILD_FIELD;
static const char identity_P[] PROGMEM = RIGCTL_UNO_IDENTITY UNO_ENC_FIELD RIGCTL_BUILD_FIELD;

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
    tx_push_locked(text_buf, n, TX_TEXT);
    sei();
    while (tx_busy) {
    }
}

#ifdef UNO_SA_ENCODER
/* the encoder's scan ends without its counts (START, IDENTIFY): the ring's storage goes back to the frames */
static void enc_release(void)
{
    cli();
    encoding = 0;
    ring.encoding = 0;
    ring.tail = ring.head;
    sei();
}
#endif

static void stop_and_drain(void)
{
    streaming = 0;
#ifdef UNO_SA_ENCODER
    enc_release();
#endif
    while (tx_busy) {
    }
}

static void stream_start(uint8_t encode)
{
#ifdef UNO_SA_ENCODER
    if (!encode) enc_release();
#endif
    cli();
    seq = 0;
    sync_latched = 0;
    tx_overrun_pending = 0;
    start_pending = 1;
#ifdef UNO_SA_ENCODER
    encoding = encode;
#else
    (void)encode;
#endif
    streaming = 1;
    sei();
}

#ifdef UNO_SA_ENCODER
/* ---- the encoder's side of loop() (docs/wire-protocol.md 1.5) ---- */
static sa_encoder_t enc;
static uint16_t cal_min[RIGCTL_ENC_N_TAXELS], cal_max[RIGCTL_ENC_N_TAXELS], cal_k = 100; /* CALIBRATE */
static uint8_t spike_buf[2][RIGCTL_SPIKE_FRAME_SIZE];
static uint16_t spike_masks[RIGCTL_SPIKE_MASKS];
static uint8_t spike_n, spike_flags, spike_b;
static uint16_t spike_seq, enc_seq;  /* seq of the spike frame's first sample, of the next sample (since ARM) */
static uint8_t counts_head[RIGCTL_COUNTS_COUNTS_OFFSET], counts_crc[2];

#define ENC_PROBE_ON() (UNO_PROBE_PORT |= (1 << UNO_PROBE_ENCODER))
#define ENC_PROBE_OFF() (UNO_PROBE_PORT &= (uint8_t)~(1 << UNO_PROBE_ENCODER))

/* send the spike frame being filled (its n samples), into the other buffer next */
static void spike_flush(void)
{
    if (spike_n == 0) return;
    uint8_t owner = spike_b ? TX_SPIKE1 : TX_SPIKE0;
    while (tx_owned & owner) { /* sent 10 ms ago: free long since, but never overwrite one in flight */
    }
    cli();
    uint8_t flags = (uint8_t)(spike_flags | enc_tick_flags);
    enc_tick_flags = 0;
    sei();
    spike_frame_build(spike_buf[spike_b], spike_seq, spike_n, flags, spike_masks);
    cli();
    tx_push_locked(spike_buf[spike_b], RIGCTL_SPIKE_FRAME_SIZE, owner);
    sei();
    spike_b ^= 1;
    spike_n = 0;
    spike_flags = 0;
}

/* encode the oldest queued sample, if any (the probe pin is high while loop() encodes); returns 1 if there was one.
 * One at a time: loop() reads the host's bytes between samples (a queue drained in one go kept them waiting for
 * several samples, more than the receive ring holds at the line rate) */
static uint8_t enc_poll(void)
{
    uint16_t x[RIGCTL_ENC_N_TAXELS];
    if (ring.encoding && sa_ring_pop(&ring, x)) {
        ENC_PROBE_ON();
        uint32_t held = enc.held_windows;
        uint16_t mask = sa_step(&enc, x);
        if (enc.held_windows != held) spike_flags |= RIGCTL_SPIKE_FLAG_HELD;
        if (spike_n == 0) spike_seq = enc_seq;
        spike_masks[spike_n++] = mask;
        enc_seq++;
        if (spike_n == RIGCTL_SPIKE_MASKS) spike_flush();
        ENC_PROBE_OFF();
        return 1;
    }
    return 0;
}

/* ARM: a new scan's samples into the ring (sample 0 the first after ARM), nothing encoded or sent yet */
static void enc_arm(void)
{
    cli();
    streaming = 0;
    encoding = 0;
    ring.encoding = 0;
    sei();
    while (tx_busy) { /* the last scan's counts (sent from the encoder's state), a taxel frame or a text reply in
                       * the storage the ring takes over */
    }
    enc_tick_flags = 0;
    enc_first = 1;
    spike_n = 0;
    spike_flags = 0;
    sa_ring_arm(&ring, shared_buf.ring);
    stream_start(1);
}

/* ENCODE from sample `from` (since ARM; ARM first if the board is not armed): the encoder at rest (calibration of
 * the last CALIBRATE), the ring from that sample (sa_ring_begin: the oldest it holds if `from` is older), spike frames
 * numbered from ARM */
static void enc_begin(uint16_t from)
{
    if (!encoding) enc_arm();
    sa_init(&enc, cal_min, cal_max, cal_k);
    spike_n = 0;
    spike_flags = 0;
    cli();
    enc_seq = sa_ring_begin(&ring, from);
    sei();
}

/* FINISH: stop the stream, encode what is queued, scale the last windows, send the counts frame */
static void enc_finish(uint16_t speed_cmm_s)
{
    cli();
    streaming = 0;
    encoding = 0;
    sei();
    while (enc_poll()) {
    }
    spike_flush();
    ENC_PROBE_ON();
    sa_finish(&enc, speed_cmm_s);
    ENC_PROBE_OFF();
    cli();
    uint16_t dropped = ring.dropped;
    sei();
    counts_frame_head(counts_head, enc.n, (uint16_t)enc.held_windows, dropped, ring.depth_max, &enc.counts[0][0],
                      counts_crc);
    cli();
    /* the counts go out from the encoder's state itself (uint16 little-endian on the AVR, as the frame has them) */
    tx_push_locked(counts_head, sizeof counts_head, TX_COUNTS);
    tx_push_locked((const uint8_t *)&enc.counts[0][0], sizeof enc.counts, TX_COUNTS);
    tx_push_locked(counts_crc, sizeof counts_crc, TX_COUNTS);
    sei();
}

static uint16_t le16(const uint8_t *p)
{
    return (uint16_t)(p[0] | ((uint16_t)p[1] << 8));
}

/* a command with a payload, complete: n bytes, the last 2 the CRC-16 of the others; a bad CRC drops it */
static void enc_command(uint8_t cmd, const uint8_t *p, uint8_t n)
{
    if (rigctl_crc16(p, (uint16_t)(n - 2)) != le16(p + n - 2)) return;
    if (cmd == RIGCTL_ENC_CMD_CALIBRATE) {
        for (uint8_t i = 0; i < RIGCTL_ENC_N_TAXELS; i++) {
            cal_min[i] = le16(p + 2 * i);
            cal_max[i] = le16(p + 2 * (RIGCTL_ENC_N_TAXELS + i));
        }
        cal_k = le16(p + 4 * RIGCTL_ENC_N_TAXELS);
    } else if (cmd == RIGCTL_ENC_CMD_SPEED) {
        /* window p[0..1] (mod 65536): the next one without a speed, or later; an earlier one was held (scaled with
         * the last speed when its slot was needed), and its speed, come too late, is dropped */
        uint16_t next = (uint16_t)(enc.windows_scaled + enc.n_speeds);
        if ((int16_t)(le16(p) - next) < 0) return;
        ENC_PROBE_ON();
        sa_speed(&enc, le16(p + 2)); /* scales the windows waiting for it: ~9 000 cycles, interrupts keep running */
        ENC_PROBE_OFF();
    } else if (cmd == RIGCTL_ENC_CMD_FINISH) {
        enc_finish(le16(p));
    } else if (cmd == RIGCTL_ENC_CMD_ENCODE) {
        enc_begin(le16(p));
    }
}

static uint8_t cmd_byte, cmd_need, cmd_got;
static uint8_t cmd_buf[RIGCTL_ENC_CALIBRATE_PAYLOAD + 2];
#endif

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
    UNO_PROBE_DDR |= (1 << UNO_PROBE_SAMPLER) | (1 << UNO_PROBE_TX) | (1 << UNO_PROBE_ENCODER) | (1 << UNO_PROBE_MARK);
    /* analog inputs A0-A2: digital input buffers off */
    DIDR0 = (1 << ADC0D) | (1 << ADC1D) | (1 << ADC2D);
    ADCSRA = UNO_ADC_PRESCALER_BITS; /* off until the stream starts (the tick switches it on) */
    adc_select(0, 0);
    set_sleep_mode(SLEEP_MODE_IDLE);
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
#ifdef UNO_SA_ENCODER
    enc_poll();
#endif
    while (rx_tail != rx_head) {
        uint8_t c = rx_ring[rx_tail];
        rx_tail = (uint8_t)((rx_tail + 1) & RX_MASK);
#ifdef UNO_SA_ENCODER
        if (cmd_need) { /* a payload byte */
            cmd_buf[cmd_got++] = c;
            if (cmd_got == cmd_need) {
                cmd_need = 0;
                enc_command(cmd_byte, cmd_buf, cmd_got);
            }
            continue;
        }
        if (c == RIGCTL_ENC_CMD_CALIBRATE || c == RIGCTL_ENC_CMD_SPEED || c == RIGCTL_ENC_CMD_FINISH ||
            c == RIGCTL_ENC_CMD_ENCODE) {
            cmd_byte = c;
            cmd_got = 0;
            cmd_need = (uint8_t)((c == RIGCTL_ENC_CMD_CALIBRATE ? RIGCTL_ENC_CALIBRATE_PAYLOAD
                                  : c == RIGCTL_ENC_CMD_SPEED   ? RIGCTL_ENC_SPEED_PAYLOAD
                                  : c == RIGCTL_ENC_CMD_ENCODE  ? RIGCTL_ENC_ENCODE_PAYLOAD
                                                                : RIGCTL_ENC_FINISH_PAYLOAD) + 2);
            continue;
        }
        if (c == RIGCTL_ENC_CMD_ARM) {
            enc_arm();
            continue;
        }
#endif
        if (c == RIGCTL_UNO_CMD_START) {
            stream_start(0);
        } else if (c == RIGCTL_UNO_CMD_STOP) {
            streaming = 0;
#ifdef UNO_SA_ENCODER
            encoding = 0; /* the ring's samples are still encoded (FINISH); an armed ring's are not */
#endif
        } else if (c == RIGCTL_UNO_CMD_IDENTIFY) {
            stop_and_drain();
            send_line_P(identity_P);
        }
    }

    /* nothing left to do until an interrupt: idle sleep (ATmega328P datasheet, "Idle Mode": the CPU stops, Timer0,
     * Timer1, the UART and INT0 run on, and any enabled interrupt wakes it), only with the ADC off (the stream
     * stopped and its last scan over: the tick switched it off) and no byte or sample waiting. Checked with interrupts
     * off, SLEEP right after SEI (the instruction after SEI runs before any interrupt), so an interrupt after the
     * check wakes the CPU at once instead of being slept past; nothing but loop() starts the stream, so the ADC
     * cannot come on in between. The wake-ups are the tick, Timer0's millis, a host byte, the transmitter. While
     * streaming, a pass only reads (no CLI/SEI): the harness skips the repeats of such a polling pass (docs/firmware.md,
     * "A spinning core"). */
    if (streaming || (ADCSRA & (1 << ADEN))) return;
    cli();
    if (rx_tail == rx_head
#ifdef UNO_SA_ENCODER
        && !(ring.encoding && sa_ring_depth(&ring))
#endif
    ) {
        sleep_enable();
        sei();
        sleep_cpu();
        sleep_disable();
    }
    sei();
}
