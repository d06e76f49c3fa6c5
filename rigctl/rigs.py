"""The composition root: the one module that builds rigs.

:func:`open_rig` opens a :class:`rigctl.acquisition.rig.Rig` on the rig of a name: the entry point of that name in
the group ``rigctl.rigs`` (:mod:`rigctl.core.rig_plugins`: rigctl's own rigs are registered there as a plugin's
are, in ``pyproject.toml``) makes its parts, which are started and wrapped here. The CLI (``rigctl acquire``,
``rigctl gui``), the GUI and the tests open rigs here (through :func:`rigctl.operations.open_control`); nothing
else imports the backends together (``rigctl.acquisition`` never imports ``rigctl.simulation``).

rigctl's own rigs (their factories below, each imports its backend only when called):

- ``"sim"`` (:func:`sim_rig`): the simulated rig (:class:`rigctl.simulation.rig.SimulatedRig`: physical model,
  virtual Mega and Uno on real ptys, real-time physics clock); options ``config`` (RigConfig), ``seed``.
- ``"replay"`` (:func:`replay_rig`): the simulated rig streaming recorded taxel signals instead of the model's
  sensor; option ``source``: a replay source object (with ``read(n)``), or a path: a session file
  (:class:`rigctl.simulation.replay.SessionReplay`: its own layout, rate and texture set, following the plates
  mounted) or a directory of FabricSlide CSV files (:class:`rigctl.simulation.replay.FabricSlideReplay`).
- ``"hil"`` (:func:`hil_rig`): the rig's firmware images under simavr (:class:`rigctl.simulation.hil.HilRig`);
  ``config``, ``seed``.
- ``"hardware"`` (:func:`hardware_rig`): the real boards on ``drum_port`` and ``taxel_port``
  (:class:`rigctl.devices.backend.SerialBackend`); plates mounted by the operator (``prompt``).
- ``"inprocess"`` (:func:`inprocess_rig`): the model and the controller logic in this process, on a simulated clock,
  no ptys (:class:`rigctl.simulation.inprocess.InProcessBackend`; fast unit tests of the runner and calibration).
- ``"handheld"`` (:func:`handheld_rig`): the paper's real-time system, no drum: an operator scans flat plates with
  the finger (:class:`rigctl.acquisition.handheld.HandheldRig`); option ``motion``: ``"sim"`` (default: the
  simulated operator, :class:`rigctl.simulation.operator.SimulatedOperator`, on a simulated clock), ``"lsl:NAME"``
  (a tracker stream), ``"serial:PORT"`` (a motion board, :class:`rigctl.devices.motion.SerialMotion`),
  ``"replay:S.h5"`` (a recorded handheld session, :class:`rigctl.simulation.handheld_replay.SessionScans`).

A plugin's rig is opened the same way; a sensor-only plugin (a :class:`rigctl.core.rig_plugins.SampleSource`) is
streamed through the simulated rig's taxel board, the drum simulated (option ``drum``: "sim" or "inprocess").
Common options: ``prompt`` (operator prompt), ``host_config_path`` (the rig config file), ``refuse_fault`` (a
fault latched at open fails it; opening never moves anything), ``textures`` (the rig's default texture set).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from rigctl.acquisition.rig import Rig, RigError
from rigctl.core.errors import describe_error
from rigctl.core.faults import FaultInjector, FaultSpec, check_faults, parse_fault
from rigctl.core.handheld import ScanSource
from rigctl.core.interfaces import RIG_KINDS, RigBackend
from rigctl.core.rig_plugins import (
    SENSOR_DRUMS,
    RigOptionError,
    RigParts,
    RigPluginError,
    RigRequest,
    SampleSource,
    load_rig_factory,
    rig_entries,
)
from rigctl.core.textures import TextureSet

__all__ = ["KINDS", "ANSWER_TIMEOUT_S", "WATCHDOG_MS", "SIM_PACE_ENV", "sim_paced",
           "drum_answer_timeout_s", "fault_refusal", "open_rig", "open_handheld",
           "make_backend", "build_rig", "plugin_identity", "replay_source", "sim_rig", "replay_rig", "hil_rig", "hardware_rig",
           "inprocess_rig", "handheld_rig"]

#: rigctl's own rigs (:data:`rigctl.core.interfaces.RIG_KINDS`); every installed one, plugins included:
#: :func:`rigctl.core.rig_plugins.rig_names`
KINDS = RIG_KINDS

#: how long the host's :class:`rigctl.devices.drum.DrumClient` waits for each Modbus answer, s, per backend. A real
#: Mega answers within milliseconds: 0.5 s, well inside the controller's default 1 s watchdog, so that a lost
#: request is retried before the watchdog trips. The simulated boards share the host's CPU: on a loaded 2-core
#: machine the virtual Mega (a thread of this process) answers up to seconds late, and the firmware under simavr runs
#: at 0.1-0.4 of real time (issue 10's loaded runs); their ptys lose nothing, so a longer wait costs only the time to
#: notice a board that is gone. The in-process backend calls the controller directly (no answer to wait for).
ANSWER_TIMEOUT_S = {"hardware": 0.5, "sim": 2.0, "replay": 2.0, "hil": 2.0}

#: WATCHDOG_MS the drum client writes when it opens, per backend (absent: the controller's default, 1000 ms). On
#: hardware a lost answer is retried after 0.5 s, inside the default 1 s. The simulated rigs (sim, replay, hil) run on
#: one shared clock with their host (rigctl.core.shared_clock): a starved host pauses the simulated world, and the
#: monitor's polls are on that clock too (rigctl.operations.RigMonitor), so starvation no longer needs the 5 s. They
#: keep it for now because the host itself leaves the controller unfed for over 1 s of the rig's time in places: with
#: 1000 ms, tests/acquisition/test_acq_faults.py failed 4 of 16 with WATCHDOG (a taxel link lost or silent during a
#: trial: the capture's failure and the recovery before STOP; issue 55 item 6, open). A test that trips the watchdog
#: on purpose writes the register itself.
WATCHDOG_MS = {"sim": 5000, "replay": 5000, "hil": 5000}


#: the environment variable that chooses how a simulated rig a command opens for itself (``--sim``, ``--replay``,
#: ``--hil``) keeps time: ``wall`` (the default: paced to the wall clock, for a person watching a live view, an LSL
#: consumer) or ``none`` (as fast as the CPU and the host's grants on the shared clock allow: tests, batch runs; every
#: timeout and the controller's watchdog judge the shared clock either way, docs/architecture.md "Time on a
#: simulated rig"). ``rigctl sim``, the rig other programs drive as hardware, is always paced
SIM_PACE_ENV = "RIGCTL_SIM_PACE"
SIM_PACES = {"wall": True, "none": False}


def sim_paced() -> bool:
    """Whether a simulated rig a command opens for itself runs paced to the wall clock (:data:`SIM_PACE_ENV`).

    Raises RigError (one line) for a value other than ``wall`` or ``none``."""
    value = os.environ.get(SIM_PACE_ENV, "").strip().lower() or "wall"
    if value not in SIM_PACES:
        raise RigError(f"{SIM_PACE_ENV}={value!r}: use wall (paced to the wall clock, the default) or none (as fast "
                       "as the CPU allows)")
    return SIM_PACES[value]


def drum_answer_timeout_s(kind: str) -> float:
    """The DrumClient answer timeout for a rig of ``kind``, s (:data:`ANSWER_TIMEOUT_S`). Raises RigError for a kind
    whose drum client does not wait for answers or an unknown kind."""
    try:
        return ANSWER_TIMEOUT_S[kind]
    except KeyError:
        raise RigError(f"no drum answer timeout for rig kind {kind!r}; one of {', '.join(ANSWER_TIMEOUT_S)}") from None


def replay_source(source: Any) -> Any:
    """A replay source for the simulated rig: an object with ``read(n)`` as is; a directory -> the FabricSlide
    replay; a file -> the replay module's session source; ``"lsl:NAME"`` -> the LSL stream NAME
    (:class:`rigctl.simulation.lsl_replay.LslReplay`). Raises RigError when the path or stream cannot be replayed
    (:class:`rigctl.core.lsl.LslUnavailable` without pylsl)."""
    if hasattr(source, "read") or callable(source):
        return source
    if str(source).startswith("lsl:"):  # a live LSL stream (a lab's own taxel device)
        from rigctl.simulation.lsl_replay import LslReplay, LslReplayError

        try:
            return LslReplay(str(source))
        except LslReplayError as exc:
            raise RigError(str(exc)) from None
    path = Path(os.fspath(source))
    from rigctl.simulation import replay

    if path.is_dir():
        return replay.FabricSlideReplay(path)
    if path.is_file():
        return replay.SessionReplay(path)
    raise RigError(f"cannot replay {path}: no such file or directory")


def _config(request: RigRequest) -> Any:
    """The simulated model's configuration a request carries (``RigConfig`` or None; the model checks it)."""
    return request.config


