"""Bounded connections: idle and slow clients cannot take the file descriptors that capture
and the database need (issue 22, row 2).

uvicorn accepts every connection and keeps one that never sends a request for good: 1,100
idle TCP connections under the usual limit of 1,024 open files starved ``/health`` and failed
a running capture with ``Errno 24``, and each refused ``accept`` logged a traceback. Here:

* at start the soft open-files limit is raised to the hard one (``raise_fd_limit``);
* a connection must send each request's headers within ``header_timeout_s`` of its opening
  or of the previous answer (idle keep-alive connections are closed sooner by uvicorn);
* a client that stops reading its answer (the server's send buffer full: a slow-read client
  asking for the 1 MB API documentation bundle on a tiny receive window) is closed after
  ``send_timeout_s`` without progress, and meanwhile counts as idle for the cap: such
  answers never complete, so 1,100 of them kept every connection busy and ``/health`` was
  refused 503;
* at most ``cap`` connections are open, ``fd_reserve`` descriptors below the limit. A
  connection beyond the cap takes the place of the oldest one with no request in progress (an
  idle client is worth least), or, when every connection is busy, is answered 503 and closed
  at once;
* a request's headers may take at most ``MAX_HEADER_BYTES``; beyond, the answer is 431 and
  the connection is closed;
* what is refused, dropped or timed out is logged at most once per ``LOG_INTERVAL_S`` with
  counts (``RateLimitFilter``; also on asyncio's accept errors and uvicorn's invalid requests).

The guard works on either of uvicorn's HTTP/1.1 protocols: ``httptools`` (llhttp, in C) when it
is installed, as it is with cellcal, else ``h11`` (pure Python). Under the history benchmark's
GETs h11's parsing and writing were about a quarter of the server's CPU per request.
"""

from __future__ import annotations

import asyncio
import json
import logging
import resource
import time
from dataclasses import dataclass, field
from typing import Any

from uvicorn.protocols.http.h11_impl import H11Protocol

try:
    from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
except ImportError:  # httptools not installed: h11 only
    HttpToolsProtocol = None  # type: ignore[assignment,misc]

#: Under uvicorn's logger, so the lines come with its own (and its handler).
log = logging.getLogger("uvicorn.error.connections")

#: Connections accepted in one go (asyncio accepts up to the listen backlog in one loop
#: iteration before any of them is seen), and the kernel's queue of connections not yet
#: accepted.
ACCEPT_BURST = 100
#: Accept bursts open beyond the cap at worst: a connection accepted in one iteration is
#: admitted (its victim aborted) two iterations later and the victim's socket closes in the
#: third, while each of those iterations accepts a burst. Measured: 248 over a cap of 724
#: during a flood of 1,100 (sampled, so a lower bound); CI once hit ``Errno 24`` with a
#: reserve of one burst plus 200.
BURSTS_IN_FLIGHT = 3
#: Open files kept for everything but connections: the accept bursts in flight, and the
#: database, images, devices and worker pipes (13 during a capture, 128 kept).
FD_RESERVE = BURSTS_IN_FLIGHT * ACCEPT_BURST + 128
#: The cap never goes below this (a tiny open-files limit still serves a few clients).
MIN_CAP = 16
#: At most one log line per message and this many seconds; the rest are counted.
LOG_INTERVAL_S = 10.0
#: A refused connection is closed when its client closes, or after this many seconds.
REFUSAL_LINGER_S = 1.0
#: A request's headers beyond this many bytes are refused (h11's own bound, which llhttp lacks).
MAX_HEADER_BYTES = 16 * 1024


def _json_answer(status: str, detail: str, code: str, *headers: str) -> bytes:
    """A whole HTTP/1.1 answer that closes the connection, with the JSON error body of every
    error (``{"detail", "code"}``)."""
    body = json.dumps({"detail": detail, "code": code}).encode()
    head = [f"HTTP/1.1 {status}", "content-type: application/json", *headers,
            "connection: close", f"content-length: {len(body)}"]
    return ("\r\n".join(head) + "\r\n\r\n").encode() + body


#: What a refused connection is told.
REFUSAL_RESPONSE = _json_answer("503 Service Unavailable",
                                "Too many connections are busy; retry in a few seconds.",
                                "too_many_connections", "retry-after: 5")
HEADERS_TOO_LARGE_RESPONSE = _json_answer(
    "431 Request Header Fields Too Large",
    f"The request's headers exceed {MAX_HEADER_BYTES} bytes.", "headers_too_large")
