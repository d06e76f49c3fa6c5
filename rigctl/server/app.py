"""The HTTP API of ``rigctl serve`` (FastAPI): a thin face on :class:`rigctl.operations.RunQueue` and the open
:class:`rigctl.operations.RigControl` (docs/serve.md).

- ``GET /status``: the rig (drum controller status, board links), the queue (held after STOP?), the current run;
- ``POST /runs`` (``{"protocol": name}`` or ``{"toml": text}``, ``"out"``, ``"overwrite"``) -> ``{"id", ...}``;
  ``GET /runs``, ``GET /runs/{id}`` (state, trials done/total, errors);
- ``POST /runs/{id}/pause|resume|abort`` (resume: after a pause, or a stopped or failed run continued from its
  session); ``POST /stop`` (STOP at once, the current run paused, the queue held); ``POST /queue/release`` (queued
  runs start again after STOP); ``POST /ack`` (``{"reason": text}``: the operator's acknowledgement of a latched
  fault, :meth:`RigControl.acknowledge`);
- ``GET /events``: server-sent events, one JSON object per progress, trial, run and STOP event (the progress events
  the CLI and the GUI draw); at most :data:`rigctl.server.events.MAX_EVENT_CLIENTS` streams at once (429 beyond);
- ``/docs`` (the OpenAPI page, :mod:`rigctl.server.apidocs`), ``/openapi.json``.

Every request passes :mod:`rigctl.server.guard` first: the Host header, a same-origin or absent Origin, the token
(always required), JSON for state-changing requests, a body size limit. A run's ``out`` is a name inside the data
folder (:func:`rigctl.storage.outputs.place_in_folder`, checked by the queue at submit and as the run starts).

STOP first, always: the routes written as plain functions run in AnyIO's worker pool (40 threads), which a burst of
slow requests can fill; ``POST /stop`` is a coroutine that hands :meth:`RunQueue.stop` to a thread of its own
(:func:`_in_own_thread`), and the event streams hold no thread at all (:mod:`rigctl.server.events`), so STOP never
waits for a pool thread.
"""

from __future__ import annotations

import asyncio
import dataclasses
import enum
import ipaddress
import json
import math
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, StreamingResponse
from pydantic import BaseModel, Field

from rigctl.core.drum import DrumError, status_line
from rigctl.core.errors import describe_error
from rigctl.core.version import __version__
from rigctl.operations import QueueError, RunQueue
from rigctl.server.apidocs import install_docs
from rigctl.server.events import MAX_EVENT_CLIENTS, EventHub
from rigctl.server.guard import MAX_BODY_BYTES, install_guard
from rigctl.server.tokens import check_token

#: how long ``/status`` waits for the monitor's first read of a rig opened just now, s
_FIRST_READ_S = 2.0

__all__ = ["RunRequest", "create_app", "is_loopback"]

_T = TypeVar("_T")


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
    toml: str | None = Field(None, description="a TOML protocol's text (instead of protocol)",
                             max_length=MAX_BODY_BYTES)
    out: str = Field(..., description="the session file to write: a name inside the server's data folder "
                                      "(e.g. \"mouse1/s1.h5\")", max_length=4096)
    overwrite: bool = Field(False, description="replace an existing out file (only a rigctl session)")


class AckRequest(BaseModel):
    """The operator's acknowledgement of a latched fault."""

    reason: str = Field(..., min_length=1, max_length=1000, description="why the fault may be cleared (logged)")
    by: str = Field("", max_length=200, description="who acknowledges (logged; default the API client)")


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


def _sse(event: dict[str, Any]) -> str:
    """One event as its server-sent-events line."""
    return f"data: {json.dumps(_plain(event))}\n\n"


async def _in_own_thread(fn: Callable[[], _T], name: str) -> _T:
    """``fn()`` in a new thread of its own (never AnyIO's worker pool, which other requests may hold), awaited."""
    loop = asyncio.get_running_loop()
    done: asyncio.Future[_T] = loop.create_future()

    def settle(value: _T | None, exc: BaseException | None) -> None:
        if done.cancelled():
            return
        if exc is not None:
            done.set_exception(exc)
        else:
            done.set_result(value)  # type: ignore[arg-type]

    def body() -> None:
        try:
            value = fn()
        except BaseException as exc:  # noqa: BLE001 - handed to the awaiting request
            loop.call_soon_threadsafe(settle, None, exc)
        else:
            loop.call_soon_threadsafe(settle, value, None)

    threading.Thread(target=body, name=name, daemon=True).start()
    return await done