def _request_options(request: RigRequest, *, ports: bool = False) -> dict[str, Any]:
    """A built-in rig's keyword options: the request's, refusing the hardware ports on a simulated rig."""
    options = dict(request.options)
    if not ports and (options.get("drum_port") or options.get("taxel_port")):
        raise RigError(f"drum_port/taxel_port select the hardware rig, not {request.name!r}")
    options.pop("drum_port", None)
    options.pop("taxel_port", None)
    return options


def _pty_backend(request: RigRequest, sim: Any) -> RigBackend:
    from rigctl.simulation.backend import PtyRigBackend

    kind = request.name
    return PtyRigBackend(sim, mode=kind, seed=request.seed, textures=request.textures,
                         drum_timeout_s=ANSWER_TIMEOUT_S[kind], drum_watchdog_ms=WATCHDOG_MS[kind])


def sim_rig(request: RigRequest) -> RigBackend:
    """The simulated rig: virtual Mega and Uno on real ptys driven by the physical model, in real time (--sim).

    Options: ``config`` (RigConfig), the keywords of :class:`rigctl.simulation.rig.SimulatedRig`."""
    from rigctl.simulation.rig import SimulatedRig

    options = _request_options(request)
    if options.pop("source", None) is not None:
        raise RigError("a replay source selects kind='replay'")
    options.setdefault("paced", sim_paced())
    return _pty_backend(request, SimulatedRig(_config(request), seed=request.seed, **options))


