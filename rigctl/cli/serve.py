"""``rigctl serve``: the headless run queue with its HTTP API (docs/serve.md)."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import click

from rigctl.cli.outputs import UsageProblem
from rigctl.cli.rig_flags import inject_option

#: the rig kinds ``--rig`` takes (``rigctl.rigs.KINDS``)
RIG_KINDS = ("sim", "hil", "hardware", "replay", "inprocess")


def default_queue_file() -> Path:
    """``$XDG_STATE_HOME/rigctl/queue.json`` (``~/.local/state/rigctl/queue.json``)."""
    state = os.environ.get("XDG_STATE_HOME") or os.path.join(os.path.expanduser("~"), ".local", "state")
    return Path(state) / "rigctl" / "queue.json"


@click.command()
@click.option("--host", default="127.0.0.1", show_default=True,
              help="Address to bind. Anything but a loopback address needs --token.")
@click.option("--port", type=click.IntRange(0, 65535), default=8765, show_default=True, help="TCP port (0: any).")
@click.option("--token", envvar="RIGCTL_SERVE_TOKEN", default=None,
              help="Token every request must carry (Authorization: Bearer TOKEN); required off loopback. "
                   "Default $RIGCTL_SERVE_TOKEN.")
@click.option("--queue", "queue_file", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="The queue file (runs survive a restart; a run cut by a crash resumes). Default "
                   "$XDG_STATE_HOME/rigctl/queue.json.")
@click.option("--rig", "kind", type=click.Choice(RIG_KINDS), default="sim", show_default=True,
              help="The rig: the simulated one, the firmware under simavr, hardware (--drum-port/--taxel-port), a "
                   "replay (--replay) or the fast in-process simulation.")
@click.option("--drum-port", default=None, help="Serial port of the drum controller (--rig hardware).")
@click.option("--taxel-port", default=None, help="Serial port of the taxel streamer (--rig hardware).")
@click.option("--replay", type=click.Path(exists=True, path_type=Path), default=None,
              help="Recording the simulated taxel board streams (--rig replay).")
@click.option("--config", "config_path", type=click.Path(exists=True, dir_okay=False, path_type=Path), default=None,
              help="Rig config JSON (calibration); default $RIGCTL_CONFIG or ~/.config/rigctl/rig.json.")
@click.option("--seed", type=click.IntRange(0, 2**32 - 1), default=0, show_default=True,
              help="Seed of a simulated rig.")
@click.option("--lsl/--no-lsl", "lsl", default=None,
              help="Publish every run on Lab Streaming Layer; default the rig config's lsl.enabled.")
@inject_option
def serve(host, port, token, queue_file, kind, drum_port, taxel_port, replay, config_path, seed, lsl, inject):
    """Open the rig and serve its run queue over HTTP until Ctrl-C / SIGTERM.

    POST /runs queues a protocol (by name or TOML text); one run owns the rig at a time, the others wait; GET
    /runs/ID, pause / resume / abort, POST /stop (STOP at once), GET /events (server-sent progress events), the
    OpenAPI page at /docs. A run cut by a crash resumes from its session file when the server starts again. Plate
    changes on hardware are announced on the event feed, not waited for (as acquire --plates auto).
    """
    from rigctl.acquisition.lsl import LslUnavailable, require_pylsl
    from rigctl.acquisition.rig import RigError
    from rigctl.acquisition.rigconfig import CalibrationError, load_rig_config
    from rigctl.core.faults import FaultSpecError
    from rigctl.operations import QueueError, RigSource, RunQueue, lsl_requested, open_control
    from rigctl.server.app import create_app, is_loopback

    if not is_loopback(host) and not token:
        raise UsageProblem(f"--host {host} serves other machines: give a --token (or $RIGCTL_SERVE_TOKEN) every "
                           "request must carry, or bind 127.0.0.1")
    if (kind == "hardware") != (drum_port is not None and taxel_port is not None):
        raise UsageProblem("--rig hardware takes both --drum-port and --taxel-port (and only it does)")
    if (kind == "replay") != (replay is not None):
        raise UsageProblem("--rig replay takes --replay RECORDING (and only it does)")
    try:
        import fastapi  # noqa: F401
        import uvicorn
    except ImportError as exc:
        raise click.ClickException(f"rigctl serve needs FastAPI and uvicorn: pip install 'rigctl[serve]' ({exc})") \
            from None
    try:
        host_config = load_rig_config(config_path)
    except CalibrationError as exc:
        raise UsageProblem(f"--config {exc}") from None
    publish = lsl_requested(lsl, host_config)
    if publish:
        try:
            require_pylsl()
        except LslUnavailable as exc:
            raise click.ClickException(str(exc)) from None
    source = RigSource(kind, drum_port=drum_port, taxel_port=taxel_port,
                       replay_dir=None if replay is None else str(replay), inject=inject)
    try:
        control = open_control(source, seed=seed, host_config_path=config_path)
    except FaultSpecError as exc:  # --inject names a fault this rig cannot model
        raise UsageProblem(str(exc)) from None
    except (RigError, OSError, ValueError) as exc:
        raise click.ClickException(" ".join(str(exc).split())) from None
    with control:
        try:
            run_queue = RunQueue(control, queue_file or default_queue_file(), lsl=publish)
        except QueueError as exc:
            raise click.ClickException(str(exc)) from None
        run_queue.start()
        app = create_app(run_queue, token=token)
        click.echo(f"rigctl serve: {source.label()} on http://{host}:{port} (API reference: /docs; queue "
                   f"{run_queue.path})", err=True)
        try:
            uvicorn.run(app, host=host, port=port, log_level=logging.getLevelName(logging.WARNING).lower())
        finally:
            run_queue.close()
