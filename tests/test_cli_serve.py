"""``cellcal serve --fd``: the service serves on a listening socket its parent bound, so a
port chosen by the parent cannot be taken by another process before the service listens
(``service.serving.local`` starts every test service this way)."""

from __future__ import annotations

import errno
import os
import socket
from pathlib import Path

import httpx
import pytest

from service.cli import main as cli
from service.serving.local import ServeOptions, listening_socket, local_service
from tests.support.cli import assert_one_line_error

KEY = "serve-key-0123456789abcdef"


@pytest.mark.timeout(300)
def test_local_service_serves_on_the_port_it_held_from_the_start(tmp_path: Path) -> None:
    with local_service(tmp_path / "data", KEY, ServeOptions()) as service:
        port = httpx.URL(service.url).port
        health = httpx.get(f"{service.url}/health", timeout=10)
        with socket.socket() as other, pytest.raises(OSError) as err:
            other.bind(("127.0.0.1", port))
    assert health.status_code == 200
    assert err.value.errno == errno.EADDRINUSE


def test_listening_socket_is_bound_and_listening() -> None:
    with listening_socket() as sock:
        host, port = sock.getsockname()
        assert host == "127.0.0.1" and port > 0
        assert sock.getsockopt(socket.SOL_SOCKET, socket.SO_ACCEPTCONN) == 1
        with socket.create_connection(("127.0.0.1", port), timeout=5):
            pass  # the backlog takes it before anyone accepts


def test_fd_that_is_not_a_socket_is_one_error_line(capsys, tmp_path: Path) -> None:
    with (tmp_path / "file").open("w") as f:
        fd = f.fileno()
        code = cli.main(["serve", "--mock", "--fd", str(fd)])
    assert code == 2
    assert_one_line_error(capsys.readouterr().err, f"--fd {fd}: not an open socket")


def test_fd_of_a_socket_that_does_not_listen_is_refused(capsys) -> None:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        fd = os.dup(sock.fileno())  # the command takes over the descriptor it is given
        code = cli.main(["serve", "--mock", "--fd", str(fd)])
    assert code == 2
    assert_one_line_error(capsys.readouterr().err, f"--fd {fd}: not a listening TCP socket")


def test_fd_with_a_port_is_refused(capsys) -> None:
    with listening_socket() as sock:
        code = cli.main(["serve", "--mock", "--fd", str(sock.fileno()), "--port", "9"])
    assert code == 2
    assert_one_line_error(capsys.readouterr().err, "--fd replaces --host and --port")
