"""``rigctl acquire``: run an acquisition protocol on the rig and record a session file."""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as _dt
import logging
import re
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import click

from rigctl.cli.interrupts import stop_on_sigterm
from rigctl.cli.outputs import HDF5_SUFFIXES, UsageProblem, check_output
from rigctl.cli.progress import bars, progress_option, show_bars
from rigctl.cli.protocols import PROTOCOL
from rigctl.cli.ranges import SEED
from rigctl.cli.rig_flags import (
    allow_firmware_mismatch_option,
    check_one_rig,
    check_rig_flags,
    check_truth_log,
    drum_port_option,
    hil_bootloaders_option,
    hx711_rate_option,
    inject_option,
    inprocess_option,
    lsl_wait_option,
    rig_option,
    rig_options_option,
    truth_log_option,
)


class ReplaySource(click.ParamType):
    """``--replay``: an existing recording (a path), or ``lsl:NAME`` (a live LSL stream, kept as text)."""

    name = "RECORDING|lsl:NAME"

    def convert(self, value, param, ctx):
        if isinstance(value, str) and value.startswith("lsl:"):
            if len(value) == 4:
                self.fail("lsl: needs a stream name or source id (lsl:NAME)", param, ctx)
            return value
        return click.Path(exists=True, path_type=Path).convert(value, param, ctx)


REPLAY = ReplaySource()


class MotionSource(click.ParamType):
    """``--motion``: ``sim``, ``lsl:NAME`` (a tracker stream) or ``serial:PORT`` (a motion board)."""

    name = "sim|lsl:NAME|serial:PORT"

    def convert(self, value, param, ctx):
        text = str(value)
        if text == "sim" or (text.startswith("lsl:") and len(text) > 4) or (text.startswith("serial:") and len(text) > 7):
            return text
        self.fail(f"{text!r}: give sim (the simulated operator), lsl:NAME (a tracker stream) or serial:PORT (a "
                  "motion board)", param, ctx)


MOTION = MotionSource()

#: --plates choices (see the option's help)
PLATE_POLICIES = ("prompt", "auto", "skip")


def _check_flags(f: dict[str, Any]) -> None:
    """The command line's combinations that are usage errors (exit 2), before anything opens."""
    _check_ports(f["drum_port"], f["taxel_port"], handheld=f["handheld"], motion=f["motion"])
    check_one_rig(sim=f["sim"], hil=f["hil"], inprocess=f["inprocess"], drum_port=f["drum_port"])
    check_rig_flags(f["rig"], f["rig_options"], others=bool(f["sim"] or f["hil"] or f["inprocess"] or f["drum_port"]
                                                            or f["replay"] or f["handheld"] or f["motion"]))
    replay, out = f["replay"], f["out"]
    if replay is not None and (f["hil"] or f["inprocess"] or f["drum_port"] is not None):
        raise click.UsageError("--replay streams a recording through the simulated rig: drop --hil/--inprocess/"
                               "--drum-port")
    if isinstance(replay, Path) and Path(out).resolve() == replay.resolve():
        raise click.UsageError(f"--out {out} is the recording being replayed: choose another output file")
    if f["resume"] and f["overwrite"]:
        raise click.UsageError("--resume and --overwrite exclude each other")
    if f["ack"] is not None and not f["ack"].strip():
        raise click.UsageError("--ack takes the reason the fault may be cleared (logged), e.g. --ack \"e-stop "
                               "released, bench checked\"")


def _load_protocol(protocol: Any, seed: int | None, trials_per_condition: int | None) -> Any:
    """The protocol (TOML or Python plan) with --seed and --trials-per-condition applied; UsageProblem (exit 2)."""
    from rigctl.acquisition.protocol import Protocol, ProtocolError, load_protocol

    try:
        proto = load_protocol(protocol)
    except ProtocolError as exc:  # the command's argument: a usage error
        raise UsageProblem(str(exc)) from None
    if seed is not None and isinstance(proto, Protocol):
        proto = proto.with_seed(seed)
    if trials_per_condition is not None:
        if not isinstance(proto, Protocol):
            raise UsageProblem(f"--trials-per-condition: {protocol} is a Python plan; set its size in the script")
        proto = dataclasses.replace(proto, trials_per_condition=trials_per_condition)
    return proto


