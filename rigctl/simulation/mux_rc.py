"""The taxel board's analog front end on the model rigs (``--sim``, ``--inprocess``): each taxel's source impedance
and anti-alias capacitor C_aa at its 74HC4051 input, and the multiplexer node and the ADC's sample-and-hold that the
firmware discharges to 0 V before each input (docs/firmware.md, "Taxel source impedance and anti-alias filter"), as
the simavr harness models them with the real firmware (arduino/simavr/rigctl_simavr.c, ``--hil``).

Per frame and taxel: C_aa charges towards the taxel's source value through its source impedance R for one frame
period; at its turn the discharged node and sample-and-hold (25 + 14 pF: NXP/TI 74HC4051 C_S, ATmega328P
"Analog Input Circuitry"; /work/shared/notes/bench-facts.md) share their charge with it, and all charge together
through R + R_on (180 Ohm) for the 17 us the firmware lets pass before it samples. Without C_aa the node alone
charges from 0 V for those 17 us. So a taxel reads its own signal low-passed by R x C_aa and scaled by a gain a
little under 1 (-0.34 % at 47 kOhm and 15 nF; 1 - exp(-17 us / (R x 39 pF)) without C_aa: 0.35 at 1 MOhm), and
nothing of its neighbours': the discharge makes the charge each switch moves depend on the taxel's own voltage only.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["MuxFrontEnd", "MUX_NODE_PF", "SAMPLE_HOLD_PF", "MUX_RON_OHM", "SETTLE_S"]

#: 74HC4051 common-node capacitance, pF (NXP/TI datasheets, C_S)
MUX_NODE_PF = 25.0
#: ATmega328P sample-and-hold capacitance, pF (datasheet, "Analog Input Circuitry")
SAMPLE_HOLD_PF = 14.0
#: 74HC4051 on-resistance at 4.5 V, Ohm (datasheets: ~70-180)
MUX_RON_OHM = 180.0
#: from an input's selection to its sample: UNO_SETTLE_COUNTS (14 us) + 1.5 ADC clocks (3 us), s
SETTLE_S = 17e-6


class MuxFrontEnd:
    """The analog path of ``n_channels`` taxels into the ADC (see the module docstring).

    Attributes
    ----------
    source_ohm : float
        Every taxel's source impedance (R_s + R_aa), Ohm; 0: an ideal source (the samples pass unchanged).
    aa_c_nf : float
        C_aa at every mux input, nF (docs: 15 nF; 0 = none fitted).
    """

    def __init__(self, n_channels: int, *, source_ohm: float = 0.0, aa_c_nf: float = 0.0,
                 period_s: float = 1e-3, adc_max: int = 1023) -> None:
        self.n_channels, self.period_s, self.adc_max = int(n_channels), float(period_s), int(adc_max)
        self.source_ohm, self.aa_c_nf = float(source_ohm), float(aa_c_nf)
        self._v: np.ndarray | None = None  # each C_aa's voltage after the last frame, in ADC counts

    @property
    def carries_state(self) -> bool:
        """True when the next frames' codes depend on this frame's (C_aa's charge is kept between frames): then every
        frame must pass through :meth:`apply`, also those nobody takes."""
        return self._v is not None or (self.source_ohm > 0.0 and self.aa_c_nf > 0.0)

    def apply(self, counts: np.ndarray) -> np.ndarray:
        """The ADC codes of ``counts`` ((n, n_channels) uint16: the taxels' source values, one row per frame, at the
        centre of their code) read through the front end, (n, n_channels) uint16."""
        r = self.source_ohm
        if r <= 0.0 or not len(counts):
            self._v = None
            return counts
        src = counts.astype(np.float64) + 0.5
        c_p = (MUX_NODE_PF + SAMPLE_HOLD_PF) * 1e-12
        if self.aa_c_nf <= 0.0:
            out = src * (1.0 - math.exp(-SETTLE_S / ((r + MUX_RON_OHM) * c_p)))
        else:
            c = self.aa_c_nf * 1e-9
            a = math.exp(-self.period_s / (r * c))
            share = c / (c + c_p)
            b = math.exp(-SETTLE_S / ((r + MUX_RON_OHM) * (c + c_p)))
            v = src[0].copy() if self._v is None else self._v
            out = np.empty_like(src)
            for i in range(len(src)):
                v = src[i] + (v - src[i]) * a  # C_aa through R until its turn
                v = src[i] + (v * share - src[i]) * b  # the node and sample-and-hold join it from 0 V, then settle
                out[i] = v
            self._v = v
        return np.clip(np.floor(out), 0, self.adc_max).astype(np.uint16)
