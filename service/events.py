"""Events of runs, calibrations and validations (``GET /runs/{id}/events``,
``GET /calibrations/{id}/events``, ``GET /validations/{id}/events``): stored, so a listener
that reconnects with ``Last-Event-ID`` misses none and sees none twice, and fanned out to the
server-sent-event listeners; the ``state`` event built from the stored row.

An event's id is its row id (``RunEventRecord``, ``JobEventRecord``): it increases along a
stream and never changes. A new listener first gets the topic's ``state`` as of the newest
stored event (with that event's id); a returning one the stored events after its
``Last-Event-ID``. Live events follow, skipping any the listener already has, so a reconnect
loses and repeats nothing. Every stream ends with its final ``state``, or with a ``shutdown``
event (no id) when the service stops first.

Publishing never waits for the database: an event joins an in-memory queue, in order, and one
writer thread stores each (retried for as long as the database does not answer) and then hands
it to the listeners. A 40 s lock as a calibration ended made each progress event wait SQLite's
30 s busy timeout inside the job, and then dropped it (issue 22); now the job goes on and the
events follow, all of them and in order, once the lock is gone.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from functools import partial
from typing import Any

from sqlalchemy.orm import Session

from service.serving.logs import log_state_event
from service.store import queries, writes
from service.store.db import Database, DatabaseUnavailableError, retry_transient
from service.store.event_relay import EventRelay, announce
from service.store.records import FINAL_JOB_STATES, FINAL_RUN_STATES, Topic

log = logging.getLogger("cellcal.service")


class EventBus:
    """Events, stored and fanned out to server-sent-event listeners; publish from any
    thread. On PostgreSQL the other services' events arrive too (``service.store.event_relay``)."""

    def __init__(self, db: Database, instance_id: str) -> None:
        self.db = db
        self.instance_id = instance_id
        self._lock = threading.Lock()
        self._listeners: dict[Topic, set[tuple[asyncio.AbstractEventLoop,
                                               asyncio.Queue[dict[str, Any]]]]] = {}
        self._relay: EventRelay | None = None
        if db.engine.dialect.name == "postgresql":
            self._relay = EventRelay(db.engine, instance_id, self._deliver_stored)
            self._relay.start()
        self._closed = False
        self._queue: deque[tuple[Topic, dict[str, Any]]] = deque()  # to store, in order
        self._finishing: dict[Topic, int] = {}  # topics whose final state is being saved
        self._queued = threading.Condition()
        self._writing = threading.Lock()  # one writer at a time: the ids follow the queue
        self._stopping = threading.Event()  # close(): the writer ends with an empty queue
        self._giving_up = threading.Event()  # close() waits no longer for the database
        self._writer_done = False  # the writer thread has ended: publish() stores itself
        self._writer = threading.Thread(target=self._write, name="event-writer", daemon=True)
        self._writer.start()

    def close(self, flush_s: float = 5.0) -> None:
        """Store the queued events (for at most ``flush_s`` seconds if the database does not
        answer), then end every stream, open or opened later, with the ``shutdown`` event,
        and stop relaying other services' events: the service is stopping."""
        deadline = time.monotonic() + flush_s
        with self._queued:
            self._stopping.set()
            self._queued.notify_all()
        if not self.flush(flush_s):
            self._giving_up.set()
        # a writer held in a statement by a locked database is not waited for beyond it
        self._writer.join(max(0.0, deadline - time.monotonic()))
        self._giving_up.set()  # an event published from now on is tried once
        if self._relay is not None:
            self._relay.close()
        with self._lock:
            self._closed = True
            for entries in self._listeners.values():
                for loop, queue in entries:
                    with contextlib.suppress(RuntimeError):  # the listener's loop has closed
                        loop.call_soon_threadsafe(queue.put_nowait, SHUTDOWN_EVENT)

    @contextlib.contextmanager
    def listen(self, topic: Topic) -> Iterator[asyncio.Queue[dict[str, Any]]]:
        """A queue receiving the topic's events while the block runs (call on the event
        loop)."""
        entry = (asyncio.get_running_loop(), asyncio.Queue[dict[str, Any]]())
        with self._lock:
            self._listeners.setdefault(topic, set()).add(entry)
            if self._closed:
                entry[1].put_nowait(SHUTDOWN_EVENT)
        try:
            yield entry[1]
        finally:
            with self._lock:
                self._listeners[topic].discard(entry)
                if not self._listeners[topic]:
                    del self._listeners[topic]

    def publish(self, topic: Topic, event: dict[str, Any]) -> None:
        """Queue the event: the writer thread stores it (its ``id`` is the row's) and then
        hands it to the topic's listeners. Returns at once, whatever the database does (once
        the bus is closed, the event is stored here)."""
        with self._queued:
            self._queue.append((topic, event))
            self._queued.notify_all()
            if not self._writer_done:
                return
        self._write_queued()

    def finish(self, topic: Topic, save: Callable[[], bool], *,
               retry: Callable[[Callable[[], dict[str, Any]]], dict[str, Any]] | None = None
               ) -> bool:
        """End ``topic``: ``save()`` stores its final state (False when it did not, e.g. the
        run was already in it), then its ``state`` event is read back (through ``retry``,
        which calls the read and may repeat it) and queued; whether it was saved.

        From before the save until the event is queued the topic counts as having an event on
        its way (:meth:`_queued_for`): a listener that reconnects in between, when the final
        state is in the database but its event in no queue, waits for the event instead of
        ending its stream with a state made from the row under an old id, and so never misses
        the stored final event. An exception from ``save`` or the read leaves the event to the
        caller (a listener that waited meanwhile gets the event the caller publishes later)."""
        with self._queued:
            self._finishing[topic] = self._finishing.get(topic, 0) + 1
        try:
            if not save():
                return False
            read = partial(self.state, topic)
            self.publish(topic, read() if retry is None else retry(read))
            return True
        finally:
            with self._queued:
                self._finishing[topic] -= 1
                if not self._finishing[topic]:
                    del self._finishing[topic]

    def flush(self, timeout: float) -> bool:
        """Wait until every event published so far is stored; False if ``timeout`` s passed
        first."""
        deadline = time.monotonic() + timeout
        with self._queued:
            while self._queue:
                left = deadline - time.monotonic()
                if left <= 0.0:
                    return False
                self._queued.wait(left)
        return True

    def _write(self) -> None:
        """The writer thread, until the bus is closed and its queue is empty."""
        while True:
            with self._queued:
                while not self._queue and not self._stopping.is_set():
                    self._queued.wait()
                if not self._queue:
                    self._writer_done = True
                    return
            self._write_queued()

    def _write_queued(self) -> None:
        """Store the queued events one by one, in order, each retried while the database does
        not answer, and hand each to the listeners once stored."""
        with self._writing:
            while True:
                with self._queued:
                    if not self._queue:
                        return
                    topic, event = self._queue[0]
                try:
                    self._store_and_send(topic, event)
                except DatabaseUnavailableError as exc:  # close() gave up waiting
                    with self._queued:
                        lost = len(self._queue)
                        self._queue.clear()
                        self._queued.notify_all()
                    log.error("%d event(s) not stored as the service stops: %s", lost, exc)
                    return
                except Exception:  # a fault of this event, not of the database: others go on
                    log.exception("%s %s: the %s event cannot be stored", topic.kind,
                                  topic.id, event["type"])
                with self._queued:
                    self._queue.popleft()
                    self._queued.notify_all()

    def _store_and_send(self, topic: Topic, event: dict[str, Any]) -> None:
        """Store one event (retried for as long as the database does not answer, until close()
        gives up), then hand it to the topic's listeners."""
        def store() -> int:
            with self.db.session() as s:
                event_id = writes.add_event(s, topic=topic, event=event)
                announce(s, topic=topic, event_id=event_id, instance_id=self.instance_id)
                return event_id

        stored = {**event, "id": retry_transient(
            store, budget_s=math.inf, stopping=self._giving_up,
            what=f"storing a {event['type']} event of {topic.kind} {topic.id}")}
        with self._lock:
            self._fan_out(topic, stored)
        if stored["type"] == "state":
            log_state_event(topic.kind, topic.id, stored)

    def _queued_for(self, topic: Topic) -> bool:
        """True if an event of ``topic`` waits to be stored, or its final state is being saved
        (:meth:`finish`)."""
        with self._queued:
            return topic in self._finishing or any(queued == topic for queued, _ in self._queue)

    def _fan_out(self, topic: Topic, event: dict[str, Any]) -> None:
        for loop, queue in self._listeners.get(topic, ()):
            with contextlib.suppress(RuntimeError):  # the listener's loop has closed
                loop.call_soon_threadsafe(queue.put_nowait, event)

    def _deliver_stored(self, topic: Topic, event_id: int) -> None:
        """Hand another service's stored event to this one's listeners of its topic (a
        listener skips what it has already)."""
        with self._lock:
            if topic not in self._listeners:
                return
        with self.db.session() as s:
            found = queries.events_after(s, topic=topic, after=event_id - 1)
        with self._lock:
            for event in found:
                if event["id"] == event_id:
                    self._fan_out(topic, event)

    def publish_state(self, topic: Topic) -> None:
        """Publish the topic's stored state as a ``state`` event."""
        self.publish(topic, self.state(topic))

    def state(self, topic: Topic) -> dict[str, Any]:
        """The topic's ``state`` event (404 for an unknown id)."""
        with self.db.session() as s:
            return state_event(s, topic)

    def backlog(self, topic: Topic, after: int | None) -> list[dict[str, Any]]:
        """What a listener gets before the live events: the state as of the newest stored
        event (``after`` None, or beyond the newest stored event: not an id this stream
        gave), or the stored events after ``after``, followed by the state if the topic has
        ended without a stored final ``state`` event (404 for an unknown id)."""
        with self.db.session() as s:
            state = {**state_event(s, topic), "id": queries.last_event_id(s, topic=topic)}
            if after is None or after > state["id"]:
                return [state]
            events = queries.events_after(s, topic=topic, after=after)
        if ends_stream(state) and not any(ends_stream(e) for e in events):
            return self._ended_unstored(topic, after, state, events)
        return events

    def _ended_unstored(self, topic: Topic, after: int, state: dict[str, Any],
                        events: list[dict[str, Any]]) -> list[dict[str, Any]]:
        """The backlog of a topic that had ended without a stored final ``state`` event when
        ``events`` were read. If one of its events is queued, or its final state is being saved
        (:meth:`finish`), the final state is on its way to the listener. Else read again: the
        writer takes an event off the queue only once it is stored, so a final state stored
        since the first read is there now (ending the stream with a made-up state instead
        repeated the last event's id, and the stored one was never sent). Only a topic whose
        final state is not stored or queued at all ends with its state made from the row, as
        of the newest stored event."""
        if self._queued_for(topic):
            return events
        with self.db.session() as s:
            events = queries.events_after(s, topic=topic, after=after)
        if not any(ends_stream(e) for e in events):
            events.append({**state, "id": events[-1]["id"] if events else state["id"]})
        return events