def replay_rig(request: RigRequest) -> RigBackend:
    """The simulated rig streaming a recording instead of its model's sensor (--replay: a session, a FabricSlide
    folder, lsl:NAME).

    Option ``source``: a replay source (``read(n)``), a path or ``lsl:NAME`` (:func:`replay_source`)."""
    from rigctl.simulation.rig import SimulatedRig

    options = _request_options(request)
    source = options.pop("source", None)
    if source is None:
        raise RigError("the replay rig needs a source (a session file, a FabricSlide directory, or a source)")
    src = replay_source(source)
    options.setdefault("paced", True if str(source).startswith("lsl:") else sim_paced())  # a live stream paces itself
    textures = request.textures or getattr(src, "textures", None)  # a session replays with its own texture set
    sim = SimulatedRig(_config(request), seed=request.seed, source=src, **options)
    return _pty_backend(dataclasses.replace(request, textures=textures), sim)


def hil_rig(request: RigRequest) -> RigBackend:
    """The rig's own firmware images under simavr, hardware in the loop (--hil).

    Options: ``config``, ``bootloaders`` and the keywords of :class:`rigctl.simulation.hil.HilRig`."""
    options = _request_options(request)
    try:
        from rigctl.simulation.hil import HilRig
    except ImportError as exc:
        raise RigError(f"the HIL rig needs rigctl.simulation.hil (the firmware under simavr): {exc}") from exc
    options.setdefault("paced", sim_paced())
    return _pty_backend(request, HilRig(_config(request), seed=request.seed, **options))


def hardware_rig(request: RigRequest) -> RigBackend:
    """The real boards: the drum controller (Mega, Modbus RTU) and the taxel streamer (Uno) on two serial ports.

    Options ``drum_port``, ``taxel_port`` (--drum-port, --taxel-port); plates mounted by the operator (prompt)."""
    drum_port, taxel_port = request.options.get("drum_port"), request.options.get("taxel_port")
    if not drum_port or not taxel_port:
        raise RigError("the hardware rig needs both drum_port and taxel_port (--drum-port, --taxel-port)")
    request.check_known(("drum_port", "taxel_port"))
    from rigctl.devices.backend import SerialBackend

    return SerialBackend(str(drum_port), str(taxel_port), prompt=request.prompt, textures=request.textures,
                         drum_timeout_s=ANSWER_TIMEOUT_S["hardware"])


