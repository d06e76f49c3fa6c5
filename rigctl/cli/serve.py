"""``rigctl serve``: the headless run queue with its HTTP API (docs/serve.md)."""

from __future__ import annotations

import contextlib
import gc
import logging
import signal
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import click

from rigctl.cli.outputs import UsageProblem
from rigctl.cli.rig_flags import RIG, inject_option, lsl_wait_option, rig_options_option
from rigctl.server.tokens import (
    TokenError,
    check_token,
    default_data_dir,
    default_queue_file,
    new_token,
    remove_token_file,
    token_file_for,
    write_token_file,
)

#: how long a shutdown waits for open connections after closing the event streams, s
SHUTDOWN_GRACE_S = 1


@click.command()
@click.option("--host", default="127.0.0.1", show_default=True,
              help="Address to bind. Anything but a loopback address needs an explicit --token.")
@click.option("--port", type=click.IntRange(0, 65535), default=8765, show_default=True, help="TCP port (0: any).")
@click.option("--token", envvar="RIGCTL_SERVE_TOKEN", default=None,
              help="Token every request must carry (Authorization: Bearer TOKEN), at least 16 characters; default "
                   "$RIGCTL_SERVE_TOKEN, else one is generated and printed. Written (0600) beside the queue file, "
                   "where rigctl's clients read it.")
@click.option("--allow-host", "allow_hosts", multiple=True, metavar="NAME",
              help="Another name the Host header may carry (besides the bound address and localhost); repeatable.")
