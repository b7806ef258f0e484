"""Server-sent event streams of runs, calibrations and validations, written once: each route
answers 404 for an unknown id before the stream starts, then sends the backlog
(``EventBus.backlog``: the state, or what came after ``Last-Event-ID``) and the live events,
and ends after the final ``state`` (or the ``shutdown`` event when the service stops first).
A ``Last-Event-ID`` that is not an event id of the stream is ignored (``event_id``)."""

from __future__ import annotations

import asyncio
import json
import math
import re
from collections.abc import AsyncIterator
from typing import Annotated, Any

from fastapi import Header
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import StreamingResponse

from service.events import EventBus, ends_stream
from service.store.records import Topic

#: Seconds between keep-alive comments on an idle event stream (proxies drop silent ones).
KEEPALIVE_S = 15.0

#: The largest event id a database stores (a signed 64-bit row id).
MAX_EVENT_ID = 2**63 - 1
_EVENT_ID = re.compile(r"[0-9]{1,19}")

LastEventId = Annotated[str | None, Header(
    description="resume after this event id: the stored events after it come first")]


def stream_doc(events: str) -> dict[int | str, dict[str, Any]]:
    """The OpenAPI ``responses`` of a stream route whose events are ``events`` (the error
    statuses are added for every route by ``service.api.openapi``)."""
    return {200: {"content": {"text/event-stream": {}},
                  "description": f"server-sent events: {events}; ids are stable, the stream "
                                 "ends after the final `state`"}}


async def event_stream(events: EventBus, topic: Topic,
                       last_event_id: str | None) -> StreamingResponse:
    """The topic's events as server-sent events; a client that reconnects with
    ``Last-Event-ID`` (browsers do) misses none and sees none twice."""
    await run_in_threadpool(events.state, topic)  # 404 before the stream starts
    return StreamingResponse(_stream(events, topic, event_id(last_event_id)),
                             media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})


def event_id(header: str | None) -> int | None:
    """The event id a ``Last-Event-ID`` header names, or None for a header that cannot be
    one (empty, not ASCII digits, beyond a database integer): such a header is ignored, as
    if the listener were new."""
    if header is None or not _EVENT_ID.fullmatch(header):
        return None
    value = int(header)
    return value if value <= MAX_EVENT_ID else None


async def _stream(events: EventBus, topic: Topic, after: int | None) -> AsyncIterator[str]:
    """The backlog, then live events newer than what was sent."""
    with events.listen(topic) as queue:
        backlog = await run_in_threadpool(events.backlog, topic, after)
        last = after or 0
        for event in backlog:
            yield _sse(event)
            if ends_stream(event):
                return
            last = event["id"]  # ascending; the state's is the newest stored event's
        while True:
            try:
                event = await asyncio.wait_for(queue.get(), KEEPALIVE_S)
            except TimeoutError:
                yield ": keep-alive\n\n"
                continue
            if event.get("id", math.inf) <= last:  # already sent in the backlog
                continue
            last = event.get("id", last)
            yield _sse(event)
            if ends_stream(event):
                return


def _sse(event: dict[str, Any]) -> str:
    """One server-sent event; the ``shutdown`` event has no id (it is not stored)."""
    data = {k: v for k, v in event.items() if k != "id"}
    head = f"id: {event['id']}\n" if "id" in event else ""
    return f"{head}event: {event['type']}\ndata: {json.dumps(data)}\n\n"
