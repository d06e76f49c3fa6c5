"""``GET /events`` of ``rigctl serve`` without a worker thread per client (issue 51 item 5, "STOP first, always").

The server's routes that are plain functions run in AnyIO's worker pool (40 threads); an event stream written as a
blocking generator held one of them for as long as its client stayed connected, so 40 idle ``/events`` clients left
``POST /stop`` waiting (10 s with 45 streams, 20 s with 120). Here the feed is an :class:`EventHub`: ONE subscription
to the run queue's events (:meth:`rigctl.operations.RunQueue.subscribe`), read by one thread of its own that formats
each event once and hands it to the event loop(s) (``loop.call_soon_threadsafe``); each client is an async generator
awaiting an ``asyncio.Queue``: an idle client costs a socket and a queue, no thread. At most ``max_clients``
(:data:`MAX_EVENT_CLIENTS`) streams are open at once; one more is answered 429 (``EventHub.open`` returns None).
"""

from __future__ import annotations

import asyncio
import contextlib
import queue
import threading
from collections.abc import AsyncIterator, Callable
from typing import Any, Protocol

__all__ = ["CLIENT_BACKLOG", "KEEPALIVE_S", "MAX_EVENT_CLIENTS", "EventClient", "EventHub"]

#: the most ``/events`` streams open at once (one more is answered 429); each is a socket and a queue, no thread
MAX_EVENT_CLIENTS = 256
#: a comment line every this many seconds keeps an idle stream open through proxies, s
KEEPALIVE_S = 10.0
#: events a client may fall behind by before it loses the oldest (a client that stops reading never holds the run)
CLIENT_BACKLOG = 10_000


class EventSource(Protocol):
    """What the hub subscribes to (:class:`rigctl.operations.RunQueue`)."""

    def subscribe(self) -> "queue.Queue[dict[str, Any] | None]": ...

    def unsubscribe(self, q: "queue.Queue[dict[str, Any] | None]") -> None: ...

    def end_streams(self) -> int: ...


class EventClient:
    """One open ``/events`` stream: the event loop it is served on and the lines waiting for it (None: the end)."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop
        self.lines: asyncio.Queue[str | None] = asyncio.Queue(CLIENT_BACKLOG)

    def put(self, line: str | None) -> None:
        """Queue ``line`` (on :attr:`loop`'s thread); a full queue drops its oldest line (the end is never lost)."""
        if self.lines.full():
            with contextlib.suppress(asyncio.QueueEmpty):
                self.lines.get_nowait()
        self.lines.put_nowait(line)


class EventHub:
    """The run queue's event feed shared by every ``/events`` client (module docstring).

    ``source``: the run queue; ``fmt(event) -> str``: one event as its server-sent-events line(s), made once per
    event whatever the number of clients; ``max_clients``: streams open at once. The hub subscribes at once and its
    thread ends when the source ends its streams (:meth:`end`, or :meth:`rigctl.operations.RunQueue.close`)."""

    def __init__(self, source: EventSource, fmt: Callable[[dict[str, Any]], str], *,
                 max_clients: int = MAX_EVENT_CLIENTS) -> None:
        self.max_clients = max_clients
        self._source = source
        self._fmt = fmt
        # the client set, shared by the loop(s) and the hub's thread, held briefly; reentrant: end() runs in a signal
        # handler (rigctl serve's Ctrl-C), on the loop's thread, which may hold it at that moment
        self._lock = threading.RLock()
        self._clients: set[EventClient] = set()
        self._ended = False
        self._counted = False
        self._feed = source.subscribe()
        self._thread = threading.Thread(target=self._pump, name="serve-events", daemon=True)
        self._thread.start()

    @property
    def clients(self) -> int:
        """Streams open now."""
        with self._lock:
            return len(self._clients)

    def open(self) -> EventClient | None:
        """A new client on the running event loop; None when :attr:`max_clients` streams are open already. A
        client opened after the feed ended gets its end at once."""
        client = EventClient(asyncio.get_running_loop())
        with self._lock:
            if len(self._clients) >= self.max_clients:
                return None
            self._clients.add(client)
            ended = self._ended
        if ended:
            client.put(None)
        return client

    def close(self, client: EventClient) -> None:
        """``client`` disconnected (or its stream ended): its place is free."""
        with self._lock:
            self._clients.discard(client)

    def end(self) -> int:
        """End every stream now (a shutting-down server does not wait for its clients): the source's feed ended,
        each client given its end. Returns how many streams were open (0 on a second call)."""
        with self._lock:
            open_now = 0 if self._counted else len(self._clients)
            self._counted = True
        self._source.end_streams()
        return open_now

    async def stream(self, client: EventClient) -> AsyncIterator[str]:
        """The lines of ``client``'s stream: a first comment, each event, a keep-alive comment every
        :data:`KEEPALIVE_S` of quiet, a last comment when the feed ends. Its place is freed when it ends or is
        cancelled (the client went away)."""
        try:
            yield ": rigctl events\n\n"
            while True:
                try:
                    line = await asyncio.wait_for(client.lines.get(), KEEPALIVE_S)
                except TimeoutError:
                    yield ": keep-alive\n\n"
                    continue
                if line is None:
                    yield ": the server is shutting down\n\n"
                    return
                yield line
        finally:
            self.close(client)

    def _pump(self) -> None:
        """The hub's thread: each event of the source formatted once and given to every client on its own loop."""
        while True:
            event = self._feed.get()
            line = None if event is None else self._fmt(event)
            with self._lock:
                if line is None:
                    self._ended = True
                by_loop: dict[asyncio.AbstractEventLoop, list[EventClient]] = {}
                for c in self._clients:
                    by_loop.setdefault(c.loop, []).append(c)
            for loop, clients in by_loop.items():
                with contextlib.suppress(RuntimeError):  # that loop has closed: its clients are gone with it
                    loop.call_soon_threadsafe(_deliver, clients, line)
            if line is None:
                return


def _deliver(clients: list[EventClient], line: str | None) -> None:
    for c in clients:
        c.put(line)
