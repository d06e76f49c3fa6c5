"""rigctl.simulation: the simulated rig (the default everywhere): physical model, virtual boards, replay, datasets.

Public API (re-exported here, imported on first use): the model (``RigConfig``, ``DrumConfig``, ``RigModel``,
``SensorModel``), the rigs (``SimulatedRig`` on ptys, ``HilRig`` the firmware under simavr, ``InProcessBackend`` on a
simulated clock), the boards (``MegaController``, ``VirtualMega``, ``VirtualUno``), ``FaultProxy``, replay
(``SessionReplay``, ``FabricSlideReplay``), datasets (``render_trial``, ``generate_dataset``) and the paper's
``TEXTURES``. Open a simulated rig through :func:`rigctl.rigs.open_rig` (or :func:`rigctl.operations.open_control`).
"""

from typing import TYPE_CHECKING

from rigctl.core.lazy import lazy_exports

#: the package's public names and the module each lives in
_EXPORTS = {
    "MegaController": "rigctl.simulation.controller",
    "generate_dataset": "rigctl.simulation.dataset",
    "render_trial": "rigctl.simulation.dataset",
    "FaultProxy": "rigctl.simulation.fault_proxy",
    "HilRig": "rigctl.simulation.hil",
    "InProcessBackend": "rigctl.simulation.inprocess",
    "DrumConfig": "rigctl.simulation.model",
    "RigConfig": "rigctl.simulation.model",
    "RigModel": "rigctl.simulation.model",
    "SensorModel": "rigctl.simulation.model",
    "FabricSlideReplay": "rigctl.simulation.replay",
    "SessionReplay": "rigctl.simulation.replay",
    "SimulatedRig": "rigctl.simulation.rig",
    "TEXTURES": "rigctl.simulation.textures",
    "VirtualMega": "rigctl.simulation.virtual_mega",
    "VirtualUno": "rigctl.simulation.virtual_uno",
}
if TYPE_CHECKING:
    # what static checkers see: the same names, typed (tests/test_public_api.py holds them equal to _EXPORTS)
    from rigctl.simulation.controller import MegaController as MegaController
    from rigctl.simulation.dataset import generate_dataset as generate_dataset, render_trial as render_trial
    from rigctl.simulation.fault_proxy import FaultProxy as FaultProxy
    from rigctl.simulation.hil import HilRig as HilRig
    from rigctl.simulation.inprocess import InProcessBackend as InProcessBackend
    from rigctl.simulation.model import (
        DrumConfig as DrumConfig,
        RigConfig as RigConfig,
        RigModel as RigModel,
        SensorModel as SensorModel,
    )
    from rigctl.simulation.replay import FabricSlideReplay as FabricSlideReplay, SessionReplay as SessionReplay
    from rigctl.simulation.rig import SimulatedRig as SimulatedRig
    from rigctl.simulation.textures import TEXTURES as TEXTURES
    from rigctl.simulation.virtual_mega import VirtualMega as VirtualMega
    from rigctl.simulation.virtual_uno import VirtualUno as VirtualUno
else:
    __all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
