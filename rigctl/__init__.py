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

from typing import TYPE_CHECKING

from rigctl.core.caches import configure_numba_cache
from rigctl.core.lazy import lazy_exports
from rigctl.core.version import __version__ as __version__

configure_numba_cache()  # numba's compiled kernels go to the user's cache folder, never into the installed package

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
if TYPE_CHECKING:
    # what static checkers see: the same names, typed (tests/test_public_api.py holds them equal to _EXPORTS)
    from rigctl.acquisition.protocol import load_protocol as load_protocol
    from rigctl.acquisition.runner import run_protocol as run_protocol
    from rigctl.analysis.data import load_features as load_features
    from rigctl.core.sensor import SensorLayout as SensorLayout
    from rigctl.core.textures import TextureSet as TextureSet
    from rigctl.encoding.pipeline import encode_session as encode_session
    from rigctl.operations import RigSource as RigSource, open_control as open_control
    from rigctl.rigs import open_rig as open_rig
    from rigctl.storage.session import open_session as open_session
else:
    __all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