def inprocess_rig(request: RigRequest) -> RigBackend:
    """The model and the controller logic in this process on a simulated clock, no ports (--inprocess: dry runs).

    Options: ``config``, ``source`` (a sample source streamed instead of the model's sensor), ``factory_calibrated``,
    ``request_ms``."""
    from rigctl.simulation.inprocess import InProcessBackend

    options = _request_options(request)
    return InProcessBackend(_config(request), seed=request.seed, textures=request.textures, **options)


def handheld_rig(request: RigRequest) -> ScanSource:
    """The paper's real-time system: an operator scans flat plates with the sensor on a finger, no drum (--handheld).

    Option ``motion``: ``sim`` (the simulated operator, default), ``lsl:NAME`` (a tracker stream; options
    ``resolve_s``, ``timeout_s``), ``serial:PORT`` (a motion board; options ``open_timeout_s``, ``timeout_s``) or
    ``replay:S.h5`` (a recorded handheld session). Option ``taxel_port`` (with ``lsl:`` or ``serial:``): the finger's
    taxel board on that port gives the taxels (:class:`rigctl.devices.finger_board.BoardFingerScans`); without it they
    come from the sensor model along the tracked path (:class:`rigctl.simulation.handheld_lsl.TrackedFingerScans`)."""
    options: dict[str, Any] = dict(request.options)
    motion = str(options.pop("motion", "sim"))
    onboard = options.pop("onboard_encoder", None)
    if options.pop("hil_finger", False):
        return _hil_finger(request, motion, onboard, options)
    if onboard is not None:
        if "taxel_port" not in options or not motion.startswith(("lsl:", "serial:")):
            raise RigError("the on-board encoder runs on the finger's taxel board: give its port (taxel_port, with a "
                           "live motion source lsl:NAME or serial:PORT) or run it under simavr (hil_finger)")
        options["onboard_encoder"] = onboard
    if motion == "sim":
        from rigctl.simulation.operator import SimulatedOperator

        if options:
            raise RigError(f"the simulated operator takes no option {', '.join(sorted(options))}"
                           + (" (a finger's taxel board needs a live motion source: lsl:NAME or serial:PORT)"
                              if "taxel_port" in options else ""))
        return SimulatedOperator(seed=request.seed, rig_config=_config(request), textures=request.textures)
    if motion.startswith(("lsl:", "serial:")):
        return _tracked_scans(motion, request, options)
    if motion.startswith("replay:"):
        from rigctl.simulation.handheld_replay import SessionScans

        if options:
            raise RigError(f"a replayed handheld session takes no option {', '.join(sorted(options))}")
        try:
            return SessionScans(motion.removeprefix("replay:"))
        except (OSError, RuntimeError, ValueError) as exc:  # ScanError, SessionError: RuntimeErrors
            raise RigError(f"cannot replay {motion.removeprefix('replay:')}: {exc}") from None
    raise RigError(f"unknown motion source {motion!r}: 'sim' (the simulated operator), 'lsl:NAME' (a tracker "
                   "stream), 'serial:PORT' (a motion board) or 'replay:S.h5' (a recorded handheld session)")


def board_range(training: Any) -> Any:
    """The on-board encoder's CALIBRATE (:class:`rigctl.devices.onboard_finger.BoardRange`) from the encoded
    training block at path ``training`` (its normalisation, rounded, and its k): the board encodes with the range the
    classifier was trained on. A BoardRange is taken as it is. Raises RigError for a file that is not one."""
    from rigctl.devices.onboard_finger import BoardRange

    if isinstance(training, BoardRange):
        return training
    from rigctl.encoding.params import EncodeParams
    from rigctl.storage.encoded import open_encoded

    try:
        with open_encoded(training) as f:
            norm, params = f.normalisation, EncodeParams.from_dict(f.parameters)
        return BoardRange.of(norm["taxel_min"], norm["taxel_max"], params.k_sa)
    except (OSError, ValueError, KeyError) as exc:
        raise RigError(f"the on-board encoder's range from {training}: {' '.join(str(exc).split())}") from None


