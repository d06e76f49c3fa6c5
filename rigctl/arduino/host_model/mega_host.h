/* mega_host.h - see mega_host.c (the model rig's host build of the drum controller; never on the Mega) */
#ifndef MEGA_HOST_H
#define MEGA_HOST_H
#include <stddef.h>
#include "../mega_drum/controller.h"
/* the layout the Python side checks its declaration of ctl_t against */
size_t mega_host_sizeof_ctl(void);
size_t mega_host_offsetof_drum_slip(void);
/* loop()'s ticks for the ms first_ms .. first_ms + n - 1, the step count from pos0 to pos1; returns the ticks run */
uint16_t mega_host_ticks(ctl_t *c, uint32_t first_ms, uint16_t n, int32_t pos0, int32_t pos1);
/* drum_apply(): the drum's step timer for the commanded speed (stopped when inhibit); returns its step rate, steps/s */
float mega_host_drum_apply(ctl_t *c, uint8_t inhibit);
#endif
