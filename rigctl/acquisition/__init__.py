"""rigctl.acquisition: recording sessions on the rig (devices -> acquisition -> storage).

- :mod:`rigctl.acquisition.protocol` - TOML protocol files (validated, errors name the key and line; any texture
  set via ``[texture_set]``) and Python-script protocols; ``load_protocol(path)``, ``Protocol.plan()``,
  ``Protocol.texture_set``.
- :mod:`rigctl.acquisition.rig` - ``Rig``: a drum controller, a taxel source and their backend behind one object,
  typed against :mod:`rigctl.core.interfaces`; opened by ``rigctl.rigs.open_rig(kind)`` (the composition root;
  this package never imports ``rigctl.simulation``); ``layout``, ``textures``, ``mount_texture``, ``press``,
  ``record_trial``, ``safe_stop``.
- :mod:`rigctl.acquisition.runner` - ``run_protocol(protocol, out_path, rig=...)``: trial by trial into a session
  file, with progress, Ctrl-C / stop / pause, failed trials and ``resume``.
- :mod:`rigctl.acquisition.calibration` - load-cell calibration with a known mass, per-taxel normalisation;
  :mod:`rigctl.acquisition.rigconfig` - the rig config file (``~/.config/rigctl/rig.json``) that keeps them;
  :mod:`rigctl.acquisition.motion` - ``wait_released`` (shared by the rig and the calibration).
- :mod:`rigctl.acquisition.link_health` - ``LinkHealth``: one health model for both boards' links (connected /
  stalled / lost / reconnected / controller reset), pure, shown by the GUI.
"""

from typing import TYPE_CHECKING

from rigctl.core.lazy import lazy_exports

#: the package's public names and the module each lives in
_EXPORTS = {
    "find_protocol": "rigctl.acquisition.builtin",
    "LoadCellCalibration": "rigctl.acquisition.calibration",
    "calibrate_loadcell": "rigctl.acquisition.calibration",
    "taxel_normalisation": "rigctl.acquisition.calibration",
    "taxel_normalisation_from_session": "rigctl.acquisition.calibration",
    "Protocol": "rigctl.acquisition.protocol",
    "ProtocolError": "rigctl.acquisition.protocol",
    "Settle": "rigctl.acquisition.protocol",
    "load_protocol": "rigctl.acquisition.protocol",
    "parse_protocol": "rigctl.acquisition.protocol",
    "CaptureError": "rigctl.acquisition.rig",
    "Rig": "rigctl.acquisition.rig",
    "RigError": "rigctl.acquisition.rig",
    "RigOpenError": "rigctl.acquisition.rig",
    "TrialAborted": "rigctl.acquisition.rig",
    "CalibrationError": "rigctl.acquisition.rigconfig",
    "load_rig_config": "rigctl.acquisition.rigconfig",
    "RunSummary": "rigctl.acquisition.runner",
    "TrialEvent": "rigctl.acquisition.runner",
    "run_protocol": "rigctl.acquisition.runner",
}
if TYPE_CHECKING:
    # what static checkers see: the same names, typed (tests/test_public_api.py holds them equal to _EXPORTS)
    from rigctl.acquisition.builtin import find_protocol as find_protocol
    from rigctl.acquisition.calibration import (
        LoadCellCalibration as LoadCellCalibration,
        calibrate_loadcell as calibrate_loadcell,
        taxel_normalisation as taxel_normalisation,
        taxel_normalisation_from_session as taxel_normalisation_from_session,
    )
    from rigctl.acquisition.protocol import (
        Protocol as Protocol,
        ProtocolError as ProtocolError,
        Settle as Settle,
        load_protocol as load_protocol,
        parse_protocol as parse_protocol,
    )
    from rigctl.acquisition.rig import (
        CaptureError as CaptureError,
        Rig as Rig,
        RigError as RigError,
        RigOpenError as RigOpenError,
        TrialAborted as TrialAborted,
    )
    from rigctl.acquisition.rigconfig import CalibrationError as CalibrationError, load_rig_config as load_rig_config
    from rigctl.acquisition.runner import (
        RunSummary as RunSummary,
        TrialEvent as TrialEvent,
        run_protocol as run_protocol,
    )
else:
    __all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
