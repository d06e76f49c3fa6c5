"""The fixed numbers of the paper's encoding model, their one home: the encoder (:mod:`rigctl.encoding`), the file
formats that record its parameters (:mod:`rigctl.storage.encoded`) and the operator layer's live encoder all read
them from here."""

__all__ = ["MODEL_RATE_HZ", "MODEL_STEP_S", "RA_CUTOFF_HZ", "SPIKE_TICK_RTOL"]

#: the model's step rate, Hz: one Izhikevich step per ms (Izhikevich 2003's scheme, :mod:`rigctl.encoding.izhikevich`);
#: readings at another rate are resampled to it (:mod:`rigctl.encoding.rate`)
MODEL_RATE_HZ: float = 1000.0
#: the model's time step, s (1 ms)
MODEL_STEP_S: float = 1.0 / MODEL_RATE_HZ
#: the RA input's low-pass cutoff, Hz (Methods: a 20 Hz Butterworth low-pass before the derivative,
#: :mod:`rigctl.encoding.filters`)
RA_CUTOFF_HZ: float = 20.0
#: how close a spike time stored as ticks must be to its time (relative: ``|ticks x tick_s x scale - t| <= SPIKE_TICK_RTOL
#: x |t|``), or the time is refused as off the tick grid: the encoded writer's check of float times and the encoder's
#: compiled tick pass (:meth:`rigctl.encoding.spikes.SpikeTrains.hstack_ticks`) both hold to it
SPIKE_TICK_RTOL: float = 1e-12
