"""Routes whose plain (``def``) endpoints run in one worker-thread call each.

FastAPI runs a ``def`` endpoint in its thread pool, and with it every ``def`` dependency, the
enter and the exit of a ``yield`` dependency (the database session) and the response
validation: six hand-overs between the event loop and a worker thread for one ``GET
/runs/{id}``. Each hand-over waits for the GIL and for the other side to be scheduled; with 20
clients on one process they added 50-110 ms to requests whose work took 2-6 ms (issue 21,
measured in ``benchmarks/README.md``). :class:`OneThreadRoute` makes such an endpoint a
coroutine that runs the original function in a single worker-thread call and closes the
request's database sessions (``service.api.deps.SessionDep``) in that same call, so the
event loop never waits on the database; the cheap dependencies are coroutines
(``service.api.deps``). The endpoint's code, its signature and its OpenAPI document stay as
they are.
"""

from __future__ import annotations

import functools
import inspect
from collections.abc import Callable, Coroutine
from typing import Any

import anyio.to_thread
from fastapi.routing import APIRoute
from sqlalchemy.orm import Session


class OneThreadRoute(APIRoute):
    """An ``APIRoute`` that runs a ``def`` endpoint with :func:`in_one_thread`."""

    def __init__(self, path: str, endpoint: Callable[..., Any], **kwargs: Any) -> None:
        if inspect.isfunction(endpoint) and not inspect.iscoroutinefunction(endpoint):
            endpoint = in_one_thread(endpoint)
        super().__init__(path, endpoint, **kwargs)


def in_one_thread(endpoint: Callable[..., Any]) -> Callable[..., Coroutine[Any, Any, Any]]:
    """``endpoint`` as a coroutine function of the same signature (``functools.wraps``: FastAPI
    reads the parameters and the return type through ``__wrapped__``) that calls it in one
    worker thread and closes the ``Session`` arguments there after it returned."""

    @functools.wraps(endpoint)
    async def run(**arguments: Any) -> Any:
        return await anyio.to_thread.run_sync(_call_and_close, endpoint, arguments)

    return run


def _call_and_close(endpoint: Callable[..., Any], arguments: dict[str, Any]) -> Any:
    try:
        return endpoint(**arguments)
    finally:
        for value in arguments.values():
            if isinstance(value, Session):
                value.close()

