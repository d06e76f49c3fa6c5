"""The HTTP API of ``rigctl serve`` (FastAPI): a thin face on :class:`rigctl.operations.RunQueue` and the open
:class:`rigctl.operations.RigControl` (docs/serve.md).

- ``GET /status``: the rig (drum controller status, board links), the queue (held after STOP?), the current run;
- ``POST /runs`` (``{"protocol": name}`` or ``{"toml": text}``, ``"out"``, ``"overwrite"``) -> ``{"id", ...}``;
  ``GET /runs``, ``GET /runs/{id}`` (state, trials done/total, errors);
- ``POST /runs/{id}/pause|resume|abort``; ``POST /stop`` (STOP at once, the current run aborted, the queue held);
  ``POST /queue/release`` (queued runs start again after STOP);
- ``GET /events``: server-sent events, one JSON object per progress, trial, run and STOP event (the progress events
  the CLI and the GUI draw);
- ``/docs`` (the OpenAPI page), ``/openapi.json``.

A token (``Authorization: Bearer <token>``, or ``?token=`` for an ``EventSource``) is required on every request
when the server has one; ``rigctl serve`` refuses to bind a non-loopback address without one.
"""

from __future__ import annotations

import dataclasses
import enum
import ipaddress
import json
import math
import queue
import secrets
from collections.abc import Iterator
from typing import Any

from fastapi import Depends, FastAPI, HTTPException, Request
from fastapi.responses import JSONResponse, StreamingResponse
from pydantic import BaseModel, Field

from rigctl.core.errors import describe_error
from rigctl.core.version import __version__
from rigctl.operations import QueueError, RunQueue

__all__ = ["RunRequest", "create_app", "is_loopback"]


def is_loopback(host: str) -> bool:
    """Whether binding ``host`` serves this machine alone (``localhost``, 127.0.0.0/8, ::1)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class RunRequest(BaseModel):
    """A run to queue: a built-in protocol by name or a TOML protocol's text, and the session file to write."""

    protocol: str | None = Field(None, description="a built-in protocol's name (rigctl protocols lists them)")
    toml: str | None = Field(None, description="a TOML protocol's text (instead of protocol)")
    out: str = Field(..., description="the session file to write (on the server's host)")
    overwrite: bool = Field(False, description="replace an existing out file")


def _plain(value: Any) -> Any:
    """JSON-able: dataclasses and enums by name, NaN as null."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, enum.Flag) and not isinstance(value, enum.IntEnum):
        return [m.name for m in type(value) if m.value and m in value]
    if isinstance(value, enum.Enum):
        return value.name
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if hasattr(value, "item"):
        return _plain(value.item())
    return value


def create_app(run_queue: RunQueue, *, token: str | None = None) -> FastAPI:
    """The API over ``run_queue`` (and its rig control); ``token``: required on every request when given."""
    app = FastAPI(title="rigctl serve", version=__version__,
                  description="The tactile texture rig's headless run queue (docs/serve.md).")

    def authorised(request: Request) -> None:
        if token is None:
            return
        given = request.headers.get("authorization", "")
        given = given[7:] if given.lower().startswith("bearer ") else request.query_params.get("token", "")
        if not secrets.compare_digest(given.encode(), token.encode()):
            raise HTTPException(401, "a valid token is required (Authorization: Bearer <token>)",
                                headers={"WWW-Authenticate": "Bearer"})

    auth = [Depends(authorised)]

    @app.exception_handler(QueueError)
    def queue_error(request: Request, exc: QueueError) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=exc.status)

    @app.get("/status", dependencies=auth)
    def status() -> dict[str, Any]:
        """Rig state (the drum controller's status), board health (the taxel stream's frames, drops, CRC errors,
        connection and reconnects; a drum controller that does not answer: ``drum_error``), the queue, the
        current run and its current trial (id, texture, speed, force, attempt, last event)."""
        control = run_queue.control
        rig: dict[str, Any] = {"mode": control.rig.mode}
        try:
            rig["drum"] = _plain(control.status())
        except Exception as exc:  # noqa: BLE001 - reported, not raised: the status page must answer
            rig["drum_error"] = describe_error(exc)
        stats = getattr(control.rig.stream, "stats", None)  # read only: never restarts a link under a run
        rig["taxel_stream"] = None if stats is None else _plain(stats)
        current = run_queue.current_id
        return {"rig": rig, "held": run_queue.held, "current_run": None if current is None else
                run_queue.get(current).public(),
                "current_trial": None if current is None else _plain(run_queue.current_trial),
                "queued": [r.id for r in run_queue.list() if r.state == "queued"]}

    @app.post("/runs", status_code=201, dependencies=auth)
    def submit(body: RunRequest) -> dict[str, Any]:
        """Queue a run; returns it (``id``). It starts when the rig is free (one run at a time)."""
        return run_queue.submit(body.out, protocol=body.protocol, toml=body.toml, overwrite=body.overwrite).public()

    @app.get("/runs", dependencies=auth)
    def runs() -> list[dict[str, Any]]:
        return [r.public() for r in run_queue.list()]

    @app.get("/runs/{run_id}", dependencies=auth)
    def run(run_id: str) -> dict[str, Any]:
        """A run: state, trials done / total, errors, the summary once ended."""
        return run_queue.get(run_id).public()

    @app.post("/runs/{run_id}/pause", dependencies=auth)
    def pause(run_id: str) -> dict[str, Any]:
        """Pause after the trial in progress (the sensor released)."""
        return run_queue.pause(run_id).public()

    @app.post("/runs/{run_id}/resume", dependencies=auth)
    def resume(run_id: str) -> dict[str, Any]:
        return run_queue.resume(run_id).public()

    @app.post("/runs/{run_id}/abort", dependencies=auth)
    def abort(run_id: str) -> dict[str, Any]:
        """Stop a run cleanly (finished trials kept, resumable), or take a queued one off the queue."""
        return run_queue.abort(run_id).public()

    @app.post("/stop", dependencies=auth)
    def stop() -> dict[str, Any]:
        """STOP, at once (the GUI's STOP): drum to rest, actuator home, the current run aborted, the queue held
        until ``POST /queue/release``."""
        return {"acknowledged": run_queue.stop(), "held": True}

    @app.post("/queue/release", dependencies=auth)
    def release() -> dict[str, Any]:
        run_queue.release()
        return {"held": False}

    @app.get("/events", dependencies=auth)
    def events() -> StreamingResponse:
        """Server-sent events: one ``data:`` JSON object per event (``type``: progress, trial, run, stop, plate)."""
        q = run_queue.subscribe()

        def stream() -> Iterator[str]:
            try:
                yield ": rigctl events\n\n"
                while True:
                    try:
                        event = q.get(timeout=10.0)
                    except queue.Empty:
                        yield ": keep-alive\n\n"
                        continue
                    yield f"data: {json.dumps(_plain(event))}\n\n"
            finally:
                run_queue.unsubscribe(q)

        return StreamingResponse(stream(), media_type="text/event-stream")

    return app
