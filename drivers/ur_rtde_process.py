"""ur-rtde in a child process of its own, so that a crash of the native client is a lost
connection for the service, not its end.

Why: ur-rtde 1.6.5 reconnects by itself after a drop, from more than one thread; when the drop is
shorter than that attempt, two receive threads read one socket and the process may die with
SIGSEGV (``tools/ur-reconnect-crash``). No flag switches this off. Here the interfaces live in a
child (``python -m drivers.ur_rtde_process``): if it dies, every call of the parent raises
:class:`RtdeClientGoneError` (a ``RuntimeError``, as ur-rtde's own errors are) saying how it ended.

Wire: the parent holds a *hub* socket to the child. Each parent thread that calls gets a channel
of its own (a socket pair whose far end travels over the hub, ``SCM_RIGHTS``) served by a thread
of its own in the child, so a blocking ``moveL`` on one thread does not hold a status read on
another, and a call costs one request and one reply on that socket (length-prefixed pickles of
a list of ``(interface, method, args)`` and ``("ok", [values])`` or ``("err", type name,
message)`` of the first that failed); several readings travel as one request.

Lifetime: the child ends when the hub closes (:meth:`RtdeProcess.close` drops the interfaces,
which disconnect, first), when the parent dies (``PR_SET_PDEATHSIG``, armed against a spawner
thread that lives as long as the process, since Linux means the thread that forked), or when the
driver kills it (:meth:`RtdeProcess.kill`, on a lost link). It ignores SIGINT and SIGTERM: a
Ctrl-C or a service stop reaches the parent, which still needs the child to stop the robot.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import ctypes
import os
import pickle
import signal
import socket
import struct
import subprocess
import sys
import threading
from collections.abc import Callable
from typing import Any

from drivers.rtde_wire import recv_exact

_HEADER = struct.Struct(">I")
#: ``prctl`` option from ``<linux/prctl.h>``.
_PR_SET_PDEATHSIG = 1
#: How long :meth:`RtdeProcess.close` lets the interfaces disconnect before killing, seconds
#: (each ur-rtde destructor takes about 0.5 s).
CLOSE_TIMEOUT_S = 3.0

#: One thread, alive as long as this process, spawns every child (see the module docstring).
_spawner = cf.ThreadPoolExecutor(max_workers=1, thread_name_prefix="ur-rtde-spawner")


class RtdeClientGoneError(RuntimeError):
    """The child process holding ur-rtde ended; ``how`` says how (``SIGSEGV``, ``exit 1``)."""

    def __init__(self, how: str) -> None:
        super().__init__(f"the ur-rtde client process ended ({how})")
        self.how = how


def _send(sock: socket.socket, obj: object) -> None:
    body = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    sock.sendall(_HEADER.pack(len(body)) + body)


def _recv(sock: socket.socket) -> Any:
    (size,) = _HEADER.unpack(recv_exact(sock, _HEADER.size))
    return pickle.loads(recv_exact(sock, size))


class RtdeProcess:
    """A child process holding ``rtde_control`` / ``rtde_receive`` interfaces by name.

    ``call("receive", "getActualQ")`` runs ``RTDEReceiveInterface.getActualQ()`` in the child;
    ``call("control", "__init__", host)`` constructs the interface there. ``timeout`` (seconds,
    None: none) bounds one call: a child that does not answer in time is killed.
    """

    def __init__(self) -> None:
        self._hub, child_end = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        self._hub_lock = threading.Lock()
        self._local = threading.local()
        self._killed = False
        self._crash: str | None = None
        argv = [sys.executable, "-m", __name__, str(child_end.fileno()), str(os.getpid())]
        try:
            self._proc = _spawner.submit(
                subprocess.Popen, argv, pass_fds=(child_end.fileno(),),
                stdin=subprocess.DEVNULL).result()
        finally:
            child_end.close()

    @property
    def pid(self) -> int:
        return self._proc.pid

    def call(self, interface: str, method: str, *args: object,
             timeout: float | None = None) -> Any:
        """``interface.method(*args)`` in the child; its RuntimeError is raised here."""
        return self.call_all([(interface, method, args)], timeout=timeout)[0]

    def call_all(self, calls: list[tuple[str, str, tuple]], *,
                 timeout: float | None = None) -> list[Any]:
        """Several ``(interface, method, args)`` calls in one round trip, in order; the first
        error is raised here (the calls after it are not made)."""
        try:
            sock = self._channel()
            sock.settimeout(timeout)
            _send(sock, calls)
            reply = _recv(sock)
        except TimeoutError:
            self.kill()
            raise RtdeClientGoneError(f"no answer to {calls[0][1]} within {timeout:g} s; "
                                      "stopped by the driver") from None
        except (OSError, EOFError):
            raise RtdeClientGoneError(self._how_it_ended()) from None
        if reply[0] == "ok":
            return reply[1]
        _, kind, message = reply
        raise {"TypeError": TypeError, "ValueError": ValueError}.get(kind, RuntimeError)(message)

    def _channel(self) -> socket.socket:
        """This thread's socket to the child, opened on first use (closed with the thread)."""
        sock = getattr(self._local, "sock", None)
        if sock is None:
            sock, far_end = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
            with far_end, self._hub_lock:
                socket.send_fds(self._hub, [b"c"], [far_end.fileno()])
            self._local.sock = sock
        return sock

    def crash(self) -> str | None:
        """How the child ended if a call found it ended by itself (``SIGSEGV``, ``exit status
        1``), else None (running, or stopped by the driver)."""
        return self._crash

    def _how_it_ended(self) -> str:
        """How the child ended, waiting a moment for its status (a reset socket may come
        first); remembered for :meth:`crash`."""
        try:
            code = self._proc.wait(timeout=2.0)
        except subprocess.TimeoutExpired:
            self.kill()
            return "its connection to the driver broke; stopped by the driver"
        if self._killed:
            return "stopped by the driver"
        self._crash = signal.Signals(-code).name if code < 0 else f"exit status {code}"
        return self._crash

    def kill(self) -> None:
        """End the child at once (SIGKILL), whatever its interfaces are doing."""
        self._killed = True
        with contextlib.suppress(ProcessLookupError):
            self._proc.kill()
        self._proc.wait()
        self._hub.close()

    def close(self) -> None:
        """Let the interfaces disconnect and the child exit; kill it after CLOSE_TIMEOUT_S."""
        with contextlib.suppress(OSError):
            self._hub.shutdown(socket.SHUT_WR)
        with contextlib.suppress(subprocess.TimeoutExpired):
            self._proc.wait(timeout=CLOSE_TIMEOUT_S)
        self.kill()


