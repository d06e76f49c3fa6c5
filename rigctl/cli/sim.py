"""``rigctl sim``: start the simulated rig and print its two port paths; ``rigctl sim dataset`` (see sim_dataset)."""

from __future__ import annotations

import math
import re
import signal
import subprocess
import sys
import threading
from pathlib import Path

import click

from rigctl.cli import SuggestingGroup
from rigctl.cli.ranges import SEED, floats
from rigctl.cli.rig_flags import FAULT_FORMS, check_truth_log, parse_injections
from rigctl.core.faults import FAULTS, INSTANT_FAULTS

#: the lines ``rigctl sim`` prints for its two ports
PORT_LINE = re.compile(r"(drum|taxel) port:\s+(\S+)")


def start_sim_process(port_dir: str, *, texture: str = "A", seed: int = 0) -> tuple[subprocess.Popen, dict[str, str]]:
    """Run ``rigctl sim`` in a separate process and wait until it has printed its two ports.

    Returns the process (stdout/stderr piped, text) and ``{"drum": path, "taxel": path}``. Raises RuntimeError with
    the simulator's stderr if it exits before printing both ports. The caller terminates the process.
    """
    proc = subprocess.Popen(
        [sys.executable, "-c", "from rigctl.cli import main; main()", "sim", "--seed", str(seed), "--texture", texture,
         "--port-dir", str(port_dir)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    ports: dict[str, str] = {}
    assert proc.stdout is not None and proc.stderr is not None  # both piped
    while len(ports) < 2:
        line = proc.stdout.readline()
        if not line:
            proc.kill()
            raise RuntimeError(f"rigctl sim did not print its ports: {proc.stderr.read()}")
        m = PORT_LINE.match(line)
        if m:
            ports[m.group(1)] = m.group(2)
    return proc, ports


@click.group(cls=SuggestingGroup, invoke_without_command=True)
@click.option("--seed", type=SEED, default=0, show_default=True, help="Seed of the model's noise and drum angle.")
@click.option("--texture", default=None,
              help="Texture plate mounted on the drum: a label of the paper's A-P (default A), or of the replayed "
                   "session's texture set (default: none mounted, the session streams in plan order).")
@click.option("--replay", "replay_dir", type=click.Path(exists=True), default=None,
              help="Stream recorded signals from this directory (e.g. ../shared/data/fabricslide) or session file "
                   "instead of the model.")
@click.option("--port-dir", type=click.Path(file_okay=False, writable=True), default=None,
              help="Directory for the port links 'drum' and 'taxel' and the control socket 'control' (default: a "
                   "fresh temporary directory); one running simulated rig per directory.")
@click.option("--truth-log", "truth_log", type=click.Path(dir_okay=False, writable=True, path_type=Path), default=None,
              metavar="FILE",
              help="Write the physical model's ground truth to FILE while it runs (CSV: wall_time_s, Unix time; time_s "
                   "from the rig's start, the clock `rigctl sim inject` uses; true_force_g, actuator_mm, "
                   "drum_speed_mm_s, motor_mm (the actuator motor's own travel); >= 100 Hz, each row flushed: another "
                   "process may read it live). FILE must not "
                   "exist.")
@click.pass_context
def sim(ctx, seed, texture, replay_dir, port_dir, truth_log):
    """Start the simulated rig: a virtual drum controller (Modbus RTU) and taxel streamer on two serial ports.

    Prints the two port paths, then runs until Ctrl-C. Any client can talk to them, e.g.
    `mbpoll -m rtu -a 1 -b 500000 -P none -t 3 -r 1 -c 13 -1 DRUM_PORT`; the faces drive it as hardware
    (`--drum-port DIR/drum --taxel-port DIR/taxel`), and `rigctl sim inject --port-dir DIR FAULT@T[+D]` injects faults
    into it while they do.
    """
    if ctx.invoked_subcommand is not None:
        return
    check_truth_log(truth_log, "sim")
    from rigctl.core.textures import PAPER_TEXTURES, TextureSetError
    from rigctl.simulation.pty import PortDirBusy
    from rigctl.simulation.rig import SimulatedRig

    source = None
    if replay_dir:
        from rigctl.operations import RigError
        from rigctl.rigs import replay_source

        try:
            source = replay_source(replay_dir)
        except (RigError, OSError, ValueError) as exc:
            raise click.ClickException(str(exc)) from None
    textures = getattr(source, "textures", None) or PAPER_TEXTURES
    try:
        if texture is not None:
            texture = textures.resolve(texture)
        elif source is None:
            texture = "A"
    except TextureSetError as exc:
        raise click.BadParameter(str(exc), param_hint="--texture") from None
    stop = threading.Event()

    def on_signal(signum, frame):
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    try:
        rig = SimulatedRig(seed=seed, source=source, port_dir=port_dir, truth_log=truth_log)
    except PortDirBusy as exc:
        raise click.ClickException(str(exc)) from None
    except OSError as exc:
        raise click.BadParameter(f"cannot use {port_dir} for the port links ({exc.strerror or exc})",
                                 param_hint="--port-dir") from None
    with rig:
        control = None
        try:  # a Ctrl-C as soon as the ports are printed (before the wait) is a clean stop too
            if texture is not None:
                rig.set_texture(texture, textures)
            control = _control(rig)
            click.echo(f"drum port:  {rig.drum_port}   (Modbus RTU, 500000 8N1, device id 1)")
            click.echo(f"taxel port: {rig.taxel_port}   (taxel stream, 1000000 baud)")
            click.echo(f"faults:     rigctl sim inject --port-dir {rig.port_dir} FAULT@T[+D]")
            if truth_log is not None:
                click.echo(f"truth log:  {truth_log}")
            replaying = ", replaying " + replay_dir if replay_dir else ""
            click.echo(f"texture {texture or '(none: plan order)'}, seed {seed}{replaying}. Ctrl-C stops.")
            sys.stdout.flush()
            while not stop.wait(0.5):
                pass
        except KeyboardInterrupt:
            pass
        finally:
            if control is not None:
                control.close()
    click.echo("simulated rig stopped.")


def _control(rig):
    """The running rig's truth log started (its time 0: now) and its control socket served (``rigctl sim inject``)."""
    from rigctl.simulation.sim_control import ControlServer

    t0 = rig.model.time_s
    if rig.truth is not None:
        rig.truth.start(t0)
    return ControlServer(rig, rig.port_dir, now_s=lambda: rig.model.time_s - t0,
                         active=lambda: sorted(rig.faults.active - INSTANT_FAULTS))  # (an instant is never active)


@sim.command("inject")
@click.option("--port-dir", required=True, type=click.Path(file_okay=False),
              help="The port folder of the running `rigctl sim` (its --port-dir).")
@click.argument("faults", nargs=-1, required=True, metavar="FAULT@T[+D]...", callback=parse_injections)
def inject(port_dir, faults):
    """Inject faults into the simulated rig running in --port-dir (`rigctl sim --port-dir DIR`): each FAULT starts T s
    from now on the rig's clock and lasts D s (no +D: to the rig's end), whatever face drives it; what each fault
    does and what clears it: docs/safety.md. FAULT is one of """
    from rigctl.simulation.sim_control import NoSimRunning, SimControlError, request

    try:
        answer = request(port_dir, {"inject": [str(f) for f in faults]})
    except NoSimRunning as exc:
        raise click.ClickException(str(exc)) from None
    except SimControlError as exc:
        if exc.usage:
            raise click.UsageError(str(exc)) from None
        raise click.ClickException(str(exc)) from None
    t0 = float(answer["time_s"])
    for spec in faults:
        ends = "" if math.isinf(spec.end_s) or spec.name in INSTANT_FAULTS else f", ends at {t0 + spec.end_s:.3f}"
        click.echo(f"armed {spec} in {port_dir}: starts at {t0 + spec.at_s:.3f}{ends} (time_s of the rig's clock)")


inject.help = (inject.help or "") + ", ".join(FAULT_FORMS.get(n, n) for n in FAULTS) + "."


try:  # the SIM-MODEL engineer's dataset generator
    from rigctl.cli.sim_dataset import dataset as _dataset
except ModuleNotFoundError as _exc:  # pragma: no cover - only while that module is missing
    if _exc.name != "rigctl.cli.sim_dataset":
        raise
else:
    sim.add_command(_dataset, "dataset")


@sim.command("operator")
@click.option("--lsl", "name", default=None, help="Name of the LSL tracker stream to publish (machine-local).")
@click.option("--serial", "serial_board", is_flag=True, default=False,
              help="Instead: a simulated serial motion board on a pty (prints its port; the frame of "
                   "docs/guides/handheld.md), the port `--motion serial:PORT` reads.")
@click.option("--fields", type=click.Choice(["position", "velocity", "both"]), default="both", show_default=True,
              help="With --serial: what the board sends (an encoder: position; an IMU: velocity).")
@click.option("--taxel-board", is_flag=True, default=False,
              help="With --lsl: also the finger's taxel board on a pty (prints its port; the 3x3 finger at 1 kHz, "
                   "the sensor model at the finger's place), the port `--taxel-port PORT` reads.")
@click.option("--seconds", type=floats(1.0, 86400.0), default=60.0, show_default=True,
              help="How long to play, s.")
@click.option("--seed", type=SEED, default=0, show_default=True, help="Seed of the operator and the tracker.")
def operator(name, serial_board, fields, taxel_board, seconds, seed):
    """Play the simulated operator in real time and publish its wrist tracker on LSL (x, y, z in the tracker's frame
    and the position along the plate, mm, at 90-120 Hz): the tracker stream `rigctl acquire ... --handheld --motion
    lsl:NAME@3` records from, with --taxel-board beside it the finger's taxel board on a pty (`--taxel-port PORT`);
    or, with --serial, as a serial motion board on a pty (`--motion serial:PORT`; docs/guides/handheld.md). Runs
    until --seconds or Ctrl-C."""
    from rigctl.core.lsl import LslUnavailable
    from rigctl.simulation.operator import publish_tracker

    if (name is None) == (not serial_board):
        raise click.UsageError("give --lsl NAME (an LSL tracker stream) or --serial (a motion board on a pty)")
    if taxel_board and serial_board:
        raise click.UsageError("--taxel-board goes with --lsl (the tracker stream it follows)")
    if serial_board:
        _serial_operator(fields, seconds, seed)
        return
    try:
        board = _finger_board(seed) if taxel_board else None
    except LslUnavailable as exc:
        raise click.ClickException(str(exc)) from None
    click.echo(f"publishing the simulated operator's tracker as LSL stream {name!r} for {seconds:g} s. Ctrl-C stops.")
    sys.stdout.flush()
    try:
        n = publish_tracker(name, seconds=seconds, seed=seed, on_scan=lambda text: click.echo(text),
                            on_pass=None if board is None else board.follow,
                            on_open=None if board is None else lambda: _say_port(board.path))
    except LslUnavailable as exc:
        raise click.ClickException(str(exc)) from None
    except KeyboardInterrupt:
        n = -1
    finally:
        if board is not None:
            board.close()
    click.echo("stopped." if n < 0 else f"done: {n} tracker samples published.")


def _finger_board(seed: int):
    """``--taxel-board``: the simulated finger's taxel board on a pty (its port is printed once the tracker stream is
    up: :func:`_say_port`). Raises LslUnavailable."""
    from rigctl.core.lsl import require_pylsl
    from rigctl.simulation.finger_board import SimulatedFingerBoard

    return SimulatedFingerBoard(clock=require_pylsl().local_clock, seed=seed)


def _say_port(path: str) -> None:
    """The line ``taxel port: PATH`` (as ``rigctl sim`` prints its ports), once the board and the tracker stream are
    both up: a script may start recording when it reads it."""
    click.echo(f"taxel port: {path}   (the finger's taxel board, 3x3 at 1 kHz: --taxel-port {path})")
    sys.stdout.flush()


def _serial_operator(fields: str, seconds: float, seed: int) -> None:
    """``rigctl sim operator --serial``: the simulated motion board until ``seconds`` or Ctrl-C."""
    import time

    from rigctl.simulation.motion_board import VirtualMotionBoard

    board = VirtualMotionBoard(seed=seed, fields=fields)
    click.echo(f"motion board (the simulated operator, {fields}) on {board.path} for {seconds:g} s: record with "
               f"--motion serial:{board.path} (it starts its stream when the port is opened, as DTR resets an "
               "Arduino). Ctrl-C stops.")
    sys.stdout.flush()
    try:
        time.sleep(seconds)
    except KeyboardInterrupt:
        pass
    finally:
        board.close()
    click.echo(f"done: {board.frames_sent} frames sent, {len(board.passes)} passes.")
