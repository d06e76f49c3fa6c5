"""Example Python protocol: a force sweep on one texture, for what the TOML format does not cover.

Run it like a TOML protocol:

    rigctl acquire example_script --out sweep.h5

A Python protocol defines ``plan(ctx)``, a generator (bluesky's plans are the model): it yields the trials it
wants (``ctx.trial(...)``) and gets each one's recording back from the ``yield`` (a
:class:`rigctl.core.trial.TrialData`, or None when the trial failed after its retries). The run engine does the rest,
as for a TOML protocol: plates, pressing, recording, retries, pause, STOP, the safety latch, progress, and a
crash-safe write of every trial (resume with ``--resume``: the recorded trials are replayed from the file, so the
plan must decide the same way from the same data). See docs/protocols.md, "Python protocols".

This one sweeps the contact force upwards in 100 g steps on the wave texture L at 100 mm/s until the mean taxel
reading of the top layer stops rising by more than 2 ADC counts (the sensor's saturation, which the paper's force
invariance module, eq. 1, has to undo), capped at 6 steps.
"""

NAME = "force_sweep_example"
MAX_TRIALS = 6  # the progress bar's total: at most one trial per force

TEXTURE = "L"
SPEED_MM_S = 100.0
TRAVEL_MM = 120.0  # half a paper trial: 1.2 s at 100 mm/s
FORCES_G = [200.0, 300.0, 400.0, 500.0, 600.0, 700.0]
MIN_RISE_COUNTS = 2.0


def plan(ctx):
    previous = None
    for force in FORCES_G:
        data = yield ctx.trial(TEXTURE, speed_mm_s=SPEED_MM_S, force_g=force, travel_mm=TRAVEL_MM)
        if data is None:  # failed after its retries: the next force
            continue
        top_mean = float(data.taxels[:, :9].mean())
        ctx.note(f"{force:6.0f} g: mean top-layer reading {top_mean:6.1f} ADC counts")
        if previous is not None and top_mean - previous < MIN_RISE_COUNTS:
            ctx.note("the reading stopped rising: saturation reached")
            return
        previous = top_mean
