/* onboard_host.h - the on-board encoder's C (common/sa_ring.c, common/sa_encoder.c with -DSA_FIXED) built for the host,
 * for the model of the encoder board (rigctl.simulation.onboard_c loads it through cffi). Never on the Uno: the board's
 * glue is uno_taxel.cpp (-DUNO_SA_ENCODER), which calls the same functions in the same order. */
#ifndef RIGCTL_ONBOARD_HOST_H
#define RIGCTL_ONBOARD_HOST_H

#include <stddef.h>
#include <stdint.h>

#include "../common/sa_encoder.h"
#include "../common/sa_ring.h"

typedef struct {
    sa_encoder_t enc;
    sa_ring_t ring;
    uint8_t storage[SA_RING_SAMPLES][SA_RING_BYTES];
    uint16_t cal_min[SA_N_TAXELS], cal_max[SA_N_TAXELS], cal_k;
} onboard_host_t;

size_t onboard_host_sizeof(void);
/* CALIBRATE then ARM (uno_taxel.cpp enc_arm) */
void onboard_host_arm(onboard_host_t *b, const uint16_t lo[SA_N_TAXELS], const uint16_t hi[SA_N_TAXELS], uint16_t k);
/* the tick's sample into the ring; 0 when dropped */
uint8_t onboard_host_push(onboard_host_t *b, const uint16_t x[SA_N_TAXELS]);
/* ENCODE from sample `from` (enc_begin); returns the sample the encoding starts at */
uint16_t onboard_host_begin(onboard_host_t *b, uint16_t from);
/* loop()'s enc_poll: encode the oldest waiting sample; returns 1 with its spike mask in *mask, 0 if none waits */
uint8_t onboard_host_step(onboard_host_t *b, uint16_t *mask);
/* SPEED (sa_speed), FINISH (sa_finish after the ring is drained) */
int8_t onboard_host_speed(onboard_host_t *b, uint16_t speed_cmm_s);
void onboard_host_finish(onboard_host_t *b, uint16_t speed_cmm_s);
/* the counts frame's fields */
void onboard_host_counts(const onboard_host_t *b, uint16_t counts[SA_N_TAXELS * SA_N_WINDOWS]);
uint32_t onboard_host_samples(const onboard_host_t *b);
uint32_t onboard_host_held(const onboard_host_t *b);
uint16_t onboard_host_dropped(const onboard_host_t *b);
uint8_t onboard_host_depth_max(const onboard_host_t *b);

#endif
