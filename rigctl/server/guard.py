"""What every request to ``rigctl serve`` passes before it reaches a route (docs/serve.md, "Security"): ASGI
middleware, outermost first:

1. the ``Host`` header must name the server (Starlette's ``TrustedHostMiddleware``: the bound address,
   ``localhost`` and ``--allow-host`` names; a DNS-rebinding page's own domain is refused, 400);
2. :class:`RequestGuard`: an ``Origin`` header, when there is one, must be the server's own (a cross-origin page is
   refused, 403; no CORS headers are ever sent); the token (``Authorization: Bearer TOKEN``, or ``?token=`` for a
   browser's ``EventSource``) on every path, /docs and /openapi.json included (401); a state-changing request
   (anything but GET and HEAD) must be ``Content-Type: application/json`` (415: an HTML form cannot send it without
   a CORS preflight); a body larger than :data:`MAX_BODY_BYTES` is refused (413) before the route reads it.

Refusals answer ``{"detail": "one line"}``.
"""

from __future__ import annotations

import json
import secrets
from collections.abc import Sequence

from starlette.applications import Starlette
from starlette.datastructures import Headers, QueryParams
from starlette.middleware.trustedhost import TrustedHostMiddleware
from starlette.types import ASGIApp, Message, Receive, Scope, Send

__all__ = ["MAX_BODY_BYTES", "RequestGuard", "install_guard"]

#: the largest request body taken, bytes (a protocol's TOML text is far smaller)
MAX_BODY_BYTES = 1_000_000
#: methods that change nothing (everything else needs JSON and a same-origin Origin)
SAFE_METHODS = ("GET", "HEAD")


async def _refuse(send: Send, status: int, detail: str, headers: Sequence[tuple[bytes, bytes]] = ()) -> None:
    body = json.dumps({"detail": detail}).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                            *headers]})
    await send({"type": "http.response.body", "body": body})


def _given_token(headers: Headers, scope: Scope) -> str:
    auth = headers.get("authorization", "")
    if auth[:7].lower() == "bearer ":
        return auth[7:].strip()
    return QueryParams(scope.get("query_string", b"").decode("latin-1")).get("token", "")


class RequestGuard:
    """The Origin, token, content-type and body-size checks (module docstring) in front of ``app``."""

    def __init__(self, app: ASGIApp, *, token: str, max_body_bytes: int = MAX_BODY_BYTES) -> None:
        self.app = app
        self._token = token.encode()
        self.max_body_bytes = max_body_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "lifespan":
            await self.app(scope, receive, send)
            return
        if scope["type"] != "http":  # no websockets here
            await send({"type": "websocket.close", "code": 1008})
            return
        headers = Headers(scope=scope)
        origin = headers.get("origin")
        if origin is not None and origin.rstrip("/").lower() != f"{scope.get('scheme', 'http')}://" \
                f"{headers.get('host', '')}".lower():
            await _refuse(send, 403, f"cross-origin requests are refused (Origin {origin[:100]}): the API serves "
                                     "rigctl's clients and scripts, not other web pages")
            return
        if not secrets.compare_digest(_given_token(headers, scope).encode("utf-8", "replace"), self._token):
            await _refuse(send, 401, "a valid token is required (Authorization: Bearer TOKEN; rigctl serve prints "
                                     "it and writes it beside its queue file)", [(b"www-authenticate", b"Bearer")])
            return
        method = scope["method"]
        if method not in SAFE_METHODS:
            ctype = headers.get("content-type", "").split(";")[0].strip().lower()
            if ctype != "application/json":
                await _refuse(send, 415, f"{method} requests must be Content-Type: application/json (got "
                                         f"{ctype[:60] or 'none'})")
                return
        try:
            declared = int(headers.get("content-length", "0"))
        except ValueError:
            await _refuse(send, 400, "a malformed Content-Length")
            return
        if declared > self.max_body_bytes:
            await _refuse(send, 413, f"the request body is {declared} bytes: at most {self.max_body_bytes}")
            return
        if method in SAFE_METHODS:
            await self.app(scope, receive, send)
            return
        chunks, size, more = [], 0, True
        while more:  # read whole (at most max_body_bytes): a chunked body has no Content-Length to trust
            message = await receive()
            if message["type"] != "http.request":
                await self.app(scope, receive, send)  # the client went away: let the route see it
                return
            chunks.append(message.get("body", b""))
            size += len(chunks[-1])
            more = message.get("more_body", False)
            if size > self.max_body_bytes:
                await _refuse(send, 413, f"the request body is over {self.max_body_bytes} bytes")
                return
        body = b"".join(chunks)
        sent = False

        async def replay() -> Message:
            nonlocal sent
            if not sent:
                sent = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)


def install_guard(app: Starlette, *, token: str, allowed_hosts: Sequence[str],
                  max_body_bytes: int = MAX_BODY_BYTES) -> None:
    """Put :class:`RequestGuard` and, outside it, the Host check in front of ``app``'s routes (``allowed_hosts``:
    names and addresses, IPv6 in brackets; ports are not compared)."""
    app.add_middleware(RequestGuard, token=token, max_body_bytes=max_body_bytes)
    app.add_middleware(TrustedHostMiddleware, allowed_hosts=list(allowed_hosts), www_redirect=False)