def confirm_on_the_terminal(message: str) -> None:
    """A live handheld operator's plate confirmation: the cue (``message``) is on the terminal already (the rig's
    ``prompt`` event); wait for Enter."""
    input(">>> press Enter once the finger is there ")


def plate_prompt(policy: str, *, hardware: bool, stdin_is_tty: bool,
                 echo: Callable[[str], Any] | None = None) -> Callable[[str], Any] | None:
    """The operator prompt ``prompt(message)`` of a ``--plates`` policy, handed to ``open_rig`` (and through it to
    the hardware backend's plate mounter and :meth:`rigctl.acquisition.rig.Rig.mount_texture`).

    - ``"prompt"``: None, i.e. the backend's terminal prompt (Enter confirms each plate change). On hardware without
      a terminal on stdin nobody could answer (every trial would fail): refused here, before the rig moves.
    - ``"auto"``: print the plate change (time-stamped, on stderr) and carry on without waiting.
    - ``"skip"``: carry on without a word: the trials run on whatever plate is mounted.

    On the simulated rigs the plates are mounted by the simulation and the policy changes nothing.

    Raises
    ------
    UsageProblem (exit 2) for ``"prompt"`` on hardware when stdin is not a terminal.
    """
    if policy not in PLATE_POLICIES:
        raise ValueError(f"plate policy must be one of {', '.join(PLATE_POLICIES)}, got {policy}")
    if policy == "prompt":
        if hardware and not stdin_is_tty:
            raise UsageProblem("plate changes are confirmed on the terminal, but stdin is not a terminal: run it in "
                               "a terminal, or pass --plates auto (announce each plate, do not wait) or --plates skip")
        return None
    if policy == "skip":
        return lambda message: None
    say = echo or (lambda text: click.echo(text, err=True))

    def announce(message: str) -> None:
        what = re.sub(r",? then confirm\.?$", ".", str(message).strip())  # nobody confirms: it does not wait
        say(f"[{_dt.datetime.now():%H:%M:%S}] plate change (--plates auto, not waiting): {what}")

    return announce


#: loggers held back while the rig opens: the rig facade's, and pymodbus' (it logs each retry of a silent port)
_HELD_LOGGERS = ("rigctl.acquisition.rig", "pymodbus.logging")


@contextlib.contextmanager
def _held_rig_warnings():
    """Hold back the log records of :data:`_HELD_LOGGERS` while the rig opens (yields the list they go to).

    A drum port that answers nothing fails the opening; pymodbus' retry messages and the three "STOP attempt
    failed" warnings of the clean-up that follows would only repeat that error. The caller re-emits them when the
    opening succeeds."""
    loggers = [logging.getLogger(name) for name in _HELD_LOGGERS]
    held: list[logging.LogRecord] = []

    def hold(record: logging.LogRecord) -> bool:
        held.append(record)
        return False

    for logger in loggers:
        logger.addFilter(hold)
    try:
        yield held
    finally:
        for logger in loggers:
            logger.removeFilter(hold)


def _recorded_before(out: Path, proto) -> int:
    """``--resume``: the trials ``out`` holds already, after checking it can be resumed with ``proto`` (refused before
    the rig moves, and the file let go at once: the run opens its own writer). A simulated rig goes on from its seed
    plus this count: one started again from the first run's seed would record that run's first trials again, byte for
    byte (the in-process rig is deterministic), which the trial validator rightly flags as copies. Raises
    click.ClickException when the file cannot be resumed (another protocol, not a session file, unreadable)."""
    from rigctl.storage.session import SessionError, SessionWriter

    try:
        check = SessionWriter.open(out, protocol_source=proto.source)
        try:
            return len(check.completed_ids())
        finally:
            check.close()
    except (SessionError, OSError) as exc:
        raise click.ClickException(str(exc)) from None