def _hil_finger(request: RigRequest, motion: str, onboard: Any, options: dict[str, Any]) -> ScanSource:
    """``hil_finger``: the simulated operator's finger on the Uno encoder image under simavr
    (:class:`rigctl.simulation.hil_finger.HilFingerScans`), the board calibrated from ``onboard_encoder``."""
    from rigctl.core.handheld import ScanError
    from rigctl.simulation.hil import HilError
    from rigctl.simulation.hil_finger import HilFingerScans

    unknown = set(options) - {"timeout_s"}
    if motion != "sim" or onboard is None or unknown:
        raise RigError("the finger's board under simavr (hil_finger) runs the encoder image with the simulated "
                       "operator: motion 'sim', an onboard_encoder and no other option"
                       + (f" (got {', '.join(sorted(unknown))})" if unknown else ""))
    try:
        return HilFingerScans(board_range(onboard), seed=request.seed, rig_config=_config(request),
                              textures=request.textures, timeout_s=float(options.get("timeout_s", 60.0)))
    except (ScanError, HilError, OSError) as exc:
        raise RigError(f"cannot start the finger's board under simavr: {exc}") from None


def _tracked_scans(motion: str, request: RigRequest, options: dict[str, Any]) -> ScanSource:
    """``motion="lsl:NAME[@channels]"`` (a tracker stream, :class:`rigctl.simulation.handheld_lsl.LslTracker`; options
    ``resolve_s``, ``timeout_s``) or ``"serial:PORT"`` (a motion board, :class:`rigctl.devices.motion.SerialMotion`;
    options ``open_timeout_s``, ``timeout_s``), the plate axis from the rig config; the taxels from the finger's taxel
    board at option ``taxel_port``, else from the sensor model along the tracked path."""
    from rigctl.acquisition.handheld import plate_axis_from_config
    from rigctl.acquisition.rigconfig import load_rig_config
    from rigctl.core.handheld import ScanError, Tracker
    from rigctl.simulation.handheld_lsl import TrackedFingerScans

    lsl = motion.startswith("lsl:")
    known = {"timeout_s", "taxel_port", "onboard_encoder", *(("resolve_s", "motion_units") if lsl else ("open_timeout_s",))}
    unknown = set(options) - known
    if unknown:
        raise RigError(f"{'a tracker stream' if lsl else 'a serial motion board'} takes no option "
                       f"{', '.join(sorted(unknown))}")
    timeout_s = float(options.get("timeout_s", 60.0))
    taxel_port = options.get("taxel_port")
    tracker: Tracker
    try:
        if lsl:
            from rigctl.simulation.handheld_lsl import LslTracker, parse_motion

            axis = plate_axis_from_config(load_rig_config(request.host_config_path))
            name, channels = parse_motion(motion)
            tracker = LslTracker(name, channels, resolve_s=float(options.get("resolve_s", 5.0)),
                                 units=options.get("motion_units"))
        else:
            from rigctl.devices.motion import SerialMotion

            axis = None  # a motion board sends the position along the plate
            tracker = SerialMotion(motion.removeprefix("serial:"),
                                   open_timeout_s=float(options.get("open_timeout_s", 5.0)))
        if options.get("onboard_encoder") is not None:
            from rigctl.devices.onboard_finger import open_onboard_finger

            return open_onboard_finger(str(taxel_port), tracker, axis, board_range(options["onboard_encoder"]),
                                       textures=request.textures, timeout_s=timeout_s)
        if taxel_port is not None:
            from rigctl.devices.finger_board import open_finger_board

            return open_finger_board(str(taxel_port), tracker, axis, textures=request.textures, timeout_s=timeout_s)
        try:
            return TrackedFingerScans(tracker, axis, rig_config=_config(request), seed=request.seed,
                                      textures=request.textures, timeout_s=timeout_s)
        except BaseException:
            tracker.close()
            raise
    except (ScanError, ValueError) as exc:
        raise RigError(str(exc)) from None


def _sensor_backend(request: RigRequest, source: SampleSource, drum: str) -> RigBackend:
    """A sensor-only plugin's samples streamed by a simulated rig's taxel board, the drum simulated (``drum``: "sim"
    on ptys in real time, "inprocess" on a simulated clock); the backend's mode is the plugin's name."""
    textures = request.textures or getattr(source, "textures", None)
    if drum == "inprocess":
        from rigctl.simulation.inprocess import InProcessBackend

        backend: Any = InProcessBackend(_config(request), seed=request.seed, textures=textures, source=source)
    else:
        from rigctl.simulation.backend import PtyRigBackend
        from rigctl.simulation.rig import SimulatedRig

        # paced whatever RIGCTL_SIM_PACE says: a plugin's source may be a live device, which keeps the wall clock's
        # time (an unpaced world asked a 200-lines-a-second pty board for its samples faster than it had them, and
        # every trial of the my-hardware guide's quick check failed, the stream stalled), as an lsl: replay does
        sim = SimulatedRig(_config(request), seed=request.seed, source=source, paced=True)
        backend = PtyRigBackend(sim, mode="sim", seed=request.seed, textures=textures,
                                drum_timeout_s=ANSWER_TIMEOUT_S["sim"], drum_watchdog_ms=WATCHDOG_MS["sim"])
    backend.mode = request.name
    return backend


