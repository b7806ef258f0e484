"""Calibration worker processes that never outlive the service, however it dies.

Solves are CPU-bound, so they run in a ``ProcessPoolExecutor`` of spawned workers. After a
``kill -9`` of the service nothing told those workers to stop: each (~190 MB) waited on its
task queue for good, and the multiprocessing resource tracker, which exits only when every
holder of its pipe has gone, stayed with them (issue 11). Each worker therefore

* asks the kernel for ``SIGKILL`` when its parent goes (Linux ``PR_SET_PDEATHSIG``). The
  kernel means the parent *thread*, so every worker is spawned from one thread that lives as
  long as the pool (:class:`CalibrationPool`), never from a request thread that may end;
* watches its parent id as well (other systems, and the moment between spawn and ``prctl``):
  once it changes the parent is gone, and the worker exits.

With the workers gone, the resource tracker sees the end of its pipe and exits too.
"""

from __future__ import annotations

import concurrent.futures as cf
import ctypes
import multiprocessing
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

#: ``prctl`` option from ``<linux/prctl.h>``.
_PR_SET_PDEATHSIG = 1
#: How often a worker checks that its parent is still there, seconds.
PARENT_WATCH_INTERVAL_S = 0.5


def _exit_with_parent(parent_pid: int) -> None:
    """Pool initializer: make this worker end when ``parent_pid`` does."""
    if sys.platform.startswith("linux"):  # on failure the parent watch below still holds
        ctypes.CDLL(None).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    if os.getppid() != parent_pid:  # the parent died before the signal was armed
        os._exit(1)
    threading.Thread(target=_watch_parent, args=(parent_pid,), name="parent-watch",
                     daemon=True).start()


def _watch_parent(parent_pid: int) -> None:
    while os.getppid() == parent_pid:
        time.sleep(PARENT_WATCH_INTERVAL_S)
    os._exit(1)


class CalibrationPool:
    """A process pool whose workers exit when the service process does.

    ``submit`` hands the call to one long-lived thread, which is where the pool spawns its
    workers (``ProcessPoolExecutor`` starts them in the submitting thread), so the parent-death
    signal is tied to a thread that ends only with :meth:`shutdown` or the process.
    """

    def __init__(self, workers: int) -> None:
        self._pool = cf.ProcessPoolExecutor(
            workers, mp_context=multiprocessing.get_context("spawn"),
            initializer=_exit_with_parent, initargs=(os.getpid(),))
        self._spawner = cf.ThreadPoolExecutor(1, thread_name_prefix="calibration-spawner")

    def submit(self, fn: Callable[..., Any], *args: Any) -> cf.Future[Any]:
        return self._spawner.submit(self._pool.submit, fn, *args).result()

    def shutdown(self) -> None:
        """Cancel queued work and let the workers go; does not wait for a running solve."""
        self._pool.shutdown(wait=False, cancel_futures=True)
        self._spawner.shutdown(wait=False)