def _check_ports(drum_port: str | None, taxel_port: str | None, *, handheld: bool, motion: str | None) -> None:
    """Both hardware ports or neither; on the handheld rig ``--taxel-port`` alone is the finger's taxel board, beside
    a live motion source. Raises click.UsageError."""
    finger_board = taxel_port is not None and drum_port is None and (handheld or motion is not None)
    if (drum_port is None) != (taxel_port is None) and not finger_board:
        raise click.UsageError("give both --drum-port and --taxel-port (hardware), or neither (--sim); on the "
                               "handheld rig, --taxel-port alone is the finger's taxel board (with --motion lsl:NAME "
                               "or serial:PORT)")
    if finger_board and not str(motion).startswith(("lsl:", "serial:")):
        raise click.UsageError("--taxel-port on the handheld rig reads the finger's taxel board beside a live motion "
                               "source: give --motion lsl:NAME or serial:PORT")


def _handheld_rig(proto: Any, *, handheld: bool, motion: str | None, hil: bool, inprocess: bool, hardware: bool,
                  replay: Any, onboard: dict[str, Any]) -> bool:
    """Whether the run records on the handheld rig: a protocol with ``rig = "handheld"``, or ``--handheld`` /
    ``--motion``. Raises click.UsageError when the flags name another rig for a handheld protocol, or the handheld rig
    for a drum protocol, or ``--onboard-encoder``'s flags (``onboard``: :func:`_check_onboard`'s) do not fit."""
    wants = getattr(proto, "rig", "drum") == "handheld"
    on_board = bool(onboard.pop("onboard"))
    _check_onboard(on_board, handheld=wants, hil=hil, replay=replay, **onboard)
    hil = hil and not on_board  # --hil with --onboard-encoder: the finger's board under simavr
    asked = handheld or motion is not None
    if asked and not wants:
        raise click.UsageError(f"--handheld/--motion record on the handheld rig, but protocol {proto.name!r} is a drum "
                               "protocol (no rig = \"handheld\")")
    if wants and (hil or inprocess or hardware or isinstance(replay, str)):
        raise click.UsageError(f"protocol {proto.name!r} records on the handheld rig (an operator's scans): drop "
                               "--hil/--inprocess/--drum-port (--sim: the simulated operator; --motion lsl:NAME: a "
                               "tracker; --replay S.h5: a recorded handheld session)")
    if wants and replay is not None and motion is not None:
        raise click.UsageError("--replay replays a handheld session's scans, their motion included: drop --motion")
    return wants


def _check_onboard(onboard: bool, *, handheld: bool, classify: Path | None, variant: str, hil: bool,
                   taxel_port: str | None, replay: Any) -> None:
    """``--onboard-encoder``: a handheld run classifying speed-scaled features (--classify: the board is calibrated
    with its range) on the finger's board (--taxel-port) or on the image under simavr (--hil). Raises
    click.UsageError."""
    if not onboard:
        return
    if not handheld:
        raise click.UsageError("--onboard-encoder encodes handheld scans on the finger's board: the protocol must record "
                               "on the handheld rig")
    if classify is None:
        raise click.UsageError("--onboard-encoder calibrates the board with the classifier's range: give --classify")
    if variant != "realtime_speed_scaled":
        raise click.UsageError("--onboard-encoder gives the board's speed-scaled features: drop --classify-variant "
                               f"{variant}")
    if replay is not None or hil == (taxel_port is not None):
        raise click.UsageError("--onboard-encoder runs on the finger's taxel board: give --taxel-port PORT (with --motion "
                               "lsl:NAME or serial:PORT) or --hil (the board under simavr), one of them, no --replay")