def build_rig(kind: str, request: RigRequest | None = None) -> RigParts:
    """What the factory of rig ``kind`` makes of ``request`` (default: no options): a backend (not started), a
    sample source or a scan source (:mod:`rigctl.core.rig_plugins`). Raises RigError for an unknown rig, a plugin
    that does not load or refuses its options, or what it returns is none of those."""
    request = request or RigRequest(kind)
    try:
        factory = load_rig_factory(kind)
    except RigPluginError as exc:
        raise RigError(str(exc)) from None
    try:
        made = factory(request)
    except RigOptionError as exc:
        raise RigError(str(exc)) from None
    if not isinstance(made, RigBackend | SampleSource | ScanSource):
        raise RigError(f"the {kind} rig's factory returned a {type(made).__name__}: neither a RigBackend, a "
                       "SampleSource nor a ScanSource (rigctl.core.rig_plugins)")
    return made


def _request(kind: str, *, config: Any = None, seed: int = 0, prompt: Callable[[str], Any] | None = None,
             textures: TextureSet | None = None, host_config_path: str | os.PathLike | None = None,
             **options: Any) -> RigRequest:
    return RigRequest(kind, options, seed=seed, config=config, prompt=prompt, textures=textures,
                      host_config_path=None if host_config_path is None else str(host_config_path))


def _as_backend(made: RigParts, request: RigRequest, drum: str | None) -> RigBackend:
    """The backend of what a factory made: a backend as is, a sample source on the simulated ``drum``; RigError
    for a scan source (a handheld rig: :func:`open_rig`) or a ``drum`` for a rig that has its own."""
    if drum is not None and drum not in SENSOR_DRUMS:
        raise RigError(f"drum={drum!r}: a sensor-only rig runs on the simulated drum {' or '.join(SENSOR_DRUMS)}")
    if isinstance(made, RigBackend):
        if drum is not None:
            raise RigError(f"the {request.name} rig has its own drum: drum= is for sensor-only rigs")
        return _identified(made, request.name, made)
    if isinstance(made, SampleSource):
        return _identified(_sensor_backend(request, made, drum or "sim"), request.name, made)
    made.close()
    raise RigError(f"the {request.name} rig is a handheld rig (no drum): open it with open_rig({request.name!r})")


def plugin_identity(kind: str, made: object) -> dict[str, Any] | None:
    """What a session records of a plugin's rig (``rig_config["plugin"]`` and the provenance's ``rig.plugin``): the
    rig's name, entry point, distribution and version, and what its backend or sample source's ``describe()`` says
    (``{"error": ...}`` when it raises); None for rigctl's own rigs."""
    entry = rig_entries().get(kind)
    if entry is None or entry.builtin:
        return None
    described: Any = None
    describe = getattr(made, "describe", None)
    if callable(describe):
        try:
            described = describe()
        except Exception as exc:  # noqa: BLE001 - a plugin's describe() failing is recorded, never fatal
            described = {"error": describe_error(exc)}
    return {"name": entry.name, "target": entry.target, "distribution": entry.distribution,
            "version": entry.version, "describe": described}


def _identified(backend: RigBackend, kind: str, made: object) -> RigBackend:
    """``backend`` with a plugin's identity (:func:`plugin_identity`) as its ``plugin`` attribute, which
    :meth:`rigctl.acquisition.rig.Rig.describe` stores (the session's rig_config and provenance)."""
    identity = plugin_identity(kind, made)
    if identity is not None:
        backend.plugin = identity  # type: ignore[attr-defined]  # a plain attribute any backend may carry
    return backend