#: What a request the HTTP parser cannot read is told (uvicorn's own answer is plain text).
INVALID_REQUEST_RESPONSE = _json_answer(
    "400 Bad Request", "Invalid HTTP request: its request line or a header cannot be parsed "
    "(e.g. a NUL byte, a bare CR or a space in a header name).", "invalid_http")


def raise_fd_limit() -> int:
    """Raise this process's soft open-files limit to the hard limit; the limit now."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    target = hard if hard != resource.RLIM_INFINITY else max(soft, 1 << 20)
    if soft != resource.RLIM_INFINITY and soft < target:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
        except (ValueError, OSError) as exc:
            log.warning("open files: could not raise the limit from %d to %d (%s)", soft,
                        target, exc)
            return soft
        log.info("open files: soft limit raised from %d to the hard limit %d", soft, target)
        return target
    log.info("open files: limit %d (soft = hard)", soft)
    return soft


def connection_cap(fd_limit: int, wanted: int) -> int:
    """At most ``wanted`` connections, and ``FD_RESERVE`` descriptors left for the rest."""
    cap = max(min(wanted, MIN_CAP), min(wanted, fd_limit - FD_RESERVE))
    log.info("connections: at most %d open at once", cap)
    return cap


@dataclass
class ConnectionLimits:
    """What a connection may take: ``cap`` connections open at once, ``header_timeout_s``
    until the first request's headers are in, ``send_timeout_s`` with its answer unread."""

    cap: int
    header_timeout_s: float
    send_timeout_s: float = 30.0
    #: The open connections in the order they came (a dict as an ordered set): oldest first.
    opened: dict[ConnectionGuard, None] = field(default_factory=dict)

    def admit(self, new: ConnectionGuard) -> bool:
        """Make room for ``new`` (True), or refuse it (False: every connection is busy)."""
        if len(self.opened) < self.cap:
            self.opened[new] = None
            return True
        victim = next((c for c in self.opened if c.idle() or c.stalled()), None)
        if victim is None:
            log.warning("%d connections, all busy: a new connection was answered 503",
                        self.cap)
            return False
        log.warning("%d connections: the oldest idle one was closed for a new one",
                    self.cap)
        victim.drop()
        self.opened[new] = None
        return True


