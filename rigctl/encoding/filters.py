"""The RA input path: 20 Hz low-pass, then the time derivative (Methods, spiking activity encoding; Fig. 2D).

"The RA mechanoreceptors are implemented using the Tonic Spiking model as well but applied to the tactile sensor
readings that have been smoothed with a 20 Hz lowpass filter and then differentiated." The paper does not name the
filter; we use:

- **Low-pass:** a 2nd-order Butterworth (``scipy.signal.butter(2, cutoff_hz, fs=fs)``), applied causally with
  ``scipy.signal.lfilter`` (direct form II transposed), so that batch and streaming give bit-identical output.
  The encoders (:mod:`rigctl.encoding.fused`, :mod:`rigctl.encoding.izhikevich`) run the same recurrence in their
  kernel and take only the coefficients: those of the default filter (2nd order, :data:`RA_CUTOFF_HZ` at
  :data:`MODEL_RATE_HZ`) are a table of scipy's exact float64 values (``tests/encoding/test_enc_filters.py`` checks
  them against scipy's), so no encoding process imports ``scipy.signal`` (~0.65 CPU-s: it loads ``scipy.stats``
  too); other parameters ask scipy. :func:`ra_input` and :class:`RAFilter` (the reference, used by tests) call
  ``lfilter`` itself: a numpy loop in its operation order matches its numbers bit for bit but not the payload of a
  nan where two nans meet (numpy's ``add`` keeps either operand's, depending on the array's length).
  The filter state is initialised to the steady state of the first sample (``lfilter_zi * x[0]``): a trial that
  starts at a reading of 0.6 starts filtered at 0.6, with no artificial step from 0 (which the derivative would turn
  into a burst of RA spikes at every trial start).
- **Derivative:** backward difference in **normalised units per second**, ``d[n] = (y[n] - y[n-1]) * fs`` with
  ``d[0] = 0``. Per second rather than per sample because with k = 3 (eq. 3) a per-sample difference at 1 kHz
  (|d| well below 0.05 for 0-1 readings) could never drive the tonic-spiking neuron past its rheobase (k*I of about
  4), so RA would be silent; per second, a texture edge that moves the reading by 0.1 in 20 ms gives k*I = 15.
- **Sign:** the derivative is half-wave rectified by default (``rectify=True``): RA fires on rising pressure.
  A negative current only hyperpolarises a tonic-spiking neuron, and a large one (k*I below about -100) makes the
  explicit 0.5 ms Euler step of eq. (3) unstable (the 0.04 v^2 term overshoots) and fires spurious spikes, so
  negative inputs are cut to 0. ``rectify=False`` passes the signed derivative (use with care).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from rigctl.core.encoding_model import MODEL_RATE_HZ, RA_CUTOFF_HZ

__all__ = ["lowpass_coefficients", "ra_input", "RAFilter"]


#: ``(b, a, lfilter_zi(b, a))`` of ``scipy.signal.butter(2, RA_CUTOFF_HZ, btype="low", fs=MODEL_RATE_HZ)``, as
#: scipy 1.17 computes them, exact float64 values (``float.hex``; checked against scipy by the tests).
_DEFAULT_LOWPASS = (
    (float.fromhex("0x1.dab3775387e7dp-9"), float.fromhex("0x1.dab3775387e7dp-8"), float.fromhex("0x1.dab3775387e7dp-9")),
    (1.0, float.fromhex("-0x1.d29c22764da5bp+0"), float.fromhex("0x1.aca312c9e96b0p-1")),
    (float.fromhex("0x1.fe254c88ac789p-1"), float.fromhex("-0x1.aac85f5295e38p-1")),
)


@lru_cache(maxsize=16)
def lowpass_coefficients(cutoff_hz: float = RA_CUTOFF_HZ, fs: float = MODEL_RATE_HZ,
                         order: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(b, a, zi_unit)`` of the Butterworth low-pass; ``zi_unit`` is ``lfilter_zi(b, a)`` (steady state for 1).

    ``b``, ``a``: ``(order + 1,)`` float64, ``a[0] == 1``; ``zi_unit``: ``(order,)`` float64. Those of
    ``scipy.signal.butter(order, cutoff_hz, btype="low", fs=fs)``: the default filter's from a table of scipy's
    values (no ``scipy.signal`` import), any other's from scipy.

    Raises
    ------
    ValueError
        if ``cutoff_hz`` is not in (0, fs/2).
    """
    if not 0 < cutoff_hz < fs / 2:
        raise ValueError(f"cutoff_hz={cutoff_hz} must be in (0, {fs / 2}) for fs={fs}")
    if (cutoff_hz, fs, order) == (RA_CUTOFF_HZ, MODEL_RATE_HZ, 2):
        b, a, zi = (np.array(v, dtype=np.float64) for v in _DEFAULT_LOWPASS)
        return b, a, zi
    # (scipy.signal imported on first use: it takes ~0.65 CPU-s to import, and the default filter needs none of it)
    from scipy import signal

    b, a = signal.butter(order, cutoff_hz, btype="low", fs=fs)
    return b, a, signal.lfilter_zi(b, a)


