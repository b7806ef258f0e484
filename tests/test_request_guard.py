"""Key and body size checked before a body is read (issue 11), against ``cellcal serve`` in a
uvicorn subprocess: a 60 MB body without key used to be parsed first (5.7-12.7 s, +0.8-1.1 GB).

The client is a raw socket that sends the body while watching for an answer, so "answered
before the body was read" is observable: the answer arrives while most of the body is unsent.
Server memory is its peak RSS (``VmHWM``, reset through ``clear_refs`` before the request).
"""

from __future__ import annotations

import json
import os
import select
import socket
from collections.abc import Iterator
from pathlib import Path
from urllib.parse import urlsplit

import pytest

from service.serving.local import LocalService, ServeOptions, local_service

KEY = "guard-key-0123456789abcdef"
BODY_BYTES = 60_000_000
#: Extra server memory a refused request may cost (issue 11 acceptance), bytes.
EXTRA_MEMORY = 50e6
CHUNK = 1 << 16


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LocalService]:
    data = tmp_path_factory.mktemp("guard") / "data"
    env = {**os.environ, "CELLCAL_MAX_BODY_BYTES": str(4 * 2**20)}
    with local_service(data, KEY, ServeOptions(env=env)) as s:
        yield s


def _status_kb(pid: int, field: str) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return float(line.split()[1])
    raise AssertionError(f"no {field} in /proc/{pid}/status")


def _body(n: int) -> Iterator[bytes]:
    """``n`` bytes of one JSON document, ``{"poses": [[0.1, ...], ...]}``, in chunks."""
    head, tail = b'{"poses": [', b"[0.1]]}"
    yield head
    item = b"[0.1, 0.2, 0.3, 0.0, 0.0, 0.0], "
    full, rest = divmod(n - len(head) - len(tail), len(item))
    block = item * (CHUNK // len(item))
    for _ in range(full // (CHUNK // len(item))):
        yield block
    yield item * (full % (CHUNK // len(item))) + b" " * rest + tail


def _chunked(parts: Iterator[bytes]) -> Iterator[bytes]:
    for part in parts:
        yield f"{len(part):x}\r\n".encode() + part + b"\r\n"
    yield b"0\r\n\r\n"


def post_streaming(url: str, path: str, headers: dict[str, str],
                   body: Iterator[bytes]) -> tuple[int, dict, int]:
    """POST ``body`` over a raw socket, stopping as soon as an answer arrives.

    Returns the status, the JSON answer and how many body bytes were sent before it came. The
    server closes the connection with body bytes unread, so the end of the answer may come as
    a reset instead of an orderly close: the answer is complete once its Content-Length is in.
    """
    host, port = urlsplit(url).hostname, urlsplit(url).port
    head = "".join(f"{k}: {v}\r\n" for k, v in {"Host": f"{host}:{port}",
                                                  "Content-Type": "application/json",
                                                  "Connection": "close", **headers}.items())
    sent = 0
    with socket.create_connection((host, port), timeout=30) as sock:
        sock.sendall(f"POST {path} HTTP/1.1\r\n{head}\r\n".encode())
        pending = b""
        parts = iter(body)
        while True:  # send while nothing has come back, never blocking in a send
            readable, writable, _ = select.select([sock], [sock], [], 30)
            if readable:
                break
            if writable:
                pending = pending or next(parts, b"")
                if not pending:
                    break
                try:
                    n = sock.send(pending)
                except (BrokenPipeError, ConnectionResetError):
                    break
                sent, pending = sent + n, pending[n:]
        return (*_read_answer(sock), sent)


def _read_answer(sock: socket.socket) -> tuple[int, dict]:
    """Status and JSON body of an HTTP/1.1 answer with a Content-Length."""
    answer = b""
    while not _complete(answer):
        try:
            chunk = sock.recv(CHUNK)
        except ConnectionResetError:
            break
        if not chunk:
            break
        answer += chunk
    status_line, _, rest = answer.partition(b"\r\n")
    _, _, payload = rest.partition(b"\r\n\r\n")
    return int(status_line.split()[1]), json.loads(payload)


def _complete(answer: bytes) -> bool:
    head, sep, payload = answer.partition(b"\r\n\r\n")
    if not sep:
        return False
    for line in head.split(b"\r\n")[1:]:
        name, _, value = line.partition(b":")
        if name.strip().lower() == b"content-length":
            return len(payload) >= int(value)
    return False


def _reset_peak(pid: int) -> float:
    """Reset the process's peak RSS to its current RSS; return that, bytes."""
    Path(f"/proc/{pid}/clear_refs").write_text("5")
    return _status_kb(pid, "VmRSS") * 1024


def _extra_peak(pid: int, before: float) -> float:
    return _status_kb(pid, "VmHWM") * 1024 - before


@pytest.mark.parametrize("headers", [{}, {"Authorization": "Bearer wrong-key-0123456789"}])
def test_sixty_megabytes_without_key_are_refused_unread(service, headers):
    before = _reset_peak(service.proc.pid)
    status, doc, sent = post_streaming(service.url, "/runs",
                                       {"Content-Length": str(BODY_BYTES), **headers},
                                       _body(BODY_BYTES))
    assert status == 401
    assert doc["code"] in ("unauthorized", "invalid_api_key") and doc["detail"]
    assert sent < BODY_BYTES / 2, "the answer waited for the body"
    extra = _extra_peak(service.proc.pid, before)
    assert extra < EXTRA_MEMORY, f"server peak RSS grew by {extra / 1e6:.0f} MB"


def test_declared_length_beyond_the_limit_is_413_unread(service):
    before = _reset_peak(service.proc.pid)
    status, doc, sent = post_streaming(
        service.url, "/runs", {"Content-Length": str(BODY_BYTES),
                               "Authorization": f"Bearer {KEY}"}, _body(BODY_BYTES))
    assert status == 413
    assert doc == {"detail": f"Request body larger than {4 * 2**20} bytes "
                             "(CELLCAL_MAX_BODY_BYTES).", "code": "payload_too_large"}
    assert sent < BODY_BYTES / 2
    assert _extra_peak(service.proc.pid, before) < EXTRA_MEMORY


def test_chunked_body_is_cut_off_at_the_limit(service):
    before = _reset_peak(service.proc.pid)
    status, doc, sent = post_streaming(
        service.url, "/runs", {"Transfer-Encoding": "chunked",
                               "Authorization": f"Bearer {KEY}"},
        _chunked(_body(BODY_BYTES)))
    assert status == 413 and doc["code"] == "payload_too_large"
    assert sent < BODY_BYTES / 2
    assert _extra_peak(service.proc.pid, before) < EXTRA_MEMORY


def test_a_body_within_the_limit_still_reaches_the_route(service):
    status, doc, _ = post_streaming(service.url, "/runs",
                                    {"Content-Length": "15", "Authorization": f"Bearer {KEY}"},
                                    iter([b'{"stations": 2}']))
    assert status == 422 and doc["code"] == "invalid_request"
    assert doc["detail"].startswith("body.stations: Input should be greater than or equal")
