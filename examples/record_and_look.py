# %% [markdown]
# # Record a session and look at it
#
# The built-in protocol `quick_check` (six 2 s trials on plates A, B and L) on the in-process simulated rig (simulated
# time: seconds; `open_rig("sim")` for the rig on serial ports in real time, `open_rig("hardware", drum_port=...,
# taxel_port=...)` for a real one), then the file read back. Run it as a script or cell by cell (`# %%`).

# %%
from pathlib import Path

import numpy as np

from rigctl.acquisition.builtin import find_protocol
from rigctl.acquisition.protocol import load_protocol
from rigctl.acquisition.runner import run_protocol
from rigctl.rigs import open_rig
from rigctl.storage.session import open_session

out = Path("quick_check.h5")
with open_rig("inprocess") as rig:
    summary = run_protocol(load_protocol(find_protocol("quick_check")), out, rig=rig, overwrite=True)
print("\n".join(summary.lines()))

# %% one trial's readings: (n_samples, n_taxels) ADC counts at the sensor's rate, and the drum's traces
with open_session(out) as s:
    print(s.layout.describe())
    for i in s.completed_ids():
        trial = s.trial(i)
        print(f"trial {i}: plate {s.plan['texture'][i]}, {trial.taxels.shape[0]} samples, "
              f"taxel sd {trial.taxels.astype(float).std(axis=0).mean():.1f} counts, "
              f"force {np.median(trial.force_g):.0f} g, speed {np.median(trial.speed_mm_s):.0f} mm/s")
