"""Run events (``GET /runs/{id}/events``): stored, so a listener that reconnects with
``Last-Event-ID`` misses none and sees none twice, and fanned out to the server-sent-event
listeners; the ``state`` event built from the stored run.

An event's id is its row id (``models.RunEvent``): it increases along a run and never changes.
A new listener first gets the run's ``state`` as of the newest stored event (with that
event's id); a returning one the stored events after its ``Last-Event-ID``. Live events follow,
skipping any the listener already has, so a reconnect loses and repeats nothing.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
from collections.abc import Iterator
from typing import Any

from sqlalchemy.orm import Session

from service import store
from service.db import Database
from service.models import FINAL_RUN_STATES


class EventBus:
    """Run events, stored and fanned out to server-sent-event listeners; publish from any
    thread."""

    def __init__(self, db: Database) -> None:
        self.db = db
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
        """Store the event (its ``id`` is the row's) and hand it to the run's listeners. One
        publish at a time, so every listener receives the events in id order."""
        with self._lock:
            with self.db.session() as s:
                event = {**event, "id": store.add_event(s, run_id=run_id, event=event)}
            for loop, queue in self._listeners.get(run_id, ()):
                with contextlib.suppress(RuntimeError):  # the listener's loop has closed
                    loop.call_soon_threadsafe(queue.put_nowait, event)

    def backlog(self, run_id: str, after: int | None) -> list[dict[str, Any]]:
        """What a listener gets before the live events: the run's state as of the newest
        stored event (``after`` None), or the stored events after ``after``, followed by the
        state if the run has ended without a stored final ``state`` event (404 for an
        unknown run)."""
        with self.db.session() as s:
            state = {**state_event(s, run_id=run_id), "id": store.last_event_id(s, run_id=run_id)}
            if after is None:
                return [state]
            events = store.events_after(s, run_id=run_id, after=after)
        if state["state"] in FINAL_RUN_STATES and not any(ends_stream(e) for e in events):
            events.append(state)
        return events


def ends_stream(event: dict[str, Any]) -> bool:
    """True for the event after which a run's stream ends (its final ``state``)."""
    return event["type"] == "state" and event["state"] in FINAL_RUN_STATES


def state_event(s: Session, *, run_id: str) -> dict[str, Any]:
    """The run's state and counts as a ``state`` event (404 for an unknown run)."""
    run = store.get_run(s, run_id=run_id)
    return {"type": "state", "run_id": run_id, "state": run.state,
            **store.run_counts(s, run=run),
            "error": None if run.error is None else {"code": run.error_code,
                                                     "detail": run.error}}
