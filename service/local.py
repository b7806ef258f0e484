"""``cellcal serve`` in a child process on a free loopback port, for the demo, tests and
benchmarks: started, waited for until healthy, and always stopped with its workers."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx

STARTUP_TIMEOUT_S = 30.0


class ServiceStartError(RuntimeError):
    """The child service exited at start-up or did not answer ``/health`` in time."""


@dataclass(frozen=True)
class LocalService:
    url: str
    key: str
    proc: subprocess.Popen[bytes]
    log: Path


def free_port() -> int:
    """A TCP port that is free on 127.0.0.1 right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass(frozen=True)
class ServeOptions:
    """How the child service runs: its mock ``scene`` file, its environment ``env`` before the
    two settings (default: this process's), its ``log`` file (default: next to the data
    directory) and how long it may take to answer ``/health`` (s)."""

    scene: Path | None = None
    env: dict[str, str] | None = None
    log: Path | None = None
    startup_timeout: float = STARTUP_TIMEOUT_S


@contextlib.contextmanager
def local_service(data_dir: Path, key: str,
                  options: ServeOptions = ServeOptions()) -> Iterator[LocalService]:
    """``cellcal serve --mock`` over ``data_dir`` with API key ``key``; yields it once healthy.

    The child gets its own process group, so the calibration worker it spawns stops with it.
    """
    port = free_port()
    log = options.log or data_dir.parent / f"serve-{port}.log"
    scene = options.scene
    cmd = [sys.executable, "-m", "service.cli", "serve", "--mock", "--host", "127.0.0.1",
           "--port", str(port), *(["--scene", str(scene)] if scene is not None else [])]
    child_env = {**(os.environ if options.env is None else options.env),
                 "CELLCAL_DATA_DIR": str(data_dir), "CELLCAL_API_KEY": key}
    with log.open("wb") as sink:
        proc = subprocess.Popen(cmd, env=child_env, stdout=sink, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, start_new_session=True)
    try:
        service = LocalService(url=f"http://127.0.0.1:{port}", key=key, proc=proc, log=log)
        _wait_healthy(service, options.startup_timeout)
        yield service
    finally:
        stop(proc)


def stop(proc: subprocess.Popen[bytes]) -> None:
    """SIGTERM to the child's process group, SIGKILL if it is still there after 10 s."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, sig)
        try:
            proc.wait(10.0)
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
