"""Run events (``GET /runs/{id}/events``): the bus that fans them out to server-sent-event
listeners, and the ``state`` event built from the stored run."""

from __future__ import annotations

import asyncio
import contextlib
import threading
from collections.abc import Iterator
from typing import Any

from sqlalchemy.orm import Session

from service import store


class EventBus:
    """Run events fanned out to server-sent-event listeners; publish from any thread."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._listeners: dict[str, set[tuple[asyncio.AbstractEventLoop,
                                             asyncio.Queue[dict[str, Any]]]]] = {}

    @contextlib.contextmanager
    def listen(self, run_id: str) -> Iterator[asyncio.Queue[dict[str, Any]]]:
        """A queue receiving the run's events while the block runs (call on the event loop)."""
        entry = (asyncio.get_running_loop(), asyncio.Queue[dict[str, Any]]())
        with self._lock:
            self._listeners.setdefault(run_id, set()).add(entry)
        try:
            yield entry[1]
        finally:
            with self._lock:
                self._listeners[run_id].discard(entry)
                if not self._listeners[run_id]:
                    del self._listeners[run_id]

    def publish(self, run_id: str, event: dict[str, Any]) -> None:
        with self._lock:
            listeners = list(self._listeners.get(run_id, ()))
        for loop, queue in listeners:
            with contextlib.suppress(RuntimeError):  # the listener's loop has closed
                loop.call_soon_threadsafe(queue.put_nowait, event)


def state_event(s: Session, *, run_id: str) -> dict[str, Any]:
    """The run's state and counts as a ``state`` event (404 for an unknown run)."""
    run = store.get_run(s, run_id=run_id)
    return {"type": "state", "run_id": run_id, "state": run.state,
            **store.run_counts(s, run=run),
            "error": None if run.error is None else {"code": run.error_code,
                                                     "detail": run.error}}
