"""One HTTP client for a test process's requests to ``rigctl serve`` on loopback.

``httpx.get(...)`` and its siblings make a new ``httpx.Client`` for every request, and each client builds an SSL
context and loads the CA bundle (~30 CPU-ms on this machine) for a plain ``http://127.0.0.1`` request: a test that
polls a server's ``/status`` every 50 ms for a minute spent a third of its CPU there (test_serve_ack: ~6.6 of 25
CPU-s). :func:`client` is made once a process; without keep-alive (each request opens and closes its own connection,
as ``httpx.get`` does), so a server stopped and started again between two requests is met as before."""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import httpx


@functools.cache
def client() -> httpx.Client:
    """The process's client: ``httpx.get``'s defaults (5 s timeout, no redirects followed), no connection kept."""
    import httpx

    return httpx.Client(limits=httpx.Limits(max_keepalive_connections=0))
