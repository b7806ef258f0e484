"""The HTTP server of ``cellcal serve``: uvicorn's, with a shutdown that stops the cell first.

On SIGTERM or SIGINT uvicorn stops accepting, then waits for the open connections to end
before the app's lifespan stops anything; an event stream never ends by itself, so the robot
went on capturing while a listener stayed (issue 22). Here the first signal stops the robot at
once (``Runtime.halt``, from a thread: a device call must not run in a signal handler); the
shutdown then lets the motion jobs end their in-flight station and record their state (runs
``interrupted``, so ``resume`` continues them; validations ``failed``), ends every event stream
with its final event (``EventBus.close``) and only then waits for the connections, all within
one grace period counted from the signal. A second signal ends the process at once, and so
does the end of the grace period: a database that does not answer (a write lock held by
another process) held each step of the shutdown for its busy timeout, and a SIGTERM with a
listener took 50 s instead of 10, the listener's stream dropped without its final event.
The jobs get the grace period less ``_STREAMS_S``, which is kept for ending the streams.
"""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import socket
import threading
import time
from types import FrameType

import uvicorn
from fastapi import FastAPI

from service.runtime import Runtime

#: uvicorn's own logger: these lines belong with its start and shutdown lines.
log = logging.getLogger("uvicorn.error")

#: Default of ``cellcal serve --graceful-timeout``, seconds.
GRACEFUL_TIMEOUT_S = 10.0
#: Connections still open this long before the grace period ends are dropped, seconds.
_DROP_MARGIN_S = 1.0
#: Longest wait for queued events to be stored before the streams end, seconds.
_FLUSH_S = 5.0
#: The end of the grace period kept for ending the event streams after the jobs, seconds
#: (at most a quarter of the grace period).
_STREAMS_S = 3.0


class CellServer(uvicorn.Server):
    """uvicorn's server for ``app``, whose shutdown stops the robot before anything else."""

    def __init__(self, config: uvicorn.Config, app: FastAPI, *,
                 graceful_timeout: float = GRACEFUL_TIMEOUT_S) -> None:
        super().__init__(config)
        self.app = app
        self.graceful_timeout = graceful_timeout
        self._deadline: float | None = None  # end of the grace period, from the first signal

    def _runtime(self) -> Runtime | None:
        """The app's runtime once its lifespan has started."""
        return getattr(self.app.state, "runtime", None)

    def handle_exit(self, sig: int, frame: FrameType | None) -> None:
        """First signal: stop the robot now and begin the shutdown; second: exit at once."""
        if self._deadline is not None:
            log.warning("second signal %s: exiting at once", signal.Signals(sig).name)
            signal.signal(sig, signal.SIG_DFL)
            signal.raise_signal(sig)
            return
        self._deadline = time.monotonic() + self.graceful_timeout
        log.info("signal %s: stopping the robot, then shutting down (within %g s)",
                 signal.Signals(sig).name, self.graceful_timeout)
        timer = threading.Timer(self.graceful_timeout, self._exit_now, args=(sig,))
        timer.daemon = True
        timer.start()
        runtime = self._runtime()
        if runtime is not None:
            threading.Thread(target=runtime.halt, name="halt", daemon=True).start()
        super().handle_exit(sig, frame)

    async def shutdown(self, sockets: list[socket.socket] | None = None) -> None:
        """Stop the jobs, end the event streams, then let uvicorn close the connections in
        what is left of the grace period; near its end the connections still open are
        dropped (not their tasks cancelled, which would answer a request in progress 500)."""
        if self._deadline is None:  # stopped without a signal
            self._deadline = time.monotonic() + self.graceful_timeout
        runtime = self._runtime()
        margin = min(_DROP_MARGIN_S, self.graceful_timeout / 4)
        if runtime is not None:
            streams = min(_STREAMS_S, self.graceful_timeout / 4)
            await asyncio.to_thread(runtime.stop_jobs, max(0.0, self._left() - streams))
            await asyncio.to_thread(runtime.events.close,
                                    min(_FLUSH_S, max(0.0, self._left() - 2 * margin)))
        dropper = asyncio.get_running_loop().call_later(max(self._left() - margin, 0.0),
                                                        self._drop_connections)
        self.config.timeout_graceful_shutdown = max(self._left(), margin)
        try:
            await super().shutdown(sockets)
        finally:
            dropper.cancel()

    def _exit_now(self, sig: int) -> None:
        """The grace period is over and the process still runs (a step of the shutdown waits
        for a database that does not answer): the signal again, which ends it at once (a
        timer thread cannot reset a handler). The robot was stopped at the first signal;
        what a job had not stored, a restart recovers."""
        log.warning("grace period over before the shutdown ended: exiting now")
        os.kill(os.getpid(), sig)

    def _drop_connections(self) -> None:
        """Abort the connections still open (a client that sends or reads nothing)."""
        connections = list(self.server_state.connections)
        if connections:
            log.warning("grace period over: dropping %d connection(s)", len(connections))
        for connection in connections:
            connection.transport.abort()

    def _left(self) -> float:
        assert self._deadline is not None
        return max(0.0, self._deadline - time.monotonic())
