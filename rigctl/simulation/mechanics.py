"""The drum and actuator mechanics of one step of :meth:`rigctl.simulation.model.RigModel.advance`, compiled.

The live rigs advance the model a few ms at a time, hundreds of times a second, for as long as they run; in numpy
each step was ~25 calls on arrays of three elements, and their fixed costs were most of a simulated rig's CPU. The
kernel computes the same quantities in the same order, one ms after another (the definitions are
:meth:`RigModel.advance`'s Notes: speed ramp, surface travel, index-mark passes, actuator travel, contact force with
the drum's runout and the texture ripple of :meth:`rigctl.simulation.model.SensorModel.contact_height`).
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def step_mechanics(speed0, target, accel_step, pos0, circ, act0, act_step, travel, gap, runout_mm, runout_phase,
                   stiffness, ripple, h_row, h_period, h_mean, pitch, pos_out, sync_out, force_out, slip,
                   motor_out, marks_per_mm, marks_out, motor0):  # pragma: no cover
    """Advance ``pos_out.size`` 1 ms steps; fills ``pos_out`` (surface travel, mm, unwrapped), ``sync_out`` (the
    index mark passed in that ms) and ``force_out`` (contact force, g); returns ``(speed, actuator_mm, pos, force,
    motor)`` after the last step (the last ms's ``pos_out``, ``force_out`` and ``motor_out``: the caller needs no
    array access for them).

    ``slip``: the fraction of the stepper's travel the drum loses (0: none, 1: a blocked drum); ``motor_out``: the
    stepper's travel per ms, mm of surface (what its step count says, without the slip), from ``motor0`` at the step's
    start (its travel since then, plus ``motor0``).
    ``marks_out``: a speed mark passed in that ms (the slot ``floor(travel * marks_per_mm)`` changed).
    ``speed0``/``target``: the stepper's surface speed now and commanded, mm/s; ``accel_step``: the speed change allowed per ms,
    mm/s; ``pos0``: travel now, mm; ``circ``: drum circumference, mm; ``act0``, ``act_step``, ``travel``, ``gap``:
    actuator position now, its travel per ms, its range and the contact gap, mm; ``runout_mm``, ``runout_phase``
    (rad); ``stiffness``, g/mm; ``ripple``: relative texture ripple of the force; ``h_row`` (n_table,) float64: the
    bottom layer's smoothed height table over ``h_period`` mm, ``h_mean`` its mean, ``pitch`` the taxel pitch, mm.
    """
    n = pos_out.size
    dv = target - speed0
    sign = 1.0 if dv >= 0.0 else -1.0  # math.copysign(1.0, dv) for dv != -0.0
    n_table = h_row.size
    rev_before = math.floor(pos0 / circ)
    slot_before = math.floor(pos0 * marks_per_mm)
    acc = 0.0
    speed = speed0
    act = act0
    for i in range(n):
        k = i + 1.0
        ramp = accel_step * k
        speed = target if ramp >= abs(dv) else speed0 + sign * ramp
        acc += speed
        motor_out[i] = acc * 1e-3 + motor0
        pos = pos0 + (1.0 - slip) * acc * 1e-3
        pos_out[i] = pos
        rev = math.floor(pos / circ)
        sync_out[i] = rev != rev_before
        rev_before = rev
        slot = math.floor(pos * marks_per_mm)
        marks_out[i] = slot != slot_before
        slot_before = slot
        act = min(max(act0 + act_step * k, 0.0), travel)
        compression = act - gap
        runout = runout_mm * math.sin(2 * np.pi * pos / circ + runout_phase)
        force = stiffness * max(compression + (runout if compression > 0 else 0.0), 0.0)
        x = ((pos % circ) - pitch) / h_period * n_table
        idx = int(math.floor(x)) % n_table
        force_out[i] = force * (1.0 + ripple * (h_row[idx] - h_mean))
    return speed, act, pos_out[n - 1], force_out[n - 1], motor_out[n - 1]