class RtdeInterface:
    """One ur-rtde interface in an RtdeProcess: ``iface.getActualQ()`` runs there.

    ``timeout`` bounds each call (seconds; None for the control interface, whose moves block
    and are watched by ``URRobot._guarded`` instead).
    """

    def __init__(self, process: RtdeProcess, name: str, timeout: float | None) -> None:
        self._process, self._name, self._timeout = process, name, timeout

    def call(self, method: str, *args: object, timeout: float | None = None) -> Any:
        return self._process.call(self._name, method, *args,
                                  timeout=self._timeout if timeout is None else timeout)

    def __getattr__(self, method: str) -> Callable[..., Any]:
        return lambda *args: self.call(method, *args)


# ---- the child ------------------------------------------------------------------------------

def _serve_channel(sock: socket.socket, interfaces: dict[str, Any],
                   classes: dict[str, type]) -> None:
    """Answer one parent thread's calls until it closes its end."""
    def answer(interface: str, method: str, args: tuple) -> Any:
        if method == "__init__":
            interfaces[interface] = classes[interface](*args)
            return None
        if interface not in interfaces:
            raise RuntimeError(f"{interface} interface not constructed")
        return getattr(interfaces[interface], method)(*args)

    with sock:
        while True:
            try:
                calls = _recv(sock)
            except (OSError, EOFError):
                return
            try:
                reply: tuple = ("ok", [answer(*call) for call in calls])
            except Exception as err:  # every failure travels to the parent
                reply = ("err", type(err).__name__, str(err))
            try:
                _send(sock, reply)
            except OSError:
                return


def _serve(hub_fd: int, parent_pid: int) -> None:
    """The child's main loop: a thread per channel received on the hub; exit when it closes."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    if os.getppid() != parent_pid:
        os._exit(1)
    import rtde_control
    import rtde_receive

    classes = {"control": rtde_control.RTDEControlInterface,
               "receive": rtde_receive.RTDEReceiveInterface}
    interfaces: dict[str, Any] = {}
    hub = socket.socket(fileno=hub_fd)
    while True:
        try:
            msg, fds, _, _ = socket.recv_fds(hub, 16, 4)
        except OSError:
            break
        if not msg:
            break
        for fd in fds:
            threading.Thread(target=_serve_channel, daemon=True,
                             args=(socket.socket(fileno=fd), interfaces, classes)).start()
    interfaces.clear()  # the destructors disconnect from the controller
    os._exit(0)


if __name__ == "__main__":
    _serve(int(sys.argv[1]), int(sys.argv[2]))
