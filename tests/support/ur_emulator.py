"""Start and stop ``mocks.ur_emulator`` processes for tests, and talk to their dashboard.

The emulator must be a separate process: the ur-rtde constructors hold the GIL while they block.
Each emulator owns one loopback address (127.0.0.2, 127.0.0.3, ...) since UR ports are fixed;
it picks and binds the address itself (``--host auto``), so concurrent sessions cannot race.
"""

from __future__ import annotations

import json
import re
import selectors
import socket
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from tests.support.helpers import ends_with_this_process, wait_for

REPO = Path(__file__).resolve().parents[2]
PORTS = (29999, 30003, 30004)


@dataclass
class EmulatorProcess:
    """A running emulator: its address, process, and dashboard helpers."""

    host: str
    proc: subprocess.Popen

    def command(self, line: str, *, timeout: float = 5.0) -> str:
        """Send one dashboard line (real or ``emulator ...``) and return the reply line."""
        with socket.create_connection((self.host, 29999), timeout) as s:
            s.settimeout(timeout)
            reader = s.makefile("r", encoding="utf-8", newline="\n")
            reader.readline()  # banner
            s.sendall((line + "\n").encode())
            return reader.readline().strip()

    def state(self) -> dict:
        """The emulator's own view: process id, joints, pose, runtime state, safety bits, faults."""
        return json.loads(self.command("emulator state"))


def serving(host: str, *, timeout: float = 0.5) -> bool:
    """True if a controller on ``host`` answers: the dashboard sends its banner and the other
    UR ports accept. False during a drop (connections are reset) and where nothing listens."""
    try:
        with socket.create_connection((host, 29999), timeout) as s:
            s.settimeout(timeout)
            if not s.recv(64).startswith(b"Connected"):
                return False
        for port in PORTS[1:]:
            socket.create_connection((host, port), timeout).close()
    except OSError:
        return False
    return True


def wait_ports(host: str, proc: subprocess.Popen | None = None, *,
               timeout: float = 10.0) -> None:
    """Block until ``host`` serves all UR ports; fail early if ``proc`` died."""
    def ports_open() -> bool:
        if proc is not None and proc.poll() is not None:
            raise RuntimeError(f"ur_emulator on {host} exited with code {proc.returncode}")
        return serving(host)
    wait_for(f"ur_emulator on {host} to open its ports", ports_open, timeout)


@contextmanager
def running_emulator(*args: str, timeout: float = 120.0) -> Iterator[EmulatorProcess]:
    """Run ``python -m mocks.ur_emulator --host auto ARGS`` for the block; always reap it.

    The emulator binds the first free loopback address itself and names it on its first
    stdout line; it keeps the ports bound until it exits (drops included), so test sessions
    running side by side (two clones) never share or steal an address.
    """
    proc = subprocess.Popen(
        [sys.executable, "-m", "mocks.ur_emulator", "--host", "auto", *args],
        cwd=REPO, stdout=subprocess.PIPE, text=True, preexec_fn=ends_with_this_process())
    try:
        line = _first_line(proc, timeout)
        m = re.match(r"ur_emulator listening on (\S+) ", line)
        if m is None:
            raise RuntimeError(f"ur_emulator did not start (exit code {proc.poll()}): {line!r}")
        yield EmulatorProcess(m.group(1), proc)
    finally:
        _reap(proc)


def _first_line(proc: subprocess.Popen, timeout: float) -> str:
    """The first stdout line of ``proc``, or '' if it exits or ``timeout`` s pass first."""
    with selectors.DefaultSelector() as sel:
        sel.register(proc.stdout, selectors.EVENT_READ)
        if not sel.select(timeout):
            return ""
    return proc.stdout.readline()


def free_host(first: int = 200, last: int = 254) -> str:
    """A loopback address on which nothing serves the UR ports (connections are refused).

    Emulators started with ``--host auto`` never take 127.0.0.200 and up.
    """
    for n in range(first, last + 1):
        if not serving(f"127.0.0.{n}"):
            return f"127.0.0.{n}"
    raise RuntimeError(f"no unused loopback address in 127.0.0.{first}..{last}")


def _reap(proc: subprocess.Popen) -> None:
    """Terminate, then kill if needed; the process must be gone afterwards."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=5)
    if proc.stdout is not None:
        proc.stdout.close()
    assert proc.poll() is not None, "ur_emulator survived teardown"
