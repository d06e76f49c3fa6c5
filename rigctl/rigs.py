"""The composition root: the one module that knows every rig backend.

:func:`open_rig` builds a :class:`rigctl.core.interfaces.RigBackend` of the kind asked for and opens a
:class:`rigctl.acquisition.rig.Rig` on it. The CLI (``rigctl acquire``, ``rigctl gui``), the GUI and the tests open
rigs here; nothing else imports the backends together (``rigctl.acquisition`` never imports ``rigctl.simulation``).

Kinds:

- ``"sim"``: the simulated rig (:class:`rigctl.simulation.rig.SimulatedRig`: physical model, virtual Mega and Uno
  on real ptys, real-time physics clock); options ``config`` (RigConfig), ``seed``.
- ``"replay"``: the simulated rig streaming recorded taxel signals instead of the model's sensor; option
  ``source``: a replay source object (with ``read(n)``), or a path: a session file
  (:class:`rigctl.simulation.replay.SessionReplay`: its own layout, rate and texture set, following the plates
  mounted) or a directory of FabricSlide CSV files (:class:`rigctl.simulation.replay.FabricSlideReplay`).
- ``"hil"``: the rig's firmware images under simavr (:class:`rigctl.simulation.hil.HilRig`); ``config``, ``seed``.
- ``"hardware"``: the real boards on ``drum_port`` and ``taxel_port`` (:class:`rigctl.devices.backend.SerialBackend`);
  plates mounted by the operator (``prompt``).
- ``"inprocess"``: the model and the controller logic in this process, on a simulated clock, no ptys
  (:class:`rigctl.simulation.inprocess.InProcessBackend`; fast unit tests of the runner and calibration).
- ``"handheld"``: the paper's real-time system, no drum: an operator scans flat plates with the finger
  (:class:`rigctl.acquisition.handheld.HandheldRig`); option ``motion``: ``"sim"`` (default: the simulated operator,
  :class:`rigctl.simulation.operator.SimulatedOperator`, on a simulated clock), ``"lsl:NAME"`` (a tracker stream),
  ``"replay:S.h5"`` (a recorded handheld session, :class:`rigctl.simulation.handheld_replay.SessionScans`);
  :func:`open_handheld`.

Common options: ``prompt`` (operator prompt), ``host_config_path`` (the rig config file), ``home`` (HOME the
actuator after opening), ``textures`` (the rig's default texture set).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from rigctl.acquisition.rig import Rig, RigError
from rigctl.core.faults import FaultInjector, FaultSpec, check_faults, parse_fault
from rigctl.core.interfaces import RIG_KINDS, RigBackend
from rigctl.core.textures import TextureSet

__all__ = ["KINDS", "ANSWER_TIMEOUT_S", "WATCHDOG_MS", "drum_answer_timeout_s", "fault_refusal", "open_rig", "open_handheld",
           "make_backend",
           "replay_source"]

#: the backends :func:`open_rig` knows (the one list: :data:`rigctl.core.interfaces.RIG_KINDS`)
KINDS = RIG_KINDS

#: how long the host's :class:`rigctl.devices.drum.DrumClient` waits for each Modbus answer, s, per backend. A real
#: Mega answers within milliseconds: 0.5 s, well inside the controller's default 1 s watchdog, so that a lost
#: request is retried before the watchdog trips. The simulated boards share the host's CPU: on a loaded 2-core
#: machine the virtual Mega (a thread of this process) answers up to seconds late, and the firmware under simavr runs
#: at 0.1-0.4 of real time (issue 10's loaded runs); their ptys lose nothing, so a longer wait costs only the time to
#: notice a board that is gone. The in-process backend calls the controller directly (no answer to wait for).
ANSWER_TIMEOUT_S = {"hardware": 0.5, "sim": 2.0, "replay": 2.0, "hil": 2.0}

#: WATCHDOG_MS the drum client writes when it opens, per backend (absent: the controller's default, 1000 ms). A lost
#: answer must be retried before the controller's host watchdog trips: on hardware the 0.5 s timeout is inside the
#: default 1 s. The firmware under simavr keeps its watchdog in simulated time, paced to the wall clock, while the
#: host waits ANSWER_TIMEOUT_S["hil"] = 2 s for a late answer (a host starved on a loaded machine: `rigctl doctor --hil`
#: tripped WATCHDOG at 120 mm/s once in two runs at load 9.5 on 2 cores): 5 s covers one such wait and its retry.
#: The virtual Mega of the simulated rigs (sim, replay) is the same case: it runs beside a host that waits
#: ANSWER_TIMEOUT_S["sim"] = 2 s, and with the 1 s default a host starved for a second on a loaded machine failed trials
#: with WATCHDOG (CI at load 12-16: test_sim_index_alignment, test_acq_faults, doctor --sim). A test that trips the
#: watchdog on purpose writes the register itself.
WATCHDOG_MS = {"sim": 5000, "replay": 5000, "hil": 5000}


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


def make_backend(kind: str = "sim", *, config: Any = None, seed: int = 0, source: Any = None,
                 drum_port: str | None = None, taxel_port: str | None = None,
                 prompt: Callable[[str], Any] | None = None, textures: TextureSet | None = None,
                 **options: Any) -> RigBackend:
    """The backend of ``kind`` (not started). Raises RigError for an unknown kind or missing options."""
    if kind == "hardware":
        if not drum_port or not taxel_port:
            raise RigError("the hardware rig needs both drum_port and taxel_port (--drum-port, --taxel-port)")
        from rigctl.devices.backend import SerialBackend

        return SerialBackend(drum_port, taxel_port, prompt=prompt, textures=textures,
                             drum_timeout_s=ANSWER_TIMEOUT_S[kind])
    if drum_port or taxel_port:
        raise RigError(f"drum_port/taxel_port select the hardware rig, not {kind!r}")
    if kind in ("sim", "replay"):
        from rigctl.simulation.backend import PtyRigBackend
        from rigctl.simulation.rig import SimulatedRig

        if kind == "replay":
            if source is None:
                raise RigError("the replay rig needs a source (a session file, a FabricSlide directory, or a source)")
            src = replay_source(source)
            textures = textures or getattr(src, "textures", None)  # a session replays with its own texture set
            sim = SimulatedRig(config, seed=seed, source=src, **options)
        else:
            if source is not None:
                raise RigError("a replay source selects kind='replay'")
            sim = SimulatedRig(config, seed=seed, **options)
        return PtyRigBackend(sim, mode=kind, seed=seed, textures=textures, drum_timeout_s=ANSWER_TIMEOUT_S[kind],
                             drum_watchdog_ms=WATCHDOG_MS[kind])
    if kind == "hil":
        try:
            from rigctl.simulation.hil import HilRig
        except ImportError as exc:
            raise RigError(f"the HIL rig needs rigctl.simulation.hil (the firmware under simavr): {exc}") from exc
        from rigctl.simulation.backend import PtyRigBackend

        return PtyRigBackend(HilRig(config, seed=seed, **options), mode="hil", seed=seed, textures=textures,
                             drum_timeout_s=ANSWER_TIMEOUT_S[kind], drum_watchdog_ms=WATCHDOG_MS[kind])
    if kind == "inprocess":
        from rigctl.simulation.inprocess import InProcessBackend

        return InProcessBackend(config, seed=seed, textures=textures, **options)
    raise RigError(f"unknown rig kind {kind!r}; choose one of {', '.join(KINDS)}")


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
             host_config_path: str | os.PathLike | None = None, home: bool = True,
             inject: Sequence[FaultSpec | str] = (), allow_firmware_mismatch: bool = False, **options: Any) -> Rig:
    """Open a rig of ``kind`` ("sim" | "hil" | "hardware" | "replay" | "inprocess" | "handheld") and start its
    taxel stream.

    Parameters
    ----------
    kind : the backend (see the module docstring).
    prompt : operator prompt for plate changes on hardware (default: a terminal prompt).
    host_config_path : the rig config file (calibration; default ``$RIGCTL_CONFIG`` or ``~/.config/rigctl/rig.json``).
    home : HOME the actuator after opening (clearing a latched fault first); False leaves a fault latched.
    inject : faults to inject (:mod:`rigctl.core.faults`: :class:`FaultSpec` s or ``"estop@3+2"`` texts), timed on
        the rig's clock from the moment it is open; every one is checked against the backend before it starts.
    allow_firmware_mismatch : open boards whose firmware build differs from the installed sources' (a warning);
        default: :class:`rigctl.acquisition.rig.FirmwareMismatch` (a RigError) naming both builds.
    **options : the backend's options: ``config``, ``seed``, ``source`` (replay), ``drum_port``/``taxel_port``
        (hardware), ``textures`` (the rig's default texture set), and backend-specific keywords.

    Returns
    -------
    Rig, open and streaming (a context manager: ``with open_rig("inprocess") as rig: ...``).

    Raises
    ------
    RigError
        Unknown kind, missing options, or the backend could not be started / the boards do not answer.
    rigctl.core.faults.FaultSpecError
        A malformed ``inject`` text, or a fault this rig cannot model (before anything starts).
    """
    faults = tuple(f if isinstance(f, FaultSpec) else parse_fault(f) for f in inject)
    if kind == "handheld":
        if faults:
            raise RigError("the handheld rig models no injected fault (--inject): the simulated drum rigs do")
        return open_handheld(prompt=prompt, host_config_path=host_config_path, **options)
    backend = make_backend(kind, prompt=prompt, **options)
    check_faults(backend, faults, kind=kind)
    rig = Rig.connect(backend, prompt=prompt, host_config_path=None if host_config_path is None
                      else str(host_config_path), home=home, allow_firmware_mismatch=allow_firmware_mismatch)
    truth_start = getattr(getattr(backend, "sim", None), "truth_start", None)
    if truth_start is not None:  # the truth log's time 0: the run's start, as the faults'
        truth_start()
    if faults and isinstance(backend, FaultInjector):
        backend.inject_faults(faults)
    return rig


def open_handheld(*, motion: str = "sim", prompt: Callable[[str], Any] | None = None,
                  host_config_path: str | os.PathLike | None = None, config: Any = None, seed: int = 0,
                  textures: TextureSet | None = None, home: bool = True, **options: Any) -> Rig:
    """Open the handheld rig (:class:`rigctl.acquisition.handheld.HandheldRig`): its scans come from the simulated
    operator (``motion="sim"``: the plate's axis calibrated from its simulated touches of the plate's two ends) or a
    tracker's LSL stream (``motion="lsl:NAME[@channels]"``, :func:`rigctl.simulation.handheld_lsl.open_lsl_scans`:
    the plate axis from the rig config; options ``resolve_s``, ``timeout_s``) or a recorded handheld session
    (``motion="replay:S.h5"``: its scans as recorded, :class:`rigctl.simulation.handheld_replay.SessionScans`).
    ``home`` is ignored (no actuator). Raises RigError for an unknown motion source or unusable options."""
    from rigctl.acquisition.handheld import HandheldRig
    from rigctl.core.handheld import PlateAxis

    path = None if host_config_path is None else str(host_config_path)
    if motion == "sim":
        from rigctl.simulation.operator import SimulatedOperator

        if options:
            raise RigError(f"the simulated operator takes no option {', '.join(sorted(options))}")
        op = SimulatedOperator(seed=seed, rig_config=config, textures=textures)
        return HandheldRig(op, axis=PlateAxis.from_touches(*op.touch_ends()), prompt=prompt, textures=textures, host_config_path=path)
    if str(motion).startswith("lsl:"):
        from rigctl.acquisition.handheld import plate_axis_from_config
        from rigctl.acquisition.rigconfig import load_rig_config
        from rigctl.core.handheld import ScanError
        from rigctl.simulation.handheld_lsl import open_lsl_scans

        try:
            config_axis = plate_axis_from_config(load_rig_config(path))
            source = open_lsl_scans(str(motion), axis=config_axis, config=config, seed=seed, textures=textures, **options)
        except (ScanError, ValueError) as exc:
            raise RigError(str(exc)) from None
        return HandheldRig(source, axis=config_axis, prompt=prompt, textures=textures, host_config_path=path)
    if str(motion).startswith("replay:"):
        from rigctl.simulation.handheld_replay import SessionScans

        if options:
            raise RigError(f"a replayed handheld session takes no option {', '.join(sorted(options))}")
        try:
            scans = SessionScans(str(motion).removeprefix("replay:"))
        except (OSError, RuntimeError, ValueError) as exc:  # ScanError, SessionError: RuntimeErrors
            raise RigError(f"cannot replay {str(motion).removeprefix('replay:')}: {exc}") from None
        return HandheldRig(scans, prompt=prompt, textures=textures or scans.textures, host_config_path=path,
                           mode="handheld-replay")
    raise RigError(f"unknown motion source {motion!r}: 'sim' (the simulated operator), 'lsl:NAME' (a tracker "
                   "stream) or 'replay:S.h5' (a recorded handheld session)")
