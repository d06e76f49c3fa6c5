"""Doctor checks of the taxel streamer (Uno), from one capture at rest (drum still, sensor released): the noise
floor per taxel, crosstalk between taxels, and the Uno's sample clock against the host's.
"""

from __future__ import annotations

import math

import numpy as np

from rigctl.acquisition.doctor.base import Check, CheckResult, DoctorContext, Skip, failed, passed
from rigctl.acquisition.doctor.measure import clock_error_ppm, crosstalk, noise_floor
from rigctl.core.trial import lower_envelope_rate_hz

__all__ = ["CHECKS", "MAX_NOISE_COUNTS", "MAX_CROSSTALK", "MIN_CROSSTALK_NOISE_COUNTS", "MAX_CLOCK_PPM"]

#: a taxel noisier than this at rest fails, ADC counts sd (the simulated sensor's floor is 1.6, fitted to FabricSlide's;
#: docs/hardware's grounding plan keeps a real one near it)
MAX_NOISE_COUNTS = 4.0
#: two taxels sharing more than this (the correlation of their changes at rest, :func:`.measure.crosstalk`) fail. An
#: unsettled 74HC4051 node leaves ~20 % of the previous channel at 47 kOhm (a correlation of ~0.24) and ~45 % at
#: 100 kOhm (bench-facts.md), with a firmware that switches straight from one input to the next (the installed one
#: discharges the node first: a taxel above 47 kOhm then reads low instead, docs/firmware.md); 10 s at rest resolve
#: ~0.015 (measured on the simulated sensor: the largest of 153 noise-only pairs stays near 0.045)
MAX_CROSSTALK = 0.10
#: ... or this many times the measurement's own spread, if larger (a short capture cannot resolve 10 %: 4.5 sigma
#: keeps the chance that one of 153 noise-only pairs fails below 0.1 %)
CROSSTALK_SIGMAS = 4.5
#: crosstalk is measured on the taxels' own noise: below this sd of the sample-to-sample change there is too little
MIN_CROSSTALK_NOISE_COUNTS = 0.3
#: the Uno's 16 MHz ceramic resonator is specified to +-0.5 % (Arduino Uno R3 schematic: CSTCE16M0V53); beyond it,
#: the board's clock is faulty
MAX_CLOCK_PPM = 5000.0


