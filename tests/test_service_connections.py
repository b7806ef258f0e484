"""Bounded connections (issue 22, row 2) against real ``cellcal serve --mock`` subprocesses:
1,100 idle TCP connections under an open-files limit of 1,024 leave ``/health`` answering and
a capture completing; a connection that sends no request is closed after the header timeout;
beyond the connection cap the oldest idle connection makes room, and when every connection
is busy the new one is answered 503 with the JSON error body. Waits are for conditions,
bounded only against a hang."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import resource
import socket
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import uvicorn
from uvicorn.server import ServerState

from service.serving.connections import (
    FD_RESERVE,
    MAX_HEADER_BYTES,
    ConnectionLimits,
    guarded_protocol,
)
from service.serving.local import LocalService, ServeOptions, local_service
from tests.support.helpers import wait_for
from tests.support.service import finished

KEY = "connections-key-0123456789abcdef"
AUTH = {"Authorization": f"Bearer {KEY}"}
HANG_S = 120.0
#: The systemd default soft limit, imposed on the service under test.
FD_LIMIT = 1024
IDLE_CONNECTIONS = 1100

pytestmark = pytest.mark.timeout(600)


def _limit_open_files() -> None:
    """In the service's process: at most ``FD_LIMIT`` open files (hard), and a soft limit
    below it for the service to raise."""
    resource.setrlimit(resource.RLIMIT_NOFILE, (FD_LIMIT // 2, FD_LIMIT))


@contextlib.contextmanager
def _own_fd_limit(needed: int) -> Iterator[None]:
    """Enough open files in this test process for ``needed`` sockets (restored after)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and hard < needed:
        pytest.skip(f"the hard open-files limit {hard} is below {needed}")
    resource.setrlimit(resource.RLIMIT_NOFILE, (max(soft, needed), hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))


@contextlib.contextmanager
def _sockets() -> Iterator[list[socket.socket]]:
    """A list of sockets, every one closed at the end whatever happens."""
    held: list[socket.socket] = []
    try:
        yield held
    finally:
        for sock in held:
            sock.close()


def _address(service: LocalService) -> tuple[str, int]:
    url = httpx.URL(service.url)
    assert url.host and url.port
    return url.host, url.port


def _closed_by_peer(sock: socket.socket) -> bool:
    """Wait until the service closes ``sock`` (True), or ``HANG_S`` pass (False)."""
    sock.settimeout(HANG_S)
    try:
        while sock.recv(4096):
            pass
    except TimeoutError:
        return False
    except ConnectionResetError:
        return True
    return True


def test_idle_flood_leaves_health_and_capture_working(tmp_path: Path) -> None:
    options = ServeOptions(preexec=_limit_open_files)
    with (_own_fd_limit(IDLE_CONNECTIONS + 256),
          local_service(tmp_path / "data", KEY, options) as service, _sockets() as idle):
        fds = Path(f"/proc/{service.proc.pid}/fd")
        began = time.monotonic()
        for _ in range(IDLE_CONNECTIONS):
            idle.append(socket.create_connection(_address(service), timeout=HANG_S))
        health = httpx.get(f"{service.url}/health", timeout=HANG_S)
        run = httpx.post(f"{service.url}/runs", json={"stations": 4}, headers=AUTH,
                         timeout=HANG_S)
        assert run.status_code == 201, run.text
        path = f"{service.url}/runs/{run.json()['id']}"  # a new connection each poll
        final = wait_for(path, lambda: httpx.get(path, headers=AUTH, timeout=HANG_S).json(),
                         5 * HANG_S, until=finished)
        open_fds = len(list(fds.iterdir()))
        log = service.log.read_text()
        took = time.monotonic() - began
    assert health.status_code == 200 and health.json()["status"] == "ok"
    assert final["state"] == "done" and final["stations_captured"] == 4, final
    assert open_fds < FD_LIMIT
    assert "Too many open files" not in log and "out of system resource" not in log
    assert "open files: soft limit raised from 512 to the hard limit 1024" in log
    assert f"at most {FD_LIMIT - FD_RESERVE} open at once" in log
    # evictions are logged, but at most once per 10 s (over 300 happened)
    lines = [ln for ln in log.splitlines() if "the oldest idle one was closed" in ln]
    assert 1 <= len(lines) <= 1 + took / 10, (took, lines)
    assert "more like this" in "".join(lines[1:]) or len(lines) == 1


@pytest.fixture(scope="module")
def header_timeout_service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LocalService]:
    """One service with a 1 s header timeout for the tests below, whose connections are
    their own (each waits for its own sockets to be closed)."""
    options = ServeOptions(env={**os.environ, "CELLCAL_HEADER_TIMEOUT_S": "1"})
    with local_service(tmp_path_factory.mktemp("header") / "data", KEY, options) as service:
        yield service


