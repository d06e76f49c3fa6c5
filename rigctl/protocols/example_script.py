"""Example Python-script protocol: a force sweep on one texture, for what the TOML format does not cover.

Run it like a TOML protocol:

    rigctl acquire example_script --out sweep.h5

A script protocol defines ``run(rig, session)``. ``rig`` is an open :class:`rigctl.acquisition.rig.Rig` (from
:func:`rigctl.rigs.open_rig`; simulated by default), ``session`` a :class:`rigctl.storage.session.SessionWriter`
whose plan starts empty. Each trial is
planned, recorded and appended in one step, so an interrupted script keeps every finished trial.

This one sweeps the contact force upwards in 100 g steps on the wave texture L at 100 mm/s until the mean taxel
reading of the top layer stops rising by more than 2 ADC counts (the sensor's saturation, which the paper's force
invariance module, eq. 1, has to undo), capped at 6 steps.
"""

from rigctl.core import PlannedTrial

NAME = "force_sweep_example"

TEXTURE = "L"
SPEED_MM_S = 100.0
TRAVEL_MM = 120.0  # half a paper trial: 1.2 s at 100 mm/s
FORCES_G = [200.0, 300.0, 400.0, 500.0, 600.0, 700.0]
MIN_RISE_COUNTS = 2.0


def run(rig, session):
    rig.mount_texture(TEXTURE)
    previous = None
    for force in FORCES_G:
        planned = PlannedTrial(
            trial_id=session.next_trial_id(), texture=TEXTURE, speed_mm_s=SPEED_MM_S, force_g=force,
            duration_s=TRAVEL_MM / SPEED_MM_S,
        )
        data = rig.record_trial(planned)
        session.append_trial(planned, data)
        top_mean = float(data.taxels[:, :9].mean())
        print(f"{force:6.0f} g: mean top-layer reading {top_mean:6.1f} ADC counts")
        if previous is not None and top_mean - previous < MIN_RISE_COUNTS:
            print("the reading stopped rising: saturation reached")
            break
        previous = top_mean