def _scan_classifier(classify: Path | None, calibration: Path | None, variant: str, pcs: int, *,
                     handheld: bool, alignment: str = "statistics") -> Any:
    """The live classifier of ``--classify`` (None without it); its predictions are echoed as they come. Raises
    click.UsageError for --classify/--calibration without a handheld protocol or --calibration alone, UsageProblem for
    a file that is not an encoded training block."""
    if (classify is not None or calibration is not None) and not handheld:
        raise click.UsageError("--classify/--calibration classify handheld scans: the protocol must record on the "
                               "handheld rig")
    if calibration is not None and classify is None:
        raise click.UsageError("--calibration re-centres the --classify classifier: give --classify too")
    if classify is None:
        return None
    from rigctl.operations import ScanClassifier

    try:
        return ScanClassifier(classify, calibration=calibration, variant=variant, n_pcs=pcs, alignment=alignment,
                              on_prediction=lambda p: click.echo(p.line()))
    except (ValueError, OSError) as exc:  # a file that is not encoded: NotEncodedError, a ValueError
        raise UsageProblem(f"--classify: {' '.join(str(exc).split())}") from None


def _cues_on_the_terminal(control: Any, source: Any) -> None:
    """A handheld rig with a live motion source (a tracker, a motion board): each cue the rig gives its operator
    (the plate, then each scan's profile and go) is a line on stderr, from the rig's event stream (``prompt``
    events). The simulated operator and a replayed session need none (they follow the plan by themselves)."""
    motion = str(getattr(source, "motion", None) or "sim")
    if source.kind != "handheld" or motion == "sim" or motion.startswith("replay:"):
        return
    control.subscribe(lambda ev: click.echo(f"operator: {ev.message}", err=True) if ev.kind == "prompt" else None)


def _prediction_lines(classifier: Any, out: Path, replay: Any) -> list[str]:
    """The summary's lines on the live predictions (none without --classify): the score; the predictions are logged
    into the session; a replayed handheld session's are compared with those its recording logged."""
    from rigctl.storage.session import SessionError

    if classifier is None or not classifier.predictions:
        return []
    right = sum(p.correct for p in classifier.predictions)
    lines = [f"  predicted: {right}/{len(classifier.predictions)} scans correct ({100 * classifier.accuracy():.1f} "
             f"%, {classifier.variant}, {classifier.model.n_pcs} PCs, features: {classifier.model.alignment})"]
    if classifier.model.alignment_note:  # the session's scans sit outside the training's alignment
        lines.append(f"  WARNING: {classifier.model.alignment_note}")
    try:
        classifier.log_to(out)
        if isinstance(replay, Path):
            n, diffs = classifier.compare_recorded(replay)
            lines += ([f"  replay: {n - len(diffs)}/{n} predictions equal those of the recorded run"] if n else
                      [f"  replay: {replay} logged no predictions to compare (recorded without --classify)"])
            lines += [f"    {d}" for d in diffs]
    except (SessionError, OSError) as exc:
        lines.append(f"  the predictions were not logged in {out}: {' '.join(str(exc).split())}")
    return lines


def _rig_source(flags: dict[str, Any], truth_log: Path | None, hx711_rate: int | None = None) -> Any:
    """The :class:`rigctl.operations.RigSource` the flags select (:meth:`~rigctl.operations.RigSource.from_flags`),
    with ``--truth-log`` and ``--hx711-rate``; UsageProblem / click.UsageError (exit 2) for options a rig does not
    take."""
    from rigctl.operations import RigSource

    try:
        source = RigSource.from_flags(**flags)
        if hx711_rate is not None:
            source = dataclasses.replace(source, hx711_rate_sps=hx711_rate)
    except ValueError as exc:  # options for one of rigctl's own rigs, a name rigctl keeps
        raise UsageProblem(str(exc)) from None
    check_truth_log(truth_log, source.kind)
    if truth_log is not None:
        source = dataclasses.replace(source, truth_log=str(truth_log))
    return source


