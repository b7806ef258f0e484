"""Independent fits spread over the cores: model-selection candidates and their folds.

Model selection (``calib.selection``) fits every candidate on all stations and then on each
cross-validation fold: some 25 joint fits that do not depend on each other once the
candidates' full fits are known. A fit is many small numpy and scipy steps that hold the
GIL, so threads would take turns; the fits run instead in worker processes *forked* from
this one: nothing is imported again and the data are shared until written, so a worker
starts in milliseconds. Results are the same numbers as in this process (the same code on
the same inputs, BLAS on one thread as ``calibrate_stations`` sets it).

One core, or a caller that asks for one worker, gets :class:`InlineExecutor`: the same
calls, in order, in this process.
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Callable, Iterator
from concurrent.futures import Executor, Future, ProcessPoolExecutor
from contextlib import contextmanager
from typing import Any


def cores() -> int:
    """The CPU cores this process may run on."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


class InlineExecutor(Executor):
    """Runs each submitted call at once, in this process: the serial path."""

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future:
        future: Future = Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except Exception as exc:  # handed to whoever reads the result, as a pool does
            future.set_exception(exc)
        return future


@contextmanager
def fit_pool(workers: int | None = None) -> Iterator[Executor]:
    """An executor of ``workers`` forked processes (default: one per core), shut down on
    exit; :class:`InlineExecutor` for one worker, where ``fork`` is unavailable, or in a
    daemonic process (which may not have children)."""
    n = cores() if workers is None else workers
    if (n <= 1 or "fork" not in multiprocessing.get_all_start_methods()
            or multiprocessing.current_process().daemon):
        yield InlineExecutor()
        return
    with ProcessPoolExecutor(n, mp_context=multiprocessing.get_context("fork")) as pool:
        yield pool