def _rest_capture(ctx: DoctorContext):
    def capture():
        rig = ctx.rig()
        rig.release()
        stream = ctx.taxel_stream()
        n = int(round(ctx.rest_s * rig.layout.sample_rate_hz))
        stream.begin_capture()
        try:
            stream.wait_capture(n, timeout_s=3 * ctx.rest_s + 5.0)
        finally:
            cap = stream.end_capture()
        if len(cap) < max(100, n // 2):
            raise RuntimeError(f"the taxel stream delivered {len(cap)} of {n} frames in {3 * ctx.rest_s + 5:g} s")
        return cap
    return ctx.cached("rest-capture", capture)


def check_noise_floor(ctx: DoctorContext) -> CheckResult:
    cap = _rest_capture(ctx)
    sd = noise_floor(cap.samples)
    full = (1 << ctx.rig().layout.adc_bits) - 1
    mean = cap.samples.mean(axis=0)
    values = {"noise_counts": [round(float(v), 3) for v in sd], "mean_counts": [round(float(v), 1) for v in mean]}
    rail = [i for i, m in enumerate(mean) if m <= 0.5 or m >= full - 0.5]
    if rail:
        return failed("noise-floor", f"taxel {rail[0]} reads {mean[rail[0]]:.0f} counts at rest, at the ADC's rail"
                      f"{f' (and {len(rail) - 1} more)' if len(rail) > 1 else ''}", "an open or shorted taxel or mux "
                      "channel: check its wiring and the 74HC4051's select lines (docs/hardware pin table)", **values)
    worst = int(np.argmax(sd))
    what = f"sd {np.median(sd):.2f} counts median, worst taxel {worst} {sd[worst]:.2f} counts ({len(cap)} samples)"
    if sd[worst] > MAX_NOISE_COUNTS:
        return failed("noise-floor", what + f" > {MAX_NOISE_COUNTS:g}", "one ground point for the Uno and the sensor, "
                      "shielded taxel leads, an RC at each mux input (docs/hardware, power and grounding)", **values)
    return passed("noise-floor", what, **values)


def check_crosstalk(ctx: DoctorContext) -> CheckResult:
    cap = _rest_capture(ctx)
    coupling, change_sd = crosstalk(cap.samples)
    if not np.isfinite(change_sd).all() or np.median(change_sd) < MIN_CROSSTALK_NOISE_COUNTS:
        raise Skip(f"the taxels are too quiet at rest to measure crosstalk on their noise (median change sd "
                   f"{np.median(change_sd):.2f} counts < {MIN_CROSSTALK_NOISE_COUNTS:g})")
    c = np.where(np.isfinite(coupling), coupling, 0.0)
    j, i = np.unravel_index(int(np.argmax(c)), c.shape)
    worst = float(c[j, i])
    pairs = coupling[np.triu_indices(len(coupling), 1)]
    pairs = pairs[np.isfinite(pairs)]
    # the estimates' own spread (robust: a few bleeding pairs do not move it): ~1.5 / sqrt(n) on quantised,
    # low-passed noise, more than the 1 / sqrt(n) of white noise
    resolution = float(1.4826 * np.median(np.abs(pairs - np.median(pairs)))) if len(pairs) else math.nan
    bound = max(MAX_CROSSTALK, CROSSTALK_SIGMAS * resolution)
    values = {"worst_pair": [int(min(i, j)), int(max(i, j))], "worst_correlation": worst,
              "resolution": resolution, "bound": bound, "per_taxel_max": [round(float(v), 4) for v in c.max(axis=1)]}
    what = (f"taxels {min(i, j)} and {max(i, j)} share {worst * 100:.1f} % (the most of any pair; resolution "
            f"{resolution * 100:.1f} % on {len(cap)} samples, bound {bound * 100:.1f} %)")
    if worst > bound:
        return failed("crosstalk", what, f"the multiplexer node does not settle through taxel {min(i, j)} or "
                      f"{max(i, j)}'s source impedance: keep each taxel's source impedance <= 47 kOhm or buffer it "
                      "(an op-amp follower; docs/hardware), and run the installed firmware (it settles and discharges the mux)",
                      **values)
    return passed("crosstalk", what, **values)


def check_uno_clock(ctx: DoctorContext) -> CheckResult:
    if ctx.mode == "hil":
        raise Skip("the firmware under simavr runs at the simulator's pace, not on a resonator: its rate on the host "
                   "clock measures the simulator")
    if ctx.mode in ("sim", "replay"):  # the in-process rig's clock is simulated: exact, it is checked
        raise Skip("the simulated Uno streams at its simulation thread's pace on this host's CPU, not on a resonator: "
                   "its rate on the host clock measures the simulator (-5271 ppm on a host at load 18)")
    cap = _rest_capture(ctx)
    nominal = float(ctx.rig().layout.sample_rate_hz)
    if len(cap) < 2 or cap.host_time_s[-1] - cap.host_time_s[0] < 2.0:
        raise Skip("less than 2 s of frames")
    rate = lower_envelope_rate_hz(cap.seq, cap.host_time_s, nominal)
    if math.isnan(rate):
        raise Skip("too few frames to measure the rate")
    ppm = clock_error_ppm(rate, nominal)
    what = f"{rate:.3f} frames/s against {nominal:g} nominal: {ppm:+.0f} ppm on the host clock"
    values = {"rate_hz": rate, "nominal_hz": nominal, "error_ppm": ppm}
    if abs(ppm) > MAX_CLOCK_PPM:
        return failed("uno-clock", what, "the Uno's clock is outside its resonator's +-0.5 %: replace the board "
                      "(every trial records the measured rate, but a clock this far off is a fault)", **values)
    return passed("uno-clock", what, **values)


CHECKS = (
    Check("noise-floor", check_noise_floor, title="taxel noise floor at rest, per taxel"),
    Check("crosstalk", check_crosstalk, title="crosstalk between taxels"),
    Check("uno-clock", check_uno_clock, title="the Uno's sample rate against the host clock"),
)