def _open_control(source: Any, *, prompt: Any, seed: int, config_path: Path | None, drum_port: str | None,
                  acknowledge: tuple[str, str] | None = None) -> Any:
    """Open the rig ``source`` names (:func:`rigctl.operations.open_control`), every failure as one line: a fault
    ``--inject`` cannot model is a usage error (exit 2), the rest a ClickException (a fault the controller still
    latches included, unless ``acknowledge``: the operator's ``--ack`` / ``--resume``); what the opening logged is
    shown once it succeeded."""
    from rigctl.acquisition.lsl import LslUnavailable
    from rigctl.core.faults import FaultSpecError
    from rigctl.devices.errors import DrumError, TaxelStreamError
    from rigctl.operations import FaultAtOpen, RigError, RigOpenError, open_control

    with _held_rig_warnings() as held:
        try:
            control = open_control(source, prompt=prompt, seed=seed, host_config_path=config_path,
                                   acknowledge=acknowledge)
        except FaultAtOpen as exc:  # shown and kept: opening never acknowledges
            raise click.ClickException(f"{exc}; nothing moved. Acknowledge it with --ack \"REASON\" (logged with "
                                       "your login name) once its cause is gone") from None
        except RigOpenError as exc:  # the port opened but the drum controller failed there
            stop = ("" if exc.stop_acknowledged
                    else "; STOP was not acknowledged either: if the drum may be moving, stop it by hand")
            hint = f"; check --drum-port {drum_port} (`rigctl ports` lists the boards)" if drum_port else ""
            raise click.ClickException(f"{exc}{hint}{stop}") from None
        except FaultSpecError as exc:  # --inject names a fault this rig cannot model: refused before it opened
            raise UsageProblem(str(exc)) from None
        except (RigError, TaxelStreamError, OSError, ValueError, LslUnavailable) as exc:
            raise click.ClickException(" ".join(str(exc).split())) from None
        except DrumError as exc:  # HOME failed
            raise click.ClickException(f"cannot open the {source.kind} rig: {' '.join(str(exc).split())}") from None
    for record in held:  # the opening succeeded: what it logged is news
        logging.getLogger(record.name).handle(record)
    return control


def _bars_follow_the_rig(control: Any, progress: Any) -> None:
    """The bars follow the rig's event stream (``RigControl.subscribe``: the run publishes its progress there), as
    the GUI's and the server's views do. The CLI polls nothing: its run reads the controller, the process is the
    heartbeat (docs/safety.md)."""
    if progress is not None:
        control.subscribe(lambda ev: progress(ev.progress) if ev.progress is not None else None)


@click.command()
@click.argument("protocol", type=PROTOCOL)
@click.option("--out", "out", required=True, type=click.Path(dir_okay=False, writable=True, path_type=Path),
              help="Session file to write (HDF5, .h5).")
@click.option("--sim", "sim", is_flag=True, default=False, help="Use the simulated rig (the default).")
@click.option("--hil", is_flag=True, default=False, help="Use the real firmware under simavr (hardware in the loop).")
@hil_bootloaders_option
@inprocess_option
@drum_port_option
@click.option("--taxel-port", default=None,
              help="Serial port of the taxel streamer (Uno) on real hardware (with --drum-port); on the handheld rig "
                   "alone (with --motion lsl:NAME or serial:PORT): the finger's taxel board, its frames the trials' "
                   "taxels (docs/guides/handheld.md).")
@rig_option
@rig_options_option
@click.option("--replay", "replay", type=REPLAY, default=None,
              help="Simulated rig whose taxel board streams this recording (a session file, at its own layout and "
                   "rate, the trials of each plate the protocol mounts; or a FabricSlide folder) instead of the model; "
                   "or lsl:NAME: the live LSL stream NAME (name or source id; a lab's own taxel device, docs/lsl). "
                   "A handheld protocol replays a recorded handheld session's scans (taxels, tracker, boundaries): "
                   "with --classify, its predictions are compared with those the recording logged.")
@click.option("--handheld", is_flag=True, default=False,
              help="Use the handheld rig (the paper's real-time system: an operator scans flat plates with the finger; "
                   "a protocol with rig = \"handheld\" selects it anyway). Motion from the simulated operator unless "
                   "--motion says otherwise (docs/guides/handheld.md).")
@click.option("--motion", type=MOTION, default=None,
              help="The handheld rig's motion source: sim (the simulated operator, default), lsl:NAME (a tracker "
                   "stream's position channels, mm: x, y, z or one along the plate; velocity channels are not read) "
                   "or serial:PORT (a motion board's CRC-checked frames: an encoder or an IMU; "
                   "docs/guides/handheld.md).")
