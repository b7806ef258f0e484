"""Events across services on PostgreSQL: every stored event is announced with ``NOTIFY``, and
each service ``LISTEN``s, so a client may follow a run, calibration or validation on any
service of the plant, not only on the one doing the work.

The notification carries only the topic, the event id and the announcing instance; a
listening service reads the event row itself (the stored event is the one truth, and a
notification's payload is limited to 8000 bytes). Its own announcements it skips: its
listeners got those events directly. With SQLite there is no relay: the service that does
the work serves its events, as before.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from sqlalchemy import Engine, text
from sqlalchemy.orm import Session

from service.store.records import Topic

log = logging.getLogger("cellcal.service")

CHANNEL = "cellcal_events"
#: Seconds between checks of the stop flag while no notification comes.
_POLL_S = 1.0

#: ``deliver(topic, event_id)``: hand a stored event to this service's listeners.
Deliver = Callable[[Topic, int], None]


def announce(s: Session, *, topic: Topic, event_id: int, instance_id: str) -> None:
    """Announce a stored event to the other services (PostgreSQL; nothing elsewhere)."""
    if s.get_bind().dialect.name != "postgresql":
        return
    s.execute(text("SELECT pg_notify(:channel, :payload)"),
              {"channel": CHANNEL, "payload": f"{topic.kind} {topic.id} {event_id} "
                                              f"{instance_id}"})
    s.commit()


class EventRelay:
    """The thread that listens for other services' events and delivers them here."""

    def __init__(self, engine: Engine, instance_id: str, deliver: Deliver) -> None:
        self.conninfo = engine.url.set(drivername="postgresql").render_as_string(
            hide_password=False)
        self.instance_id = instance_id
        self.deliver = deliver
        self._stop = threading.Event()
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._listen, name="event-relay", daemon=True)

    def start(self) -> None:
        """Start listening; returns once ``LISTEN`` is in force (or failed, logged)."""
        self._thread.start()
        self._ready.wait(30.0)

    def _listen(self) -> None:
        import psycopg

        while not self._stop.is_set():
            try:
                with psycopg.connect(self.conninfo, autocommit=True) as conn:
                    conn.execute(f"LISTEN {CHANNEL}")
                    self._ready.set()
                    while not self._stop.is_set():
                        for note in conn.notifies(timeout=_POLL_S):
                            self._relay(note.payload)
            except psycopg.Error as exc:  # the server restarted: listen again
                log.warning("event relay: %s; listening again in 1 s", exc)
                self._ready.set()
                self._stop.wait(1.0)

    def _relay(self, payload: str) -> None:
        try:
            kind, topic_id, event_id, instance_id = payload.split(" ")
            if instance_id != self.instance_id:
                self.deliver(Topic(kind, topic_id), int(event_id))  # type: ignore[arg-type]
        except Exception as exc:  # one bad notification must not end the relay
            log.warning("event relay: notification %r: %s", payload, exc)

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(2 * _POLL_S + 5.0)