def make_backend(kind: str = "sim", *, drum: str | None = None, **options: Any) -> RigBackend:
    """The backend of rig ``kind`` (not started): the entry point of that name in the group ``rigctl.rigs``
    (:mod:`rigctl.core.rig_plugins`) called with the options (``config``, ``seed``, ``prompt``, ``textures``,
    ``host_config_path`` and the rig's own); a sensor-only plugin's samples on the simulated ``drum`` ("sim",
    default, or "inprocess"). A plugin's identity (:func:`plugin_identity`) is kept as the backend's ``plugin``.
    Raises RigError for an unknown rig, a plugin that does not load or missing options."""
    request = _request(kind, **options)
    return _as_backend(build_rig(kind, request), request, drum)


def fault_refusal(kind: str, spec: FaultSpec) -> str | None:
    """Why a rig of ``kind`` cannot inject ``spec``, known before anything is built (None: it can, or only its
    backend can tell: the firmware under simavr, checked when it opens). The CLI refuses with it (exit 2)."""
    if kind == "hardware":
        return "the hardware rig injects no faults (only the simulated rigs: --sim, --inprocess, --hil)"
    if kind in ("sim", "replay", "inprocess"):
        from rigctl.simulation.faults import model_fault_refusal

        return model_fault_refusal(spec)
    return None


def open_rig(kind: str = "sim", *, prompt: Callable[[str], Any] | None = None,
             host_config_path: str | os.PathLike | None = None, refuse_fault: bool = True,
             inject: Sequence[FaultSpec | str] = (), allow_firmware_mismatch: bool = False, **options: Any) -> Rig:
    """Open rig ``kind`` (an installed rig's name: "sim" | "hil" | "hardware" | "replay" | "inprocess" | "handheld"
    or a plugin's, :func:`rigctl.core.rig_plugins.rig_names`) and start its taxel stream.

    Parameters
    ----------
    kind : the rig (see the module docstring).
    prompt : operator prompt for plate changes on hardware (default: a terminal prompt).
    host_config_path : the rig config file (calibration; default ``$RIGCTL_CONFIG`` or ``~/.config/rigctl/rig.json``).
    refuse_fault : a fault the controller latches at open fails it (:class:`rigctl.acquisition.rig.FaultAtOpen`);
        False keeps it latched for the operator to acknowledge. Opening never moves anything and never acknowledges
        (docs/safety.md): the first start (a press, a run's first trial) HOMEs and TAREs.
    inject : faults to inject (:mod:`rigctl.core.faults`: :class:`FaultSpec` s or ``"estop@3+2"`` texts), timed on
        the rig's clock from the moment it is open; every one is checked against the backend before it starts.
    allow_firmware_mismatch : open boards whose firmware build differs from the installed sources' (a warning);
        default: :class:`rigctl.acquisition.rig.FirmwareMismatch` (a RigError) naming both builds.
    **options : the rig's options: ``config``, ``seed``, ``textures`` (the rig's default texture set), ``source``
        (replay), ``drum_port``/``taxel_port`` (hardware), ``motion`` (handheld), ``drum`` (a sensor-only plugin's
        simulated drum), ``hx711_rate_sps`` (the simulated rigs: their HX711's rate, 10 or 80 SPS; default the rig
        config's ``force_loop.hx711_rate_sps`` when no ``config`` is given, else the model's), and the rig's own
        keywords (a plugin's ``--rig-option`` s).

    Returns
    -------
    Rig, open and streaming (a context manager: ``with open_rig("inprocess") as rig: ...``).

    Raises
    ------
    RigError
        Unknown rig, a plugin that does not load, missing options, or the backend could not be started / the boards
        do not answer.
    rigctl.core.faults.FaultSpecError
        A malformed ``inject`` text, or a fault this rig cannot model (before anything starts).
    """
    faults = tuple(f if isinstance(f, FaultSpec) else parse_fault(f) for f in inject)
    drum = options.pop("drum", None)
    chosen_rate = options.pop("hx711_rate_sps", None)
    _simulated_hx711(kind, options, chosen_rate, host_config_path)
    request = _request(kind, prompt=prompt, host_config_path=host_config_path, **options)
    made = build_rig(kind, request)
    if isinstance(made, ScanSource) and not isinstance(made, RigBackend):
        if faults or drum is not None:
            made.close()
            raise RigError(f"the {kind} rig models no injected fault (--inject): the simulated drum rigs do"
                           if faults else f"the {kind} rig is a handheld rig: it has no drum (drum=)")
        return _handheld(made, request)
    backend = _as_backend(made, request, drum)
    check_faults(backend, faults, kind=kind)
    # FAULT@0 is wired that way from power-on: armed before the rig opens, the controller powered on with it (all
    # the run's fault times then count from that power-on)
    power_on = bool(faults) and any(f.at_power_on for f in faults) and isinstance(backend, FaultInjector)
    if power_on and isinstance(backend, FaultInjector):
        backend.inject_faults(faults, power_on=True)
    rig = Rig.connect(backend, prompt=prompt, host_config_path=request.host_config_path, refuse_fault=refuse_fault,
                      allow_firmware_mismatch=allow_firmware_mismatch, hx711_rate_sps=chosen_rate)
    truth_start = getattr(getattr(backend, "sim", None), "truth_start", None)
    if truth_start is not None:  # the truth log's time 0: the run's start, as the faults'
        truth_start()
    if faults and not power_on and isinstance(backend, FaultInjector):
        backend.inject_faults(faults)
    return rig