@click.option("--motion-units", "motion_units", type=click.Choice(["m", "mm"]), default=None,
              help="With --motion lsl:NAME: the unit of the stream's positions (Motive and Vicon bridges publish "
                   "metres). Default: the stream's own channel metadata (unit), else mm.")
@click.option("--classify", "classify", type=click.Path(exists=True, dir_okay=False, path_type=Path), default=None,
              help="Handheld rig: predict each scan's texture at its end with the classifier trained on this encoded "
                   "training block (rigctl encode of a handheld_training session; LDA on --pcs PCs of its real-time "
                   "speed-scaled features): one line per scan, and an LSL marker with --lsl.")
@click.option("--calibration", "calibration", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              default=None, help="With --classify: the encoded calibration block (handheld_calibration) whose mean "
                                 "feature vector re-centres the classifier (the paper's calibration).")
@click.option("--classify-variant", "classify_variant", type=click.Choice(["realtime_speed_scaled", "realtime_original"]),
              default="realtime_speed_scaled", show_default=True,
              help="With --classify: the features classified (Speed Scaled: the paper's system; Original: without the "
                   "speed invariance module).")
@click.option("--classify-alignment", "classify_alignment", type=click.Choice(["statistics", "none", "session"]),
              default="statistics", show_default=True,
              help="With --classify: statistics: each taxel's mean, spread and change over the scan's windows (does "
                   "not depend on where on the plate the scan was cut: a calibration touch a few mm off, a re-strapped "
                   "tracker; docs/results.md 3b); none: the paper's classifier on the windows themselves; session: "
                   "the windows shifted by the calibration block's measured shift.")
@click.option("--onboard-encoder", "onboard_encoder", is_flag=True, default=False,
              help="Handheld rig with --classify: the finger's taxel board runs the encoder image (uno_encoder) and "
                   "encodes each scan itself, calibrated with the --classify block's range: ARM at the cue (the board "
                   "keeps its last 32 samples), ENCODE from the finger's entry as the tracker shows it, the "
                   "tracker's velocity of each 100 ms window, FINISH at its end; the trials keep the board's "
                   "spikes and counts instead of raw taxels. With --taxel-port PORT (and --motion lsl:NAME or "
                   "serial:PORT), or --hil: the simulated operator's finger on the image under simavr "
                   "(docs/guides/handheld.md).")
@click.option("--pcs", "pcs", type=click.IntRange(1, 1000), default=25, show_default=True,
              help="With --classify: principal components of the classifier (the paper: 25).")
@click.option("--resume", is_flag=True, default=False,
              help="Continue an interrupted session file from its plan (same protocol; no trial recorded twice). "
                   "A latched fault that ended it is acknowledged by this command (logged with your login name), "
                   "and the run goes on.")
@click.option("--ack", "ack", metavar="REASON", default=None,
              help="Acknowledge a fault the drum controller still latches when the rig opens (its cause gone: the "
                   "e-stop released), logged with your login name and REASON in the rig's log and the session; "
                   "without it such a fault ends the command (exit 1) before anything moves.")
@click.option("--overwrite", is_flag=True, default=False, help="Replace an existing --out file.")
@click.option("--seed", type=SEED, default=None,
              help="Seed of the simulated rig, and of a protocol's random trial order.")
@click.option("--trials-per-condition", "trials_per_condition", type=click.IntRange(1, 100_000), default=None,
              help="Override the TOML protocol's trials per condition (e.g. 1 for a first try of a long protocol); "
                   "give it again with --resume.")
@click.option("--on-failure", type=click.Choice(["continue", "stop"]), default="continue", show_default=True,
              help="What to do after a failed trial (timeout, fault).")
@click.option("--config", "config_path", type=click.Path(exists=True, dir_okay=False, path_type=Path), default=None,
              help="Rig config JSON (calibration); default $RIGCTL_CONFIG or ~/.config/rigctl/rig.json (used when "
                   "it exists).")
