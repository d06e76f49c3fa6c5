"""``rigctl acquire``: run an acquisition protocol on the rig and record a session file."""

from __future__ import annotations

import signal
import sys
from pathlib import Path

import click


def _sigterm_as_interrupt(signum, frame):
    raise KeyboardInterrupt


@click.command()
@click.argument("protocol", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--out", "out", required=True, type=click.Path(dir_okay=False, path_type=Path),
              help="Session file to write (HDF5, .h5).")
@click.option("--sim", "sim", is_flag=True, default=False, help="Use the simulated rig (the default).")
@click.option("--hil", is_flag=True, default=False, help="Use the real firmware under simavr (hardware in the loop).")
@click.option("--drum-port", default=None, help="Serial port of the drum controller (Mega) on real hardware.")
@click.option("--taxel-port", default=None, help="Serial port of the taxel streamer (Uno) on real hardware.")
@click.option("--replay", "replay", type=click.Path(exists=True, path_type=Path), default=None,
              help="Simulated rig whose taxel board streams this recording (a session file, at its own layout and "
                   "rate, the trials of each plate the protocol mounts; or a FabricSlide folder) instead of the model.")
@click.option("--resume", is_flag=True, default=False,
              help="Continue an interrupted session file from its plan (same protocol; no trial recorded twice).")
@click.option("--overwrite", is_flag=True, default=False, help="Replace an existing --out file.")
@click.option("--seed", type=int, default=None,
              help="Seed of the simulated rig, and of a protocol's random trial order.")
@click.option("--on-failure", type=click.Choice(["continue", "stop"]), default="continue", show_default=True,
              help="What to do after a failed trial (timeout, fault).")
@click.option("--config", "config_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Rig config JSON (calibration); default $RIGCTL_CONFIG or ~/.config/rigctl/rig.json.")
@click.option("--quiet", is_flag=True, default=False, help="No progress bar.")
def acquire(protocol, out, sim, hil, drum_port, taxel_port, replay, resume, overwrite, seed, on_failure, config_path,
            quiet):
    """Run PROTOCOL (a .toml protocol file or a .py script) and record every trial into --out.

    On the simulated rig by default. Ctrl-C stops cleanly (the rig is left safe, finished trials are kept);
    continue later with --resume. Exit status: 0 when every planned trial is complete, 1 otherwise.
    """
    from rigctl.acquisition.protocol import Protocol, ProtocolError, load_protocol
    from rigctl.acquisition.rig import RigError
    from rigctl.acquisition.runner import run_protocol
    from rigctl.rigs import open_rig
    from rigctl.storage.session import SessionError

    if (drum_port is None) != (taxel_port is None):
        raise click.UsageError("give both --drum-port and --taxel-port (hardware), or neither (--sim)")
    if drum_port is not None and (sim or hil):
        raise click.UsageError("--drum-port/--taxel-port select the hardware rig: drop --sim/--hil")
    if sim and hil:
        raise click.UsageError("choose one of --sim and --hil")
    if replay is not None and (hil or drum_port is not None):
        raise click.UsageError("--replay streams a recording through the simulated rig: drop --hil/--drum-port")
    if replay is not None and Path(out).resolve() == Path(replay).resolve():
        raise click.UsageError(f"--out {out} is the recording being replayed: choose another output file")
    if resume and overwrite:
        raise click.UsageError("--resume and --overwrite exclude each other")
    try:
        proto = load_protocol(protocol)
    except ProtocolError as exc:
        raise click.ClickException(str(exc)) from None
    if seed is not None and isinstance(proto, Protocol):
        proto = proto.with_seed(seed)
    if out.exists() and not (resume or overwrite):
        raise click.ClickException(f"{out} exists: continue it with --resume, or pass --overwrite")
    if resume and not out.exists():
        raise click.ClickException(f"{out} does not exist: nothing to resume")
    if resume:
        from rigctl.storage.session import SessionWriter

        try:  # refuse before the rig moves
            SessionWriter.open(out, protocol_source=proto.source)
        except (SessionError, OSError) as exc:
            raise click.ClickException(str(exc)) from None

    # SIGTERM (e.g. a service manager) stops like Ctrl-C: clean stop, rig left safe
    signal.signal(signal.SIGTERM, _sigterm_as_interrupt)
    try:
        kind = "hardware" if drum_port is not None else "replay" if replay is not None else "hil" if hil else "sim"
        rig = open_rig(kind, drum_port=drum_port, taxel_port=taxel_port, source=replay,
                       seed=0 if seed is None else seed, host_config_path=config_path)
    except RigError as exc:
        raise click.ClickException(str(exc)) from None
    with rig:
        try:
            summary = run_protocol(proto, out, rig=rig, resume=resume, progress=not quiet,
                                   on_failure=on_failure, overwrite=overwrite)
        except (SessionError, FileExistsError, FileNotFoundError, ValueError) as exc:
            raise click.ClickException(str(exc)) from None
    for line in summary.lines():
        click.echo(line)
    sys.exit(0 if summary.ok else 1)