@click.option("--data-dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="The folder runs write their sessions in (a run's out is a name inside it). Default "
                   "$XDG_DATA_HOME/rigctl/sessions.")
@click.option("--queue", "queue_file", type=click.Path(dir_okay=False, writable=True, path_type=Path), default=None,
              help="The queue file (runs survive a restart; a run cut by a crash resumes). Default "
                   "$XDG_STATE_HOME/rigctl/queue.json.")
@click.option("--rig", "kind", type=RIG, default="sim", show_default=True,
              help="The rig: sim (the simulated one), hil (the firmware under simavr), hardware (--drum-port/"
                   "--taxel-port), replay (--replay), inprocess (the fast in-process simulation) or an installed "
                   "plugin's rig (--rig-option KEY=VALUE; `rigctl rigs` lists them).")
@rig_options_option
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
@lsl_wait_option
@click.option("--ack", "ack", metavar="REASON", default=None,
              help="Acknowledge a fault the drum controller still latches when the server starts (its cause gone), "
                   "logged with your login name and REASON. Without it the fault is kept and shown (GET /status), "
                   "the queue held until POST /ack and POST /queue/release: a server never acknowledges in its own "
                   "name, and a restarted one never moves by itself.")
@inject_option
def serve(host, port, token, allow_hosts, data_dir, queue_file, kind, rig_options, drum_port, taxel_port, replay,
          config_path, seed, lsl, lsl_wait_s, ack, inject):
    """Open the rig and serve its run queue over HTTP until Ctrl-C / SIGTERM.

    POST /runs queues a protocol (by name or TOML text) into a session inside --data-dir; one run owns the rig at
    a time, the others wait; GET /runs/ID, pause / resume / abort, POST /stop (STOP at once), POST /ack, GET
    /events (server-sent progress events), the OpenAPI page at /docs. Every request needs the token, a Host header
    naming this server and, for a POST, JSON from no other web page (docs/serve.md, "Security"). A run cut by a crash
    resumes from its session file when the server starts again. Plate changes on hardware are announced on the
    event feed, not waited for (as acquire --plates auto).
    """
    from rigctl.server.app import is_loopback

    if not is_loopback(host) and not token:
        raise UsageProblem(f"--host {host} serves other machines: give a --token (or $RIGCTL_SERVE_TOKEN) every "
                           "request must carry, or bind 127.0.0.1")
    try:
        token = check_token(token) if token is not None else new_token()
    except TokenError as exc:
        raise UsageProblem(f"--token: {exc}") from None
    for name in allow_hosts:
        if not name or "*" in name[1:] or (name.startswith("*") and not name.startswith("*.")) or "/" in name:
            raise UsageProblem(f"--allow-host {name!r}: give a host name or address (a leading '*.' for a domain)")
    if (kind == "hardware") != (drum_port is not None and taxel_port is not None):
        raise UsageProblem("--rig hardware takes both --drum-port and --taxel-port (and only it does)")
    if (kind == "replay") != (replay is not None):
        raise UsageProblem("--rig replay takes --replay RECORDING (and only it does)")
    if ack is not None and not ack.strip():
        raise UsageProblem("--ack takes the reason the fault may be cleared (logged)")
    if kind == "handheld":
        raise UsageProblem("--rig handheld: the run queue serves a drum rig (the handheld rig records with rigctl "
                           "acquire --handheld)")
    _serve(host=host, port=port, token=token, generated=not _given(), allow_hosts=allow_hosts,
           data_dir=data_dir or default_data_dir(), queue_file=queue_file or default_queue_file(), kind=kind,
           drum_port=drum_port, taxel_port=taxel_port, replay=replay, config_path=config_path, seed=seed, lsl=lsl,
           inject=inject, lsl_wait_s=lsl_wait_s, rig_options=rig_options, ack=ack)


def _given() -> bool:
    """Whether the token came from --token or $RIGCTL_SERVE_TOKEN (not generated)."""
    ctx = click.get_current_context()
    return ctx.get_parameter_source("token") not in (None, click.core.ParameterSource.DEFAULT)


def _bind(host: str, port: int) -> socket.socket:
    """The listening socket (bound here, so the token file and the banner name the real port when --port 0)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError as exc:
        sock.close()
        raise click.ClickException(f"cannot listen on {host}:{port} ({exc.strerror or exc})") from None
    sock.listen(2048)  # uvicorn's own backlog: a burst of clients connecting at once is queued, not refused
    sock.set_inheritable(True)
    return sock


def _checked_before_open(*, kind: str, queue_file: Path, drum_port: str | None, taxel_port: str | None,
                         replay: Path | None, config_path: Path | None, lsl: bool | None, inject: tuple[Any, ...],
                         rig_options: dict[str, str]) -> tuple[bool, Any]:
    """What serve checks before it locks the queue, binds the port or opens the rig: FastAPI and uvicorn, the rig
    config, the queue file, LSL, the rig source and its injections. Returns ``(publish, source)``; UsageProblem
    (exit 2) or ClickException (exit 1), one line."""
    from rigctl.acquisition.lsl import LslUnavailable, require_pylsl
    from rigctl.acquisition.rigconfig import CalibrationError, load_rig_config
    from rigctl.operations import QueueError, RigSource, lsl_requested, read_queue_file

    try:
        import fastapi  # noqa: F401
        import uvicorn  # noqa: F401
    except ImportError as exc:
        raise click.ClickException(f"rigctl serve needs FastAPI and uvicorn: pip install 'rigctl[serve]' ({exc})") \
            from None
    try:
        host_config = load_rig_config(config_path)
    except CalibrationError as exc:
        raise UsageProblem(f"--config {exc}") from None
    try:  # the queue file read before the rig opens: a session, another program's file or a device is refused
        read_queue_file(queue_file)
    except QueueError as exc:
        raise UsageProblem(f"--queue {exc}") from None
    publish = lsl_requested(lsl, host_config)
    if publish:
        try:
            require_pylsl()
        except LslUnavailable as exc:
            raise click.ClickException(str(exc)) from None
    try:
        source = RigSource(kind, drum_port=drum_port, taxel_port=taxel_port,
                           replay_dir=None if replay is None else str(replay), inject=inject, options=rig_options)
    except ValueError as exc:  # options for one of rigctl's own rigs, a name rigctl keeps
        raise UsageProblem(str(exc)) from None
    why = source.injection_refusal()  # known before the rig opens or the port is bound
    if why:
        raise UsageProblem(why)
    return publish, source


def _serve(*, host: str, port: int, token: str, generated: bool, allow_hosts: tuple[str, ...], data_dir: Path,
           queue_file: Path, kind: str, drum_port: str | None, taxel_port: str | None, replay: Path | None,
           config_path: Path | None, seed: int, lsl: bool | None, inject: tuple[Any, ...],
           lsl_wait_s: float, rig_options: dict[str, str], ack: str | None = None) -> None:
    import uvicorn

    from rigctl.acquisition.safety import operator_name
    from rigctl.core.faults import FaultSpecError
    from rigctl.operations import Home, QueueError, RigError, RunQueue, lock_queue_file, open_control
    from rigctl.server.app import create_app

    publish, source = _checked_before_open(kind=kind, queue_file=queue_file, drum_port=drum_port,
                                           taxel_port=taxel_port, replay=replay, config_path=config_path, lsl=lsl,
                                           inject=inject, rig_options=rig_options)
    try:  # one server per queue file, known before this one opens the rig (opening a board's port resets it)
        queue_lock = lock_queue_file(queue_file)
    except QueueError as exc:
        raise click.ClickException(str(exc)) from None
    try:
        sock = _bind(host, port)
    except BaseException:
        queue_lock.release()
        raise
    try:
        # nothing moves at open (the first run's start HOMEs): a restarted server never moves by itself; a fault the
        # controller latches is kept (the queue held) unless the operator acknowledges it here (--ack)
        control = open_control(source, seed=seed, host_config_path=config_path, home=Home.AT_START,
                               acknowledge=None if ack is None else (ack.strip(), operator_name()))
    except FaultSpecError as exc:  # --inject names a fault this rig cannot model
        sock.close()
        queue_lock.release()
        raise UsageProblem(str(exc)) from None
    except (RigError, OSError, ValueError) as exc:
        sock.close()
        queue_lock.release()
        raise click.ClickException(" ".join(str(exc).split())) from None
    with control:
        try:
            run_queue = RunQueue(control, queue_file, lsl=publish, data_dir=data_dir, lsl_wait_s=lsl_wait_s,
                                 file_lock=queue_lock)
        except QueueError as exc:
            sock.close()
            queue_lock.release()
            raise click.ClickException(str(exc)) from None
        bound = f"[{host}]" if ":" in host else host
        url = f"http://{bound}:{sock.getsockname()[1]}"
        app = create_app(run_queue, token=token, allowed_hosts=(bound, "localhost", *allow_hosts))
        token_file = write_token_file(token_file_for(run_queue.path), url=url, token=token)
        run_queue.start()
        click.echo(f"rigctl serve: {source.label()} on {url} (sessions in {run_queue.data_dir}; queue "
                   f"{run_queue.path}; token in {token_file})", err=True)
        if generated:  # printed once, as Jupyter does: the API reference with the token
            click.echo(f"rigctl serve: open {url}/docs?token={token}", err=True)
        if control.latch is not None:  # shown and kept: the server never acknowledges in its own name
            click.echo(f"rigctl serve: LATCHED {control.latch.describe()}; the queue is held: POST /ack (the "
                       "operator's reason), then POST /queue/release", err=True)
        server = _Server(uvicorn.Config(app, log_level=logging.getLevelName(logging.WARNING).lower(),
                                        timeout_graceful_shutdown=SHUTDOWN_GRACE_S), app.state.events)
        try:
            server.run(sockets=[sock])
        finally:
            run_queue.close()
            remove_token_file(token_file, token)
            sock.close()
            click.echo(f"rigctl serve: stopped in {server.shutdown_s:.1f} s ({server.streams_closed} event "
                       "stream(s) closed, the queue saved)", err=True)
            # every file is closed: spare the interpreter's final cyclic collection over numba's and FastAPI's
            # objects (2-3 s on a busy 2-core machine, 0.2 s with them frozen), so Ctrl-C returns the prompt at once
            gc.freeze()


def _server_class() -> Any:
    import uvicorn

    class Server(uvicorn.Server):
        """uvicorn's server that ends the event streams first when told to exit (uvicorn's graceful shutdown
        otherwise waits for every open response: an /events client kept Ctrl-C waiting ~50 s)."""

        def __init__(self, config: Any, events: Any) -> None:
            super().__init__(config)
            self.events = events  # the app's EventHub
            self.streams_closed = 0
            self._exit_t: float | None = None

        @property
        def shutdown_s(self) -> float:
            return 0.0 if self._exit_t is None else time.monotonic() - self._exit_t

        @contextlib.contextmanager
        def capture_signals(self) -> Iterator[None]:
            """Ctrl-C and SIGTERM end the server (:meth:`handle_exit`); unlike uvicorn's own, the signal is not
            raised again afterwards: the queue is closed and the token file removed, then the command returns."""
            if threading.current_thread() is not threading.main_thread():
                yield
                return
            original = {sig: signal.signal(sig, self.handle_exit) for sig in (signal.SIGINT, signal.SIGTERM)}
            try:
                yield
            finally:
                for sig, handler in original.items():
                    signal.signal(sig, handler)

        def handle_exit(self, sig: int, frame: Any) -> None:
            if self._exit_t is None:
                self._exit_t = time.monotonic()
                click.echo("rigctl serve: stopping (closing the event streams, the run in progress stopped "
                           "cleanly and kept queued)", err=True)
            self.streams_closed += self.events.end()
            super().handle_exit(sig, frame)

    return Server


def _Server(config: Any, events: Any) -> Any:  # noqa: N802 - a class made on first use (uvicorn is optional)
    return _server_class()(config, events)
