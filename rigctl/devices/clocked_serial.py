"""pymodbus' serial client with its answer wait timed on a simulated rig's shared clock
(:class:`rigctl.core.shared_clock.SharedClock`, docs/architecture.md "Time on a simulated rig").

pymodbus waits for an answer on the wall clock (``timeout`` s, then pyserial's blocking read). On a simulated rig the
boards run on simulated time, which stands still while the host is starved: an answer timeout judged on the wall
clock then fires although the board has had no time to answer. Here the wait is the same (data that has stopped
growing is an answer, or ``timeout`` passes) on the shared clock, and each request is a sign of the host's life (the
boards may run on past it by the clock's lead only). An answer's wait also lasts at least :data:`ANSWER_MIN_WALL_S`
of wall time: the board's server is a thread of a simulator (or a simavr process) that a loaded machine can starve
while the world, run faster than real time, would pass the whole timeout in a fraction of that (beside four CPU hogs
an unpaced rig timed out three answers in a row and its controller latched WATCHDOG); meanwhile the world stands at
the deadline.
"""

from __future__ import annotations

from typing import Any

from pymodbus.client import ModbusSerialClient

from rigctl.core.shared_clock import SharedClock

__all__ = ["ClockedSerialClient", "ANSWER_MIN_WALL_S"]

#: the least wall time an answer's wait takes before it gives up, s (a timeout on the shared clock that a paced rig
#: spends anyway; an unpaced one no longer gives up on a board its machine has not let run)
ANSWER_MIN_WALL_S = 0.5


class ClockedSerialClient(ModbusSerialClient):
    """:class:`pymodbus.client.ModbusSerialClient` whose answer timeout (``timeout``, s) is of ``clock`` time.

    Parameters: pymodbus' own, and ``clock`` (keyword): the simulated rig's shared clock."""

    def __init__(self, *args: Any, clock: SharedClock, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.clock = clock

    def _waiting(self) -> int:
        """Bytes waiting on the port."""
        return int(self.socket.in_waiting) if self.socket else 0

    def send(self, request: bytes, addr: tuple[Any, ...] | None = None) -> int:
        # stamped before the write: the board's side knows it is on the way (taken back if the write raises)
        with self.clock.writing(self.comm_params.host, len(request)):
            if self._waiting():  # pymodbus drops what waits before it sends
                self.note_taken()
            return super().send(request, addr)

    def _wait_for_data(self) -> int:
        """Bytes waiting once they have stopped growing (two looks in a row the same, as pymodbus' wait), or what is
        there when ``timeout`` s of the shared clock have passed."""
        seen = [0, False]  # bytes at the last look; whether any came

        def settled() -> bool:
            available = self._waiting()
            if seen[1] and available == seen[0]:
                return True
            if available and available != seen[0]:
                seen[0], seen[1] = available, True
            return False

        # looked at as often as pymodbus' own wait looks (its receive interval: 4 character times, at least 1 ms)
        port, in_flight = self.comm_params.host, self.clock.in_flight
        self.clock.wait_for(settled, float(self.comm_params.timeout_connect or 0.0), max_step_s=self._recv_interval,
                            min_wall_s=ANSWER_MIN_WALL_S,
                            in_flight=None if in_flight is None else (lambda: in_flight(port)))
        return self._waiting()

    def note_taken(self) -> None:
        """The host is about to take or drop what waits on the port (a flush of its input): as a read, for the board's
        side (:meth:`rigctl.core.shared_clock.SharedClock.note_read`)."""
        self.clock.note_read(self.comm_params.host)

    def recv(self, size: int | None) -> bytes:
        """What has come, up to ``size`` bytes (None: all), after :meth:`_wait_for_data`; never a blocking read
        (pyserial's would wait on the wall clock)."""
        if not self.socket:
            return super().recv(size)  # (raises ConnectionException)
        available = self._wait_for_data() if size is None or size > self._waiting() else size
        if available:  # before the read: the board's side knows the reply reached us
            self.note_taken()
        self.clock.touch()
        take = available if size is None else min(size, available)
        return bytes(self.socket.read(take)) if take > 0 else b""
