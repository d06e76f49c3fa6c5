"""rigctl: control, recording and neuromorphic analysis for a tactile texture drum rig.

Subpackages, in the direction data flows:

- :mod:`rigctl.devices` - wire protocols and the clients of the two boards (drum controller, taxel streamer)
- :mod:`rigctl.simulation` - the simulated rig: physical model, virtual boards on ptys, replay, dataset generator
- :mod:`rigctl.acquisition` - protocols (TOML), the rig facade and the trial runner
- :mod:`rigctl.storage` - HDF5 session files
- :mod:`rigctl.encoding` - force invariance, Izhikevich SA/RA encoding, speed invariance, spiking features
- :mod:`rigctl.analysis` - PCA + LDA analyses of the paper (Fig. 3, Table 1, Fig. 4)
"""

__version__ = "0.1.0"
