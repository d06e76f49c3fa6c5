"""rigctl: control, recording and neuromorphic analysis for a tactile texture drum rig.

Subpackages, in the direction data flows:

- :mod:`rigctl.devices` - wire protocols and the clients of the two boards (drum controller, taxel streamer)
- :mod:`rigctl.simulation` - the simulated rig: physical model, virtual boards on ptys, replay, dataset generator
- :mod:`rigctl.acquisition` - protocols (TOML), the rig facade and the trial runner
- :mod:`rigctl.storage` - HDF5 session files
- :mod:`rigctl.encoding` - force invariance, Izhikevich SA/RA encoding, speed invariance, spiking features
- :mod:`rigctl.analysis` - PCA + LDA analyses of the paper (Fig. 3, Table 1, Fig. 4)
- :mod:`rigctl.operations` - the operator layer the CLI and the GUI call (open a rig, setpoints, run, analyse)

What every layer shares is :mod:`rigctl.core`; :mod:`rigctl.rigs` opens a rig of any kind. Each package re-exports
its public names (``from rigctl.storage import open_session``; ``__all__`` lists them, docs/architecture.md
describes them); the most used ones are re-exported here too.
"""

__version__ = "0.1.0"

from rigctl.core.lazy import lazy_exports

#: the package's public names and the module each lives in
_EXPORTS = {
    "load_protocol": "rigctl.acquisition.protocol",
    "run_protocol": "rigctl.acquisition.runner",
    "load_features": "rigctl.analysis.data",
    "SensorLayout": "rigctl.core.sensor",
    "TextureSet": "rigctl.core.textures",
    "encode_session": "rigctl.encoding.pipeline",
    "RigSource": "rigctl.operations",
    "open_control": "rigctl.operations",
    "open_rig": "rigctl.rigs",
    "open_session": "rigctl.storage.session",
}
__all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
