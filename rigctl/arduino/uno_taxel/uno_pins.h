/* uno_pins.h - Uno (ATmega328P) wiring of the taxel streamer; docs/firmware.md has the drawing. */
#ifndef UNO_PINS_H
#define UNO_PINS_H
/* mux select lines S0, S1, S2 of all three 74HC4051 = D4, D5, D6 = PORTD bits 4..6 (written in one store) */
#define UNO_SEL_PORT      PORTD
#define UNO_SEL_DDR       DDRD
#define UNO_SEL_SHIFT     4
#define UNO_SEL_MASK      (0x07 << UNO_SEL_SHIFT)
/* mux outputs (COM) of mux 0, 1, 2 -> A0 (PC0), A1, A2 = ADC channels 0..2; A3-A5 unused. Declared for the
 * docs' pin table (rigctl/firmware_pins.py), like every pin the board uses */
#define UNO_MUX_COM_PIN   PINC
#define UNO_MUX_COM_SHIFT 0
#define UNO_MUX_COM_MASK  (0x07 << UNO_MUX_COM_SHIFT)
/* sync-in from the Mega's index output -> D2 (PD2) = INT0, rising edge */
#define UNO_SYNC_IN_PIN   PIND
#define UNO_SYNC_IN_BIT   2
/* timing probes for the simavr harness and a scope: D8 (PB0) high while a sampler ISR runs,
 * D9 (PB1) high while the UART transmit ISR runs, D10 (PB2) high while loop() runs the encoder (uno_encoder image) */
#define UNO_PROBE_PORT    PORTB
#define UNO_PROBE_DDR     DDRB
#define UNO_PROBE_SAMPLER 0
#define UNO_PROBE_TX      1
#define UNO_PROBE_ENCODER 2
/* marker for the simavr harness and a scope: D11 (PB3) high from the tick that gives the encoder a scan's first sample
 * to the next tick (uno_encoder image) */
#define UNO_PROBE_MARK    3
/* ADMUX MUX3:0 of the ADC's GND channel (0 V): the sample-and-hold is discharged there between two inputs */
#define UNO_ADMUX_GND     0x0F
/* ADC clock prescaler 32: 500 kHz ADC clock, 13 ADC clocks = 26 us per conversion, 18 conversions ~ 0.47 ms */
#define UNO_ADC_PRESCALER_BITS ((1 << ADPS2) | (1 << ADPS0))
/* Timer1 at clk/8 (0.5 us per count): TOP of the 1 kHz tick, and the settling time between selecting an input and
 * starting its conversion: 28 counts = 14 us, + 3 us of sampling = 9 tau at 47 kOhm source impedance (tau =
 * 47 kOhm x (25 pF 74HC4051 COM + 14 pF sample-and-hold) = 1.8 us): <0.1 LSB of a full-scale step remains.
 * Scan: 18 x (26 us conversion + 14 us + ~4 us of interrupt entry) ~ 0.8 ms of the 1 ms tick (docs/firmware.md) */
#define UNO_TICK_TOP       1999
#define UNO_SETTLE_COUNTS  28
#endif