@click.option("--plates", type=click.Choice(PLATE_POLICIES), default="prompt", show_default=True,
              help="Plate changes on hardware and for a live handheld operator (--motion lsl:/serial:): prompt = ask "
                   "on the terminal and wait for Enter (refused when stdin "
                   "is not a terminal); auto = print 'plate change: mount texture plate X' with the time and carry "
                   "on without waiting (a plate changer, or an operator following the printed schedule); skip = "
                   "never ask: every trial runs on the plate already mounted and is labelled with the plan's texture "
                   "(one-texture protocols, dry runs). The simulated rigs mount their plates themselves.")
@click.option("--lsl/--no-lsl", "lsl", default=None,
              help="Publish the run on Lab Streaming Layer (taxels, SA/RA spikes, drum state, markers; docs/lsl.md); "
                   "default: the rig config's lsl.enabled, else off. Needs pylsl: pip install 'rigctl[lsl]'.")
@lsl_wait_option
@inject_option
@hx711_rate_option
@allow_firmware_mismatch_option
@truth_log_option
@progress_option
def acquire(protocol, out, sim, hil, hil_bootloaders, inprocess, drum_port, taxel_port, rig, rig_options, replay,
            handheld, motion, motion_units, classify,
            calibration, classify_variant, classify_alignment, onboard_encoder, pcs, resume, ack, overwrite, seed, trials_per_condition,
            on_failure, config_path,
            plates, lsl, lsl_wait_s,
            inject, hx711_rate, allow_firmware_mismatch, truth_log, progress):
    """Run PROTOCOL (a .toml protocol file or a .py script) and record every trial into --out.

    On the simulated rig by default. Ctrl-C stops cleanly (the rig is left safe, finished trials are kept);
    continue later with --resume. A latched fault (e-stop, over-force, reset, ...: docs/safety.md) stops the rig and
    ends the run, resumable; --resume is the operator's acknowledgement and the start (logged in the session with
    the fault it clears). A fault the controller still latches when the rig opens ends the command naming it (exit
    1), unless --ack REASON acknowledges it. Exit status: 0 when every planned trial is complete, 1 otherwise; 2 for
    a usage error (refused before the rig moves).
    """
    from rigctl.acquisition.lsl import LslUnavailable, require_pylsl
    from rigctl.acquisition.rigconfig import CalibrationError, load_rig_config
    from rigctl.acquisition.safety import operator_name
    from rigctl.operations import ProtocolRun, lsl_requested
    from rigctl.storage.session import SessionError

    hil = hil or hil_bootloaders
    _check_flags(dict(drum_port=drum_port, taxel_port=taxel_port, handheld=handheld, motion=motion, sim=sim, hil=hil,
                      inprocess=inprocess, rig=rig, rig_options=rig_options, replay=replay, out=out, resume=resume,
                      overwrite=overwrite, ack=ack))
    if resume and not out.exists():
        raise UsageProblem(f"--resume: {out} does not exist: nothing to resume")
    check_output(out, overwrite=overwrite or resume,
                 inputs=(protocol, replay if isinstance(replay, Path) else None, config_path), suffixes=HDF5_SUFFIXES,
                 overwrite_hint="continue it with --resume, or pass --overwrite", kind="session")
    hardware = drum_port is not None
    if inject and hardware:
        raise click.UsageError("--inject works on the simulated rigs (--sim, --inprocess, --hil), not on hardware")
    try:  # the rig config is read again when the rig opens; a bad one is refused here, before anything starts
        host_config = load_rig_config(config_path)
    except CalibrationError as exc:
        if config_path is not None:
            raise UsageProblem(f"--config {exc}") from None
        raise click.ClickException(f"{exc} (fix it, or give another file with --config)") from None
    publish = lsl_requested(lsl, host_config)
    if publish:  # before the rig moves
        try:
            require_pylsl()
        except LslUnavailable as exc:
            raise click.ClickException(f"{exc}{'' if lsl else ' (asked for by the rig config: lsl.enabled)'}") from None
    proto = _load_protocol(protocol, seed, trials_per_condition)
    handheld = _handheld_rig(proto, handheld=handheld, motion=motion, hil=hil, inprocess=inprocess, hardware=hardware,
                             replay=replay, onboard=dict(onboard=onboard_encoder, classify=classify,
                                                         variant=classify_variant, taxel_port=taxel_port))
    # a person at the plates: the drum rig's hardware, or a live handheld operator (a tracker, a motion board), whose
    # plate cue says "then confirm" and waits for Enter on the terminal (--plates prompt) like a drum's plate change
    live_operator = handheld and motion is not None and motion.startswith(("lsl:", "serial:"))
    prompt = plate_prompt(plates, hardware=hardware or live_operator, stdin_is_tty=sys.stdin.isatty())
    plate_confirm = None
    if live_operator:  # the handheld rig's cues reach the terminal as events (_cues_on_the_terminal); only the
        # plate cue waits, and only under --plates prompt (auto and skip: the cue is printed and the run goes on)
        plate_confirm, prompt = (confirm_on_the_terminal if plates == "prompt" else None), None
    classifier = _scan_classifier(classify, calibration, classify_variant, pcs, handheld=handheld,
                                  alignment=classify_alignment)
    if hardware and plates == "skip":
        with contextlib.suppress(Exception):  # a note only; the runner reports a plan it cannot build
            labels = sorted({str(t.texture) for t in proto.plan()})
            if len(labels) > 1:
                click.echo(f"note: --plates skip: the plan's {len(labels)} textures ({', '.join(labels[:8])}"
                           f"{' ...' if len(labels) > 8 else ''}) are all recorded on the plate already mounted, "
                           "each trial labelled with the plan's texture", err=True)
    rig_seed = (0 if seed is None else seed) + (_recorded_before(out, proto) if resume else 0)

    # SIGTERM (e.g. a service manager) stops like Ctrl-C: clean stop, rig left safe
    stop_on_sigterm()
    source = _rig_source(dict(hil=hil, drum_port=drum_port, taxel_port=taxel_port, replay=replay,
                              bootloaders=hil_bootloaders, inprocess=inprocess, inject=inject, handheld=handheld,
                              motion=motion, allow_firmware_mismatch=allow_firmware_mismatch, rig=rig,
                              options=rig_options, onboard_encoder=str(classify) if onboard_encoder else None,
                              motion_units=motion_units), truth_log,
                         hx711_rate)
    # the operator at this terminal acknowledges at open: --ack REASON, or --resume (acknowledge and go on)
    acknowledge = ((ack.strip(), operator_name()) if ack is not None
                   else ("rigctl acquire --resume", operator_name()) if resume else None)
    control = _open_control(source, prompt=prompt, seed=rig_seed, config_path=config_path, drum_port=drum_port,
                            acknowledge=acknowledge)
    with control, bars(show_bars(progress)) as progress:
        _bars_follow_the_rig(control, progress)
        _cues_on_the_terminal(control, source)
        try:  # in this thread: Ctrl-C and SIGTERM stop the run cleanly
            # a latched fault ends the run (nobody here can acknowledge it mid-run); --resume is the acknowledgement
            run = ProtocolRun(control, proto, out, resume=resume, on_failure=on_failure, prompt=plate_confirm,
                              overwrite=overwrite, lsl=publish, on_trial=None if classifier is None else classifier.on_trial,
                              on_latch="end", acknowledge=acknowledge or ("rigctl acquire --resume",
                                                                           operator_name()))
            if run.lsl is not None:
                run.lsl.wait_s = lsl_wait_s  # --lsl-wait: run_start waits for a recorder
            if classifier is not None:
                classifier.lsl = run.lsl
            summary = run.run()
        except (SessionError, FileExistsError, FileNotFoundError, ValueError, LslUnavailable) as exc:
            raise click.ClickException(str(exc)) from None
    for line in summary.lines() + _prediction_lines(classifier, out, replay if handheld else None):
        click.echo(line)
    sys.exit(0 if summary.ok else 1)