#: The last event of every stream still open when the service stops; not stored, so it has no
#: id and a client's ``Last-Event-ID`` stays that of the last stored event it got.
SHUTDOWN_EVENT: dict[str, Any] = {
    "type": "shutdown",
    "detail": "The service is shutting down; reconnect with Last-Event-ID once it is back."}


def ends_stream(event: dict[str, Any]) -> bool:
    """True for the event after which a stream ends (its final ``state``, or ``shutdown``)."""
    if event["type"] == "shutdown":
        return True
    final = FINAL_RUN_STATES if "run_id" in event else FINAL_JOB_STATES
    return event["type"] == "state" and event["state"] in final


def state_event(s: Session, topic: Topic) -> dict[str, Any]:
    """The topic's state as a ``state`` event (404 for an unknown id): a run's with its
    station counts, a calibration's or a validation's with its error and code if it failed."""
    if topic.kind == "run":
        return run_state_event(s, run_id=topic.id)
    row = (queries.get_calibration(s, cal_id=topic.id) if topic.kind == "calibration"
           else queries.get_validation(s, val_id=topic.id))
    return {"type": "state", f"{topic.kind}_id": topic.id, "state": row.state,
            "error": row.error, "error_code": row.error_code}


def run_state_event(s: Session, *, run_id: str) -> dict[str, Any]:
    """The run's state and counts as a ``state`` event (404 for an unknown run)."""
    run = queries.get_run(s, run_id=run_id)
    return {"type": "state", "run_id": run_id, "state": run.state,
            **queries.run_counts(s, run=run),
            "error": None if run.error is None else {"code": run.error_code,
                                                     "detail": run.error},
            "stop_reason": None if run.cold_start is None else run.cold_start.get("stop_reason")}