#: the rigs whose HX711 is simulated: their rate is chosen (``hx711_rate_sps``) or the rig config's
SIMULATED_HX711 = ("sim", "hil", "inprocess", "replay")


def _simulated_hx711(kind: str, options: dict[str, Any], rate: int | None, host_config_path: Any) -> None:
    """The simulated HX711's rate into ``options["config"]`` (docs/config.md, ``--hx711-rate``): ``rate`` (10 or 80)
    if given, else the rig config's ``force_loop.hx711_rate_sps`` (the board the rig config is for) unless the caller
    gave a model ``config`` of its own. RigError for a rate on a rig whose HX711 is real, or not 10/80."""
    if rate is not None and kind not in SIMULATED_HX711:
        raise RigError(f"hx711_rate_sps chooses a simulated HX711's rate, not the {kind} rig's (its RATE pin)")
    if kind not in SIMULATED_HX711 or (rate is None and options.get("config") is not None):
        return
    if rate is None:
        from rigctl.acquisition.rigconfig import CalibrationError, load_rig_config

        try:  # (an invalid file is refused, naming it, when the rig opens)
            rate = (load_rig_config(host_config_path).get("force_loop") or {}).get("hx711_rate_sps")
        except (CalibrationError, OSError):
            rate = None
        if rate is None:
            return
    if int(rate) not in (10, 80):
        raise RigError(f"the HX711 runs at 10 or 80 samples/s, got {rate}")
    from rigctl.simulation.model import RigConfig

    config = options.get("config") or RigConfig()
    options["config"] = dataclasses.replace(config, mechanics=dataclasses.replace(config.mechanics,
                                                                                  hx711_rate_sps=float(rate)))


def _handheld(source: ScanSource, request: RigRequest) -> Rig:
    """The handheld rig (:class:`rigctl.acquisition.handheld.HandheldRig`) on ``source``: a source that can touch
    the plate's two ends (the simulated operator) calibrates the plate's axis from them, the others take it from the
    rig config; a source's own texture set (a replayed session's) unless the request names one; mode
    "handheld-replay" for a replayed handheld session, else the rig's name."""
    from rigctl.acquisition.handheld import HandheldRig
    from rigctl.core.handheld import PlateAxis

    touch_ends = getattr(source, "touch_ends", None)
    axis = PlateAxis.from_touches(*touch_ends()) if callable(touch_ends) else None
    replayed = request.name == "handheld" and str(request.options.get("motion", "")).startswith("replay:")
    return HandheldRig(source, axis=axis, prompt=request.prompt,
                       textures=request.textures or getattr(source, "textures", None),
                       host_config_path=request.host_config_path, mode="handheld-replay" if replayed else request.name)


def open_handheld(*, prompt: Callable[[str], Any] | None = None, host_config_path: str | os.PathLike | None = None,
                  home: bool = True, **options: Any) -> Rig:
    """Open the built-in handheld rig (:func:`handheld_rig`: ``motion="sim"``, the simulated operator, the plate's
    axis calibrated from its simulated touches of the plate's two ends; ``motion="lsl:NAME[@channels]"``, a tracker
    stream, the plate axis from the rig config, options ``resolve_s``, ``timeout_s``; ``motion="replay:S.h5"``, a
    recorded handheld session's scans as recorded). ``home`` is ignored (no actuator). Raises RigError for an unknown
    motion source or unusable options."""
    return open_rig("handheld", prompt=prompt, host_config_path=host_config_path, **options)