def test_a_connection_without_a_request_is_closed(header_timeout_service: LocalService) -> None:
    service = header_timeout_service
    with _sockets() as held:
        silent = socket.create_connection(_address(service), timeout=HANG_S)
        slow = socket.create_connection(_address(service), timeout=HANG_S)
        held += [silent, slow]
        slow.sendall(b"GET /health HTTP/1.1\r\nHost: x\r\n")  # the headers never end
        assert _closed_by_peer(silent) and _closed_by_peer(slow)
        assert httpx.get(f"{service.url}/health", timeout=HANG_S).status_code == 200


def test_a_client_trickling_its_next_request_is_closed(
        header_timeout_service: LocalService) -> None:
    """After an answer on a kept-alive connection, the next request's headers come one byte
    at a time (each byte restarts uvicorn's keep-alive timer): the header timeout ends it."""
    service = header_timeout_service
    with _sockets() as held:
        sock = socket.create_connection(_address(service), timeout=HANG_S)
        held.append(sock)
        sock.sendall(b"GET /health HTTP/1.1\r\nHost: x\r\n\r\n")
        assert sock.recv(4096).startswith(b"HTTP/1.1 200")
        sock.settimeout(0.2)

        def closed_after_one_more_byte() -> bool:
            try:
                sock.sendall(b"X")
                return sock.recv(4096) == b""
            except TimeoutError:
                return False
            except (BrokenPipeError, ConnectionResetError):
                return True
        wait_for("the trickling connection to be closed", closed_after_one_more_byte, HANG_S)


class _FullTransport(asyncio.Transport):
    """A client's connection whose send buffer fills with the first body bytes and is never
    read (what a slow-read client makes of a large answer, whatever the kernel buffers)."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        super().__init__()
        self.loop, self.protocol, self.aborted, self.closing = loop, None, False, False

    def get_extra_info(self, name: str, default: Any = None) -> Any:
        return {"peername": ("127.0.0.1", 40000), "sockname": ("127.0.0.1", 8000)}.get(
            name, default)

    def write(self, data: Any) -> None:
        if not self.closing and b"HTTP/1.1" not in bytes(data)[:9]:  # body: the buffer is full
            self.protocol.pause_writing()

    def is_closing(self) -> bool:
        return self.closing

    def close(self) -> None:
        self.abort()

    def abort(self) -> None:
        if not self.closing:
            self.closing = self.aborted = True
            self.loop.call_soon(self.protocol.connection_lost, None)

    def can_write_eof(self) -> bool:
        return False

    def pause_reading(self) -> None: ...

    def resume_reading(self) -> None: ...


async def _big_answer(scope: Any, receive: Any, send: Any) -> None:
    """An ASGI app answering every request with a body sent in two chunks."""
    await send({"type": "http.response.start", "status": 200, "headers": []})
    await send({"type": "http.response.body", "body": b"x" * 65536, "more_body": True})
    await send({"type": "http.response.body", "body": b"x" * 65536})


@pytest.mark.parametrize("parser", ["httptools", "h11"])
def test_a_client_reading_none_of_its_answer_is_closed_and_makes_room(parser: str) -> None:
    """A slow-read client (issue 22, a variant of row 2): 1,100 clients that read none of a
    1.5 MB answer kept every connection busy, and /health was refused 503 for ~15 s. Such a
    connection counts as idle for the cap, and the send timeout closes it."""
    async def scenario() -> None:
        loop = asyncio.get_running_loop()
        limits = ConnectionLimits(cap=1, header_timeout_s=60.0, send_timeout_s=3600.0)
        config = uvicorn.Config(_big_answer, log_level="critical", lifespan="off")
        config.load()

        def connect() -> tuple[Any, _FullTransport]:
            protocol = guarded_protocol(limits, parser=parser)(
                config=config, server_state=ServerState(), app_state={})
            transport = _FullTransport(loop)
            transport.protocol = protocol
            protocol.connection_made(transport)
            return protocol, transport

        stalled, first = connect()
        stalled.data_received(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")
        while not stalled.stalled():  # the app's first body chunk fills the buffer
            await asyncio.sleep(0)
        assert not stalled.idle()  # its answer never completes
        second, other = connect()  # beyond the cap: the stalled one makes room
        assert first.aborted and not other.aborted
        assert list(limits.opened) == [second]
        limits.send_timeout_s = 0.01  # and on its own, the send timeout closes it
        second.data_received(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")
        while not other.aborted:
            await asyncio.sleep(0.01)
        assert not limits.opened

    asyncio.run(asyncio.wait_for(scenario(), HANG_S))


def _open_stream(service: LocalService, run_id: str) -> socket.socket:
    """A connection following the run's event stream (busy until the run ends)."""
    sock = socket.create_connection(_address(service), timeout=HANG_S)
    sock.sendall(f"GET /runs/{run_id}/events HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer "
                 f"{KEY}\r\n\r\n".encode())
    head = b""
    while b"event: state" not in head:
        chunk = sock.recv(4096)
        assert chunk, head
        head += chunk
    assert head.startswith(b"HTTP/1.1 200"), head
    return sock