def ra_input(readings: np.ndarray, *, cutoff_hz: float = RA_CUTOFF_HZ, fs: float = MODEL_RATE_HZ, rectify: bool = True,
             order: int = 2) -> np.ndarray:
    """RA input current of one trial: low-passed, differentiated, rectified (see module docstring).

    Parameters
    ----------
    readings : (n_samples, n_taxels) float, normalised 0-1 readings of one trial (or ``(n_trials, n_samples,
        n_taxels)``: filtered along axis -2).
    cutoff_hz, fs : low-pass cutoff and sample rate (Hz).
    rectify : half-wave rectify the derivative.

    Returns
    -------
    float64 array of the input's shape, normalised units per second.
    """
    x = np.asarray(readings, dtype=np.float64)
    if x.ndim not in (2, 3):
        raise ValueError(f"readings must be (n_samples, n_taxels) or (n_trials, n_samples, n_taxels), got {x.shape}")
    if x.shape[-2] == 0:
        return np.zeros_like(x)
    b, a, zi_unit = lowpass_coefficients(float(cutoff_hz), float(fs), int(order))
    first = x[..., :1, :]  # (..., 1, n_taxels)
    zi = zi_unit[:, None] * first  # broadcasts to (..., order, n_taxels)
    from scipy.signal import lfilter

    y, _ = lfilter(b, a, x, axis=-2, zi=zi)
    d = np.empty_like(y)
    d[..., 0, :] = 0.0
    np.subtract(y[..., 1:, :], y[..., :-1, :], out=d[..., 1:, :])
    d *= fs
    if rectify:
        np.maximum(d, 0.0, out=d)
    return d


class RAFilter:
    """Streaming version of :func:`ra_input`: same output, chunk by chunk (filter state and last value kept).

    Parameters
    ----------
    n_taxels : int
    cutoff_hz, fs, rectify, order : as in :func:`ra_input`.
    """

    def __init__(self, n_taxels: int, *, cutoff_hz: float = RA_CUTOFF_HZ, fs: float = MODEL_RATE_HZ, rectify: bool = True,
                 order: int = 2):
        self.b, self.a, self._zi_unit = lowpass_coefficients(float(cutoff_hz), float(fs), int(order))
        self.n_taxels = n_taxels
        self.fs = float(fs)
        self.rectify = rectify
        self.reset()

    def reset(self) -> None:
        """Forget the state: the next chunk is treated as a trial start."""
        self._zi: np.ndarray | None = None  # (order, n_taxels) lfilter state
        self._last: np.ndarray | None = None  # (n_taxels,) last filtered sample

    def process(self, chunk: np.ndarray) -> np.ndarray:
        """``(n, n_taxels)`` normalised readings -> ``(n, n_taxels)`` float64 RA input (units/s)."""
        x = np.asarray(chunk, dtype=np.float64)
        if x.ndim != 2 or x.shape[1] != self.n_taxels:
            raise ValueError(f"chunk must be (n, {self.n_taxels}), got {x.shape}")
        if x.shape[0] == 0:
            return np.zeros((0, self.n_taxels))
        if self._zi is None:
            self._zi = self._zi_unit[:, None] * x[:1, :]
            self._last = None
        from scipy.signal import lfilter

        y, self._zi = lfilter(self.b, self.a, x, axis=0, zi=self._zi)
        d = np.empty_like(y)
        d[0] = 0.0 if self._last is None else y[0] - self._last
        np.subtract(y[1:], y[:-1], out=d[1:])
        d[0] *= self.fs
        d[1:] *= self.fs
        self._last = y[-1].copy()
        if self.rectify:
            np.maximum(d, 0.0, out=d)
        return d