class ConnectionGuard:
    """Mixed in before one of uvicorn's HTTP/1.1 protocols, it puts that protocol's
    connections under ``limits`` (set by ``guarded_protocol``). Uses what both protocols have:
    ``transport``, ``loop``, ``cycle`` (the request in progress or last answered) and their
    asyncio callbacks."""

    limits: ConnectionLimits
    transport: asyncio.Transport
    loop: asyncio.AbstractEventLoop
    cycle: Any

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._refused = False
        self._header_bytes = 0  # received since the last answer, no request's headers yet
        self._timer: asyncio.TimerHandle | None = None
        self._answered: Any = None  # the request cycle before the headers awaited now
        self._stall: asyncio.TimerHandle | None = None  # running while the client reads nothing

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)  # type: ignore[misc]
        if not self.limits.admit(self):
            # answer, then half-close and read what the client sent until it closes (closing
            # with its request unread would reset the connection before it reads the 503)
            self._refused = True
            transport.write(REFUSAL_RESPONSE)
            if transport.can_write_eof():
                transport.write_eof()
            self._timer = self.loop.call_later(REFUSAL_LINGER_S, transport.abort)
            return
        self._await_headers()

    def on_response_complete(self) -> None:
        super().on_response_complete()  # type: ignore[misc]
        if not self.transport.is_closing():  # kept alive: the next request's headers are due
            self._await_headers()

    def _await_headers(self) -> None:
        """Drop the connection unless a new request's headers are in within the timeout
        (uvicorn's keep-alive timer stops at the first byte, so a client sending one byte at
        a time would hold the connection for good)."""
        if self._timer is not None:
            self._timer.cancel()
        self._answered = self.cycle
        self._header_bytes = 0
        self._timer = self.loop.call_later(self.limits.header_timeout_s, self._header_timeout)

    def data_received(self, data: bytes) -> None:
        if self._refused:
            return
        super().data_received(data)  # type: ignore[misc]
        if self.cycle is not self._answered or self.transport.is_closing():
            return  # a request's headers are in (or the protocol closed the connection)
        self._header_bytes += len(data)  # all of it belongs to headers still incomplete
        if self._header_bytes > MAX_HEADER_BYTES:
            log.warning("a request's headers exceeded %d bytes: answered 431, closed",
                        MAX_HEADER_BYTES)
            self.transport.write(HEADERS_TOO_LARGE_RESPONSE)
            self.transport.close()

    def send_400_response(self, msg: str) -> None:
        """A request the parser rejects gets the JSON error body (uvicorn logs ``msg``)."""
        self.transport.write(INVALID_REQUEST_RESPONSE)
        self.transport.close()

    def eof_received(self) -> bool | None:
        if self._refused:
            self.transport.close()
        return super().eof_received()  # type: ignore[misc]

    def pause_writing(self) -> None:
        """The client reads nothing of the answer (the send buffer is full): closed unless it
        reads again within ``send_timeout_s``."""
        super().pause_writing()  # type: ignore[misc]
        if self._stall is None:
            self._stall = self.loop.call_later(self.limits.send_timeout_s, self._send_timeout)

    def resume_writing(self) -> None:
        if self._stall is not None:
            self._stall.cancel()
            self._stall = None
        super().resume_writing()  # type: ignore[misc]

    def connection_lost(self, exc: Exception | None) -> None:
        self.limits.opened.pop(self, None)
        for timer in (self._timer, self._stall):
            if timer is not None:
                timer.cancel()
        super().connection_lost(exc)  # type: ignore[misc]

    def idle(self) -> bool:
        """True while no request is in progress (none yet, or between requests)."""
        return self.cycle is None or self.cycle.response_complete

    def stalled(self) -> bool:
        """True while the client reads none of its answer."""
        return self._stall is not None

    def drop(self) -> None:
        """Close the connection now, without waiting to write anything."""
        self.limits.opened.pop(self, None)
        self.transport.abort()

    def _header_timeout(self) -> None:
        self._timer = None
        if self.cycle is self._answered and self.idle() and not self.transport.is_closing():
            log.warning("a connection sent no complete request in %g s: closed",
                        self.limits.header_timeout_s)
            self.drop()

    def _send_timeout(self) -> None:
        self._stall = None
        log.warning("a client read none of its answer in %g s: closed",
                    self.limits.send_timeout_s)
        self.drop()


class GuardedH11(ConnectionGuard, H11Protocol):
    """h11's protocol under the guard."""


if HttpToolsProtocol is not None:
    class GuardedHttpTools(ConnectionGuard, HttpToolsProtocol):
        """httptools' protocol under the guard."""


def guarded_protocol(limits: ConnectionLimits, *, parser: str = "auto") -> type[ConnectionGuard]:
    """The protocol class for ``uvicorn.Config(http=...)`` under ``limits``: ``parser``
    ``httptools`` or ``h11``; ``auto``, httptools when it is installed."""
    if parser == "auto":
        parser = "h11" if HttpToolsProtocol is None else "httptools"
    base: type[ConnectionGuard] = GuardedHttpTools if parser == "httptools" else GuardedH11
    return type(base.__name__, (base,), {"limits": limits})


class RateLimitFilter(logging.Filter):
    """Passes each message (by its format string) at most once per ``interval`` s; the next
    one passed says how many were held back meanwhile."""

    def __init__(self, interval: float = LOG_INTERVAL_S, *,
                 only: tuple[str, ...] | None = None) -> None:
        super().__init__()
        self.interval = interval
        self.only = only  # message prefixes limited; None: all
        self._last: dict[str, float] = {}
        self._held: dict[str, int] = {}

    def filter(self, record: logging.LogRecord) -> bool:
        key = str(record.msg).split("\n", 1)[0]  # asyncio's messages go on with details
        if self.only is not None and not key.startswith(self.only):
            return True
        now = time.monotonic()
        if now - self._last.get(key, -self.interval) < self.interval:
            self._held[key] = self._held.get(key, 0) + 1
            return False
        self._last[key] = now
        if held := self._held.pop(key, 0):
            record.msg = f"{record.msg} (and {held} more like this in {self.interval:g} s)"
        return True


def limit_connection_logs() -> None:
    """Rate-limit the log lines a flood of connections makes: ours, asyncio's accept errors
    (``socket.accept() out of system resource``), uvicorn's invalid requests."""
    log.addFilter(RateLimitFilter())
    logging.getLogger("asyncio").addFilter(RateLimitFilter())
    logging.getLogger("uvicorn.error").addFilter(
        RateLimitFilter(only=("Invalid HTTP request",)))
