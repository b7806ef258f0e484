"""``cellcal serve`` in a child process on a free loopback port, for the demo, tests and
benchmarks: started, waited for until healthy, and always stopped with its workers.

The port is bound here and the listening socket handed to the child (``cellcal serve --fd``),
so no other process can take it between choosing and serving (no check-then-bind race).
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx

from service.serving.parent_death import die_with_parent

#: Only a bound against a hang: a loaded machine starts a service many times slower.
STARTUP_TIMEOUT_S = 120.0


class ServiceStartError(RuntimeError):
    """The child service exited at start-up or did not answer ``/health`` in time."""


@dataclass(frozen=True)
class LocalService:
    url: str
    key: str
    proc: subprocess.Popen[bytes]
    log: Path


def listening_socket() -> socket.socket:
    """A TCP socket listening on a port of 127.0.0.1 the system chose (port 0)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    try:
        sock.bind(("127.0.0.1", 0))
        sock.listen(128)
    except OSError:
        sock.close()
        raise
    return sock


@dataclass(frozen=True)
class ServeOptions:
    """How the child service runs: its mock ``scene`` file, its environment ``env`` before the
    two settings (default: this process's), its ``log`` file (default: next to the data
    directory), how long it may take to answer ``/health`` (s), and whether it simulates the
    cell (``--mock``; without it the devices come from ``CELLCAL_ROBOT``/``CELLCAL_CAMERA``)."""

    scene: Path | None = None
    env: dict[str, str] | None = None
    log: Path | None = None
    startup_timeout: float = STARTUP_TIMEOUT_S
    mock: bool = True
    #: More ``cellcal serve`` options, e.g. ``("--graceful-timeout", "5")``.
    args: tuple[str, ...] = ()
    #: Called in the child before it runs the service (after the parent-death signal is set),
    #: e.g. to lower its resource limits.
    preexec: Callable[[], None] | None = None
    #: The child's working directory, first on its ``sys.path`` (default: this process's), e.g.
    #: another version of the code checked out there (``benchmarks.history_cpu``).
    cwd: Path | None = None


@contextlib.contextmanager
def local_service(data_dir: Path, key: str,
                  options: ServeOptions = ServeOptions()) -> Iterator[LocalService]:
    """``cellcal serve --mock`` over ``data_dir`` with API key ``key``; yields it once healthy.

    The child gets its own process group, so the calibration worker it spawns stops with it.
    """
    with listening_socket() as sock:
        port = sock.getsockname()[1]
        log = options.log or data_dir.parent / f"serve-{port}.log"
        scene = options.scene
        cmd = [sys.executable, "-m", "service.cli", "serve", "--fd", str(sock.fileno()),
               *(["--mock"] if options.mock else []),
               *(["--scene", str(scene)] if scene is not None else []), *options.args]
        child_env = {**(os.environ if options.env is None else options.env),
                     "CELLCAL_DATA_DIR": str(data_dir), "CELLCAL_API_KEY": key}
        with log.open("wb") as sink:
            proc = subprocess.Popen(cmd, env=child_env, cwd=options.cwd, stdout=sink,
                                    stderr=subprocess.STDOUT,
                                    stdin=subprocess.DEVNULL, start_new_session=True,
                                    pass_fds=(sock.fileno(),),
                                    preexec_fn=_child_setup(options.preexec))
    try:
        service = LocalService(url=f"http://127.0.0.1:{port}", key=key, proc=proc, log=log)
        _wait_healthy(service, options.startup_timeout)
        yield service
    finally:
        stop(proc)


def _child_setup(then: Callable[[], None] | None) -> Callable[[], None]:
    """What the child runs before ``exec``: ask for SIGTERM when this process dies, so a
    parent killed without cleanup (a test run ended by its CI timeout) leaves no service
    holding its port; then ``then``. SIGTERM, not SIGKILL: the service stops its robot first
    and exits within its grace period."""
    parent = os.getpid()

    def setup() -> None:
        die_with_parent(signal.SIGTERM, parent)
        if then is not None:
            then()
    return setup


#: How long a stopped service may take (it stops its robot and exits within its 10 s grace
#: period when idle; a loaded machine is slower) before it is killed, seconds.
STOP_TIMEOUT_S = 60.0


def stop(proc: subprocess.Popen[bytes]) -> None:
    """SIGTERM to the child's process group, SIGKILL if it is still there after
    ``STOP_TIMEOUT_S``."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, sig)
        try:
            proc.wait(STOP_TIMEOUT_S)
            return
        except subprocess.TimeoutExpired:
            continue


def _wait_healthy(service: LocalService, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while True:
        if service.proc.poll() is not None:
            lines = service.log.read_text(errors="replace").strip().splitlines()
            why = next((ln.removeprefix("cellcal: error: ") for ln in reversed(lines)
                        if ln.startswith("cellcal: error: ")), lines[-1] if lines else "")
            raise ServiceStartError(f"the service exited at startup: {why}")
        with contextlib.suppress(httpx.TransportError):
            if httpx.get(f"{service.url}/health", timeout=1.0).status_code == 200:
                return
        if time.monotonic() > deadline:
            raise ServiceStartError(f"the service did not answer within {timeout:g} s")
        time.sleep(0.1)