def create_app(run_queue: RunQueue, *, token: str,
               allowed_hosts: Sequence[str] = ("127.0.0.1", "localhost"),
               max_event_clients: int = MAX_EVENT_CLIENTS) -> FastAPI:
    """The API over ``run_queue`` (and its rig control), behind :mod:`rigctl.server.guard`.

    ``token``: required on every request (at least 16 characters; :class:`rigctl.server.tokens.TokenError`, a
    ValueError, otherwise); ``allowed_hosts``: the names the Host header may carry (the bound address,
    ``localhost``, ``--allow-host``); ``max_event_clients``: ``/events`` streams open at once (one more: 429).
    ``app.state.events`` is the :class:`rigctl.server.events.EventHub` (its ``end()`` closes every stream)."""
    check_token(token)
    app = FastAPI(title="rigctl serve", version=__version__, docs_url=None, redoc_url=None,
                  description="The tactile texture rig's headless run queue (docs/serve.md).")
    install_guard(app, token=token, allowed_hosts=allowed_hosts)
    app.state.events = EventHub(run_queue, _sse, max_clients=max_event_clients)

    # the handlers are coroutines: Starlette runs a plain function's in the worker pool, which a refusal must not wait
    # for either
    @app.exception_handler(QueueError)
    async def queue_error(request: Request, exc: QueueError) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=exc.status)

    @app.exception_handler(RequestValidationError)
    async def invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        first = exc.errors()[0] if exc.errors() else {}
        where = ".".join(str(p) for p in first.get("loc", ()) if p != "body") or "body"
        status = 413 if first.get("type") == "string_too_long" and where == "toml" else 422
        return JSONResponse({"detail": f"{where}: {first.get('msg', 'invalid request')}"}, status_code=status)

    install_docs(app)  # the OpenAPI page, from the Swagger UI files rigctl ships (no CDN, no token in it)
    _run_routes(app, run_queue)
    _rig_routes(app, run_queue)
    _stop_and_events(app, run_queue, app.state.events)
    return app


def _run_routes(app: FastAPI, run_queue: RunQueue) -> None:
    """The runs: queue one, list them, one run, pause / resume / abort."""

    @app.post("/runs", status_code=201)
    def submit(body: RunRequest) -> dict[str, Any]:
        """Queue a run; returns it (``id``). It starts when the rig is free (one run at a time)."""
        return run_queue.submit(body.out, protocol=body.protocol, toml=body.toml, overwrite=body.overwrite).public()

    @app.get("/runs")
    def runs() -> list[dict[str, Any]]:
        return [r.public() for r in run_queue.list()]

    @app.get("/runs/{run_id}")
    def run(run_id: str) -> dict[str, Any]:
        """A run: state, trials done / total, errors, the summary once ended."""
        return run_queue.get(run_id).public()

    @app.post("/runs/{run_id}/pause")
    def pause(run_id: str) -> dict[str, Any]:
        """Pause after the trial in progress (the sensor released)."""
        return run_queue.pause(run_id).public()

    @app.post("/runs/{run_id}/resume")
    def resume(run_id: str) -> dict[str, Any]:
        """Go on after a pause; or queue a stopped or failed run again, to continue its session where it ended
        (finished trials kept, none recorded twice)."""
        return run_queue.resume(run_id).public()

    @app.post("/runs/{run_id}/abort")
    def abort(run_id: str) -> dict[str, Any]:
        """Stop a run cleanly (finished trials kept, resumable), or take a queued one off the queue."""
        return run_queue.abort(run_id).public()



