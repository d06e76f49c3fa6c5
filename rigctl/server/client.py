"""A client of ``rigctl serve`` (httpx): what a script, or the GUI attached to a server instead of owning the rig,
calls (docs/serve.md). Every call is one request; errors are :class:`ServerError` in one line."""

from __future__ import annotations

import os
from typing import Any

from rigctl.core.errors import describe_error
from rigctl.server.tokens import default_queue_file, read_token_file, token_file_for

__all__ = ["ServerClient", "ServerError"]


class ServerError(RuntimeError):
    """The server refused a request or could not be reached: ``status`` (HTTP, 0 when unreachable) and its detail."""

    def __init__(self, message: str, status: int = 0) -> None:
        super().__init__(message)
        self.status = status


class ServerClient:
    """The API of the ``rigctl serve`` at ``url`` (e.g. ``http://127.0.0.1:8765``) with its ``token``.

    ``token`` None: ``$RIGCTL_SERVE_TOKEN``, else the token the server at ``url`` wrote beside its queue file
    (``token_file``, default beside ``$XDG_STATE_HOME/rigctl/queue.json``: :mod:`rigctl.server.tokens`; used only
    when it was written for ``url``). ``client``: an ``httpx.Client`` to use instead (tests pass FastAPI's
    TestClient); ``timeout_s`` per request."""

    def __init__(self, url: str = "http://127.0.0.1:8765", *, token: str | None = None, timeout_s: float = 2.0,
                 client: Any = None, token_file: str | os.PathLike[str] | None = None) -> None:
        import httpx

        self.url = url.rstrip("/")
        if not token:
            token = os.environ.get("RIGCTL_SERVE_TOKEN") or read_token_file(
                token_file if token_file is not None else token_file_for(default_queue_file()), self.url)
        #: whether a token is sent (from the argument, the environment or the server's token file)
        self.has_token = bool(token)
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self._http = client if client is not None else httpx.Client(base_url=self.url, timeout=timeout_s)
        self._headers = headers
        self._httpx = httpx

    def _call(self, method: str, path: str, **kw: Any) -> Any:
        if method != "GET" and "json" not in kw:
            kw["json"] = {}  # the server takes state-changing requests as JSON only (no web form can send one)
        try:
            r = self._http.request(method, path, headers=self._headers, **kw)
        except self._httpx.HTTPError as exc:
            raise ServerError(f"rigctl serve at {self.url} does not answer ({describe_error(exc)})") from None
        if r.status_code >= 400:
            try:
                detail = r.json().get("detail", r.text)
            except ValueError:
                detail = r.text
            raise ServerError(f"{method} {path}: {r.status_code} {detail}", r.status_code)
        return r.json()

    def status(self) -> dict[str, Any]:
        return self._call("GET", "/status")

    def runs(self) -> list[dict[str, Any]]:
        return self._call("GET", "/runs")

    def run(self, run_id: str) -> dict[str, Any]:
        return self._call("GET", f"/runs/{run_id}")

    def submit(self, out: str, *, protocol: str | None = None, toml: str | None = None,
               overwrite: bool = False) -> dict[str, Any]:
        """Queue a run (a built-in protocol by name, or TOML text) into the session ``out``, a name inside the
        server's data folder."""
        return self._call("POST", "/runs", json={"protocol": protocol, "toml": toml, "out": out,
                                                 "overwrite": overwrite})

    def pause(self, run_id: str) -> dict[str, Any]:
        return self._call("POST", f"/runs/{run_id}/pause")

    def resume(self, run_id: str) -> dict[str, Any]:
        """Go on after a pause, or continue a stopped or failed run from its session."""
        return self._call("POST", f"/runs/{run_id}/resume")

    def abort(self, run_id: str) -> dict[str, Any]:
        return self._call("POST", f"/runs/{run_id}/abort")

    def stop(self) -> dict[str, Any]:
        """STOP at once (the drum to rest, the current run aborted, the queue held)."""
        return self._call("POST", "/stop")

    def release(self) -> dict[str, Any]:
        return self._call("POST", "/queue/release")

    def acknowledge(self, reason: str, *, by: str = "") -> dict[str, Any]:
        """The operator's acknowledgement of a latched fault (``POST /ack``), logged with ``reason`` and ``by``."""
        return self._call("POST", "/ack", json={"reason": reason, "by": by})

    def close(self) -> None:
        self._http.close()