def test_beyond_the_cap_idle_connections_make_room_busy_ones_do_not(tmp_path: Path) -> None:
    options = ServeOptions(env={**os.environ, "CELLCAL_MAX_CONNECTIONS": "3"})
    with local_service(tmp_path / "data", KEY, options) as service, _sockets() as held:
        run_id = httpx.post(f"{service.url}/runs", json={"stations": 200}, headers=AUTH,
                            timeout=HANG_S).json()["id"]
        httpx.post(f"{service.url}/runs/{run_id}/pause", headers=AUTH, timeout=HANG_S)
        held += [_open_stream(service, run_id), _open_stream(service, run_id)]
        idle = socket.create_connection(_address(service), timeout=HANG_S)
        held.append(idle)
        # the cap is reached; the idle connection makes room for the new request
        assert httpx.get(f"{service.url}/health", timeout=HANG_S).status_code == 200
        assert _closed_by_peer(idle)
        held.append(_open_stream(service, run_id))  # now three busy connections
        refused = httpx.get(f"{service.url}/health", timeout=HANG_S)
        assert refused.status_code == 503
        assert refused.json()["code"] == "too_many_connections"
        assert refused.headers["retry-after"] == "5"
        held.pop().close()  # a stream ends: its place is free again
        r = wait_for("the freed place", lambda: httpx.get(f"{service.url}/health", timeout=HANG_S),
                     HANG_S, until=lambda r: r.status_code != 503)
        assert r.status_code == 200


def test_headers_beyond_the_bound_are_answered_431_and_closed(
        header_timeout_service: LocalService) -> None:
    """A request whose headers pass ``MAX_HEADER_BYTES`` gets the JSON error body and the
    connection is closed (llhttp, unlike h11, sets no bound of its own); others are served."""
    service = header_timeout_service
    with _sockets() as held:
        sock = socket.create_connection(_address(service), timeout=HANG_S)
        held.append(sock)
        sock.sendall(b"GET /health HTTP/1.1\r\nHost: x\r\n")
        answer = b""
        with contextlib.suppress(BrokenPipeError, ConnectionResetError):
            for _ in range(2 * MAX_HEADER_BYTES // 1000):
                sock.sendall(b"X-Pad: " + b"a" * 991 + b"\r\n")
        with contextlib.suppress(ConnectionResetError):
            while chunk := sock.recv(4096):
                answer += chunk
        head, _, body = answer.partition(b"\r\n\r\n")
        assert head.startswith(b"HTTP/1.1 431"), answer[:200]
        assert json.loads(body)["code"] == "headers_too_large"
    assert httpx.get(f"{service.url}/health", timeout=HANG_S).status_code == 200


@pytest.mark.parametrize("request_bytes", [
    b"GET /health HTTP/1.1\r\nHost: x\r\nX-Tag: a\x00b\r\n\r\n",  # a NUL in a header
    b"GET /health HTTP/1.1\r\nHo st: x\r\n\r\n",  # a space in a header name
    b"\x16\x03\x01\x02\x00\x01\x00\x01\xfc\x03\x03\r\n\r\n"])  # TLS spoken to plain HTTP
def test_a_request_the_parser_rejects_gets_the_json_error_body(
        header_timeout_service: LocalService, request_bytes: bytes) -> None:
    """uvicorn answers an unparsable request in plain text; here it is the JSON error body
    of every error, and the connection is closed."""
    service = header_timeout_service
    with _sockets() as held:
        sock = socket.create_connection(_address(service), timeout=HANG_S)
        held.append(sock)
        sock.sendall(request_bytes)
        answer = b""
        with contextlib.suppress(ConnectionResetError):
            while chunk := sock.recv(4096):
                answer += chunk
        head, _, body = answer.partition(b"\r\n\r\n")
        assert head.startswith(b"HTTP/1.1 400"), answer[:200]
        assert b"content-type: application/json" in head.lower()
        assert json.loads(body)["code"] == "invalid_http"
    assert httpx.get(f"{service.url}/health", timeout=HANG_S).status_code == 200


def test_the_service_parses_http_with_httptools() -> None:
    """httptools is a dependency: the guarded protocol is uvicorn's httptools one."""
    from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

    limits = ConnectionLimits(cap=10, header_timeout_s=1.0)
    assert issubclass(guarded_protocol(limits), HttpToolsProtocol)
    assert not issubclass(guarded_protocol(limits, parser="h11"), HttpToolsProtocol)