def _rig_routes(app: FastAPI, run_queue: RunQueue) -> None:
    """The rig: its status, STOP, the queue released, a latched fault acknowledged, the event feed."""

    @app.get("/status")
    def status() -> dict[str, Any]:
        """Rig state (the drum controller's status as the rig's monitor last read it, ``drum_age_s`` ago; a drum
        controller that does not answer: ``drum_error``; ``text``: that status in the words every face shows,
        :func:`rigctl.core.drum.status_line`), board health (the taxel stream's frames, drops, CRC
        errors, connection and reconnects), the queue, the current run and its current trial (id, texture, speed,
        force, attempt, last event). A request reads nothing from the rig: a client polling ``/status`` never feeds
        the controller's watchdog."""
        control = run_queue.control
        rig: dict[str, Any] = {"mode": control.mode}
        latch = control.latch  # a latched fault holds the rig until POST /ack
        rig["latch"] = None if latch is None else {**_plain(latch.to_dict()), "text": latch.describe()}
        monitor = control.monitor  # the library's poll (started with the queue)
        first = time.monotonic() + _FIRST_READ_S
        while monitor.latest is None and monitor.failures == 0 and time.monotonic() < first:
            time.sleep(0.02)  # a server just started: its monitor's first read
        if monitor.ok and monitor.latest is not None:
            rig["drum"] = _plain(monitor.latest)
            # the words every face shows (one home: rigctl.core.drum.status_line), the latch's label in a FAULT
            rig["text"] = status_line(monitor.latest, None if latch is None else latch.label)
            rig["drum_age_s"] = round(monitor.age_s(), 3)
        else:
            rig["drum_error"] = monitor.error or "no status read yet"
        stats = getattr(control.taxels, "stats", None)  # read only: never restarts a link under a run
        rig["taxel_stream"] = None if stats is None else _plain(stats)
        current = run_queue.current_id
        return {"rig": rig, "held": run_queue.held, "current_run": None if current is None else
                run_queue.get(current).public(),
                "current_trial": None if current is None else _plain(run_queue.current_trial),
                "queued": [r.id for r in run_queue.list() if r.state == "queued"]}

    @app.post("/queue/release")
    def release() -> dict[str, Any]:
        run_queue.release()
        return {"held": False}

    @app.post("/ack")
    def ack(body: AckRequest, request: Request) -> dict[str, Any]:
        """The operator's acknowledgement of a latched fault (e-stop, over-force, ...), logged in the rig's log and the
        session with ``by`` and ``reason``; it clears the latch and never moves anything (docs/safety.md): ``start``
        says which start the rig waits for (a paused run's resume, the queue's release)."""
        acknowledge = getattr(run_queue.control, "acknowledge", None)
        if acknowledge is None:
            raise QueueError("this rigctl has no fault acknowledgement (RigControl.acknowledge)", 501)
        client = request.client.host if request.client is not None else "?"
        by = body.by.strip() or f"rigctl serve client {client}"
        try:
            result = acknowledge(body.reason, by=by)
        except (ValueError, RuntimeError, DrumError) as exc:  # nothing latched; the condition persists; no answer
            raise QueueError(f"acknowledgement refused: {describe_error(exc)}", 409) from None
        to_dict = getattr(result, "to_dict", None)
        return {"acknowledged": True, "by": by, "result": _plain(to_dict() if to_dict is not None else result),
                "start": run_queue.start_needed()}



def _stop_and_events(app: FastAPI, run_queue: RunQueue, hub: EventHub) -> None:
    """STOP and the event feed: coroutines on the event loop, neither waits for (nor holds) a worker-pool thread."""

    @app.post("/stop")
    async def stop() -> dict[str, Any]:
        """STOP, at once (the GUI's STOP): drum to rest, actuator home, the current run paused (one ``POST
        /runs/{id}/resume`` goes on; abort is ``POST /runs/{id}/abort``), the queue held until that resume or ``POST
        /queue/release``. Served in a thread of its own, whatever else the server is doing."""
        return {"acknowledged": await _in_own_thread(run_queue.stop, "serve-stop"), "held": True}

    @app.get("/events", response_model=None)
    async def events() -> StreamingResponse | JSONResponse:
        """Server-sent events: one ``data:`` JSON object per event (``type``: progress, trial, run, stop, plate, rig:
        the rig monitor's state, faults, link, dead-man and latch events); a comment line every 10 s of quiet; the
        stream ends when the server shuts down. At most ``max_event_clients`` streams at once: 429 beyond."""
        client = hub.open()
        if client is None:
            return JSONResponse({"detail": f"{hub.max_clients} event streams are open already (the most this "
                                           "server serves); close one and try again"}, status_code=429,
                                headers={"Retry-After": "10"})
        return StreamingResponse(hub.stream(client), media_type="text/event-stream")
