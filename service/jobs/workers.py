"""Worker processes that never outlive the service, however it dies: calibration solves
(``service.jobs.calibrations``) and posted images (``service.jobs.image_worker``).

Solves are CPU-bound, so they run in a ``ProcessPoolExecutor`` of spawned workers. After a
``kill -9`` of the service nothing told those workers to stop: each (~190 MB) waited on its
task queue for good, and the multiprocessing resource tracker, which exits only when every
holder of its pipe has gone, stayed with them (issue 11). Each worker therefore

* asks the kernel for ``SIGKILL`` when its parent goes (Linux ``PR_SET_PDEATHSIG``). The
  kernel means the parent *thread*, so every worker is spawned from one thread that lives as
  long as the pool (:class:`WorkerPool`), never from a request thread that may end;
* watches its parent id as well (other systems, and the moment between spawn and ``prctl``):
  once it changes the parent is gone, and the worker exits.

With the workers gone, the resource tracker sees the end of its pipe and exits too.

A pool may cap each worker's address space (``RLIMIT_AS``): an allocation beyond it fails in
the worker (``MemoryError``, OpenCV's "Insufficient memory") instead of taking the host.

A solve reports its progress with :func:`report_progress`: the message travels over the pool's
pipe to the service process, where a reader thread hands it to the pool's ``on_progress``.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import functools
import logging
import multiprocessing
import os
import resource
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

from service.serving.parent_death import die_with_parent

#: How often a worker checks that its parent is still there, seconds.
PARENT_WATCH_INTERVAL_S = 0.5


log = logging.getLogger("cellcal.service")


@dataclass(frozen=True)
class _ProgressPipe:
    """A worker's end of its pool's progress pipe; the lock keeps the workers' messages
    whole."""

    send: Connection
    lock: Any  # multiprocessing.Lock


#: In a worker: the pool's progress pipe (``_init_worker``).
_progress: _ProgressPipe | None = None


def report_progress(message: Any) -> None:
    """Send ``message`` (picklable) from a worker to its pool's ``on_progress``; ignored
    outside a worker. Written before this returns, so a message sent before the solve returns
    reaches the service before its result does."""
    if _progress is None:
        return
    with _progress.lock, contextlib.suppress(OSError):  # the service has stopped reading
        _progress.send.send(message)


def _init_worker(parent_pid: int, progress: _ProgressPipe, memory_bytes: int | None) -> None:
    """Pool initializer: keep the progress pipe, cap the address space, end with the
    service."""
    global _progress
    _progress = progress
    if memory_bytes is not None:
        resource.setrlimit(resource.RLIMIT_AS, (memory_bytes, memory_bytes))
    _exit_with_parent(parent_pid)


def _exit_with_parent(parent_pid: int) -> None:
    """Pool initializer: make this worker end when ``parent_pid`` does."""
    die_with_parent(signal.SIGKILL, parent_pid)  # on failure the parent watch below holds
    threading.Thread(target=_watch_parent, args=(parent_pid,), name="parent-watch",
                     daemon=True).start()


def _watch_parent(parent_pid: int) -> None:
    while os.getppid() == parent_pid:
        time.sleep(PARENT_WATCH_INTERVAL_S)
    os._exit(1)


class WorkerPool:
    """A process pool whose workers exit when the service process does, each with at most
    ``memory_bytes`` of address space if given, at scheduling priority ``nice`` (0 = the
    service's; 19 yields the cores to everything else).

    ``submit`` hands the call to one long-lived thread, which is where the pool spawns its
    workers (``ProcessPoolExecutor`` starts them in the submitting thread), so the parent-death
    signal is tied to a thread that ends only with :meth:`shutdown` or the process.

    A worker that dies while idle (the kernel's out-of-memory killer, a ``kill``) breaks a
    ``ProcessPoolExecutor`` for good: it refuses every later task. Such a pool is replaced by
    a new one at the next ``submit``, so one dead worker does not fail every later
    calibration, report or posted image until the service is restarted.
    """

    def __init__(self, workers: int, on_progress: Callable[[Any], None], *,
                 memory_bytes: int | None = None, nice: int = 0) -> None:
        context = multiprocessing.get_context("spawn")
        self._receive, send = context.Pipe(duplex=False)
        self._new_pool = functools.partial(
            cf.ProcessPoolExecutor, workers, mp_context=context, initializer=_init_worker,
            initargs=(os.getpid(), _ProgressPipe(send, context.Lock()), memory_bytes))
        self._pool = self._new_pool()
        # Linux keeps a nice value per thread and a new process inherits its creator's: the
        # spawning thread takes ``nice``, so the workers run at it from their first import
        self._spawner = cf.ThreadPoolExecutor(1, thread_name_prefix="worker-spawner",
                                              initializer=os.nice, initargs=(nice,))
        self._stop = threading.Event()
        self._reader = threading.Thread(target=self._read_progress, args=(on_progress,),
                                        name="calibration-progress", daemon=True)
        self._reader.start()

    def _read_progress(self, on_progress: Callable[[Any], None]) -> None:
        """Hand the workers' progress messages to ``on_progress`` until :meth:`shutdown`."""
        while not self._stop.is_set():
            try:
                if not self._receive.poll(PARENT_WATCH_INTERVAL_S):
                    continue
                message = self._receive.recv()
            except (EOFError, OSError):  # the pipe is closed
                return
            try:
                on_progress(message)
            except Exception:  # a lost progress message must not end the reader
                log.exception("calibration progress %r", message)

    def submit(self, fn: Callable[..., Any], *args: Any) -> cf.Future[Any]:
        return self._spawner.submit(self._submit, fn, *args).result()

    def _submit(self, fn: Callable[..., Any], *args: Any) -> cf.Future[Any]:
        """On the spawning thread: submit, to a new pool if a worker of this one died."""
        try:
            return self._pool.submit(fn, *args)
        except cf.process.BrokenProcessPool:
            log.warning("a worker process had died (out of memory, or killed); new worker "
                        "processes are started")
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = self._new_pool()
            return self._pool.submit(fn, *args)

    def shutdown(self) -> None:
        """Cancel queued work and let the workers go; does not wait for a running solve."""
        self._pool.shutdown(wait=False, cancel_futures=True)
        self._spawner.shutdown(wait=False)
        self._stop.set()
        if threading.current_thread() is not self._reader:
            self._reader.join()
            self._receive.close()
