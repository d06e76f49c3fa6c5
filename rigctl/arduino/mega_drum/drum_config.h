/* drum_config.h - the Mega drum controller's configuration: drum geometry, motion limits, force-loop gains and
 * pins, in one place (docs/wire-protocol.md 2.6, docs/firmware.md). Geometry must match the rig config
 * (rigctl.simulation.model.DrumConfig). */
#ifndef DRUM_CONFIG_H
#define DRUM_CONFIG_H
#include "../common/rigctl_wire.h"

/* ---- drum (spec 2.6): f = v * steps_per_rev * microsteps / (pi * diameter) ---- */
#define DRUM_DIAMETER_MM       ((float)RIGCTL_DRUM_DIAMETER_MM_DEF)
#define DRUM_STEPS_PER_REV     RIGCTL_DRUM_STEPS_PER_REV_DEF
#define DRUM_MICROSTEPS        RIGCTL_DRUM_MICROSTEPS_DEF
#define DRUM_USTEPS_PER_REV    ((uint16_t)(DRUM_STEPS_PER_REV * DRUM_MICROSTEPS))
#define DRUM_ACCEL_MM_S2       400.0f   /* acceleration ramp of the drum's surface speed */
/* speed marks (spec 2.6): microsteps of one mark interval, and the most that may pass without a mark (DRUM_SLIP) */
#define DRUM_MARKS_PER_REV     RIGCTL_DRUM_MARKS_PER_REV
#define DRUM_USTEPS_PER_MARK   ((uint16_t)(DRUM_USTEPS_PER_REV / DRUM_MARKS_PER_REV))
#define DRUM_SLIP_STEPS        ((uint32_t)DRUM_USTEPS_PER_MARK * (100u + RIGCTL_DRUM_SLIP_TOLERANCE_PCT) / 100u)

/* ---- actuator: lead-screw stepper pressing the drum onto the sensor ---- */
#define ACT_MAX_SPEED_MM_S     5.0f     /* force loop output clamp and back-off speed */
#define ACT_HOME_SPEED_MM_S    3.0f     /* HOME seeks the switch at this speed */
#define ACT_MAX_TRAVEL_MM      20.0f    /* end of travel: ACTUATOR_TRAVEL fault while seeking force */
/* HOME gives up (HOME_NOT_FOUND) after this much travel towards home or this long (spec 2.5): a broken switch
 * wire must not drive the actuator into its rear stop for ever */
#define ACT_HOME_MAX_TRAVEL_MM ((float)RIGCTL_HOME_MAX_TRAVEL_MM)
#define ACT_HOME_TIMEOUT_MS    RIGCTL_HOME_TIMEOUT_MS

/* ---- force loop (PI on the load cell, run on each HX711 reading; docs/wire-protocol.md 2.9) ----
 * output: actuator velocity in mm/s, positive towards the sensor. Gains are holding registers (FORCE_KP/KI_80SPS,
 * _10SPS), the time step is the HX711 period measured at boot. The integral grows only while abs(error) is below
 * this band (no wind-up during the approach to contact); rigctl.simulation.model.FORCE_PI_INTEGRATE_BAND_G is held
 * to it by tests/test_wire_spec.py. */
#define FORCE_INTEGRATE_BAND_G 50.0f

/* ---- pins (Arduino Mega 2560) ---- */
/* drum stepper driver: STEP D11 = PB5, DIR D10 = PB4 (Timer1 compare interrupt makes the step pulses) */
#define PIN_DRUM_STEP_PORT  PORTB
#define PIN_DRUM_STEP_DDR   DDRB
#define PIN_DRUM_STEP_BIT   5
#define PIN_DRUM_DIR_BIT    4
/* actuator stepper driver: STEP D5 = PE3, DIR D6 = PH3 (Timer3) */
#define PIN_ACT_STEP_PORT   PORTE
#define PIN_ACT_STEP_DDR    DDRE
#define PIN_ACT_STEP_BIT    3
#define PIN_ACT_DIR_PORT    PORTH
#define PIN_ACT_DIR_DDR     DDRH
#define PIN_ACT_DIR_BIT     3
/* actuator home switch D7 = PH4, to GND when home (internal pull-up) */
#define PIN_HOME_PIN        PINH
#define PIN_HOME_PORT       PORTH
#define PIN_HOME_BIT        4
/* HX711: DOUT D3 = PE5 (input), SCK D4 = PG5 (output) */
#define PIN_HX_DOUT_PIN     PINE
#define PIN_HX_DOUT_PORT    PORTE
#define PIN_HX_DOUT_BIT     5
#define PIN_HX_SCK_PORT     PORTG
#define PIN_HX_SCK_DDR      DDRG
#define PIN_HX_SCK_BIT      5
/* stepper drivers' enable, shared by both drivers: D8 = PH5, active low (A4988, DRV8825, TMC2209 EN).
 * Board: 10 kOhm pull-up EN -> 5 V, so the drivers stay disabled while the MCU is in reset or in its bootloader
 * (pins are inputs then); 10 kOhm pull-downs on both STEP pins so no step is made meanwhile. STATUS_FLAGS'
 * DRIVERS_ENABLED is the line read back on PIN_EN_PIN, not the output latch. */
#define PIN_EN_PORT         PORTH
#define PIN_EN_PIN          PINH
#define PIN_EN_DDR          DDRH
#define PIN_EN_BIT          5
/* e-stop input D2 = PE4 (INT4): normally-closed contact to GND, internal pull-up: open (pressed, or a broken wire)
 * reads high and trips ESTOP in the INT4 interrupt */
#define PIN_ESTOP_PIN       PINE
#define PIN_ESTOP_PORT      PORTE
#define PIN_ESTOP_BIT       4
/* drum index pulse out D9 = PH6 -> Uno D2 (sync-in) */
#define PIN_INDEX_PORT      PORTH
#define PIN_INDEX_DDR       DDRH
#define PIN_INDEX_BIT       6
/* drum index sensor (optical/Hall, open collector, active low) D48 = PL1 = ICP5: Timer5 input capture */
#define PIN_INDEX_SENSOR_PORT PORTL
#define PIN_INDEX_SENSOR_BIT  1
/* drum speed-mark sensor (a slotted disc of RIGCTL_DRUM_MARKS_PER_REV slots on the drum shaft; optical, open
 * collector, active low) D19 = PD2 = INT2: its falling edge is timestamped on Timer5 in the INT2 interrupt */
#define PIN_MARK_SENSOR_PIN   PIND
#define PIN_MARK_SENSOR_PORT  PORTD
#define PIN_MARK_SENSOR_BIT   2
#ifdef RIGCTL_TEST_HOOKS
/* test image only (mega_drum_test.elf, never flashed): pin D22 (port A bit 0) high makes loop() hang, for the
 * AVR watchdog test */
#define PIN_TEST_HANG_PIN   PINA
#define PIN_TEST_HANG_BIT   0
#endif

#endif
