"""Server-sent event streams of runs, calibrations and validations, written once: each route
answers 404 for an unknown id before the stream starts, then sends the backlog
(``EventBus.backlog``: the state, or what came after ``Last-Event-ID``) and the live events,
and ends after the final ``state``."""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from typing import Annotated, Any

from fastapi import Header
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import StreamingResponse

from service.events import EventBus, ends_stream
from service.models import Topic

#: Seconds between keep-alive comments on an idle event stream (proxies drop silent ones).
KEEPALIVE_S = 15.0

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
    after = int(last_event_id) if last_event_id and last_event_id.isdigit() else None
    return StreamingResponse(_stream(events, topic, after), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})


async def _stream(events: EventBus, topic: Topic, after: int | None) -> AsyncIterator[str]:
    """The backlog, then live events newer than what was sent."""
    with events.listen(topic) as queue:
        backlog = await run_in_threadpool(events.backlog, topic, after)
        last = after or 0
        for event in backlog:
            yield _sse(event)
            if ends_stream(event):
                return
            last = max(last, event["id"])
        while True:
            try:
                event = await asyncio.wait_for(queue.get(), KEEPALIVE_S)
            except TimeoutError:
                yield ": keep-alive\n\n"
                continue
            if event["id"] <= last:  # already sent in the backlog
                continue
            last = event["id"]
            yield _sse(event)
            if ends_stream(event):
                return


def _sse(event: dict[str, Any]) -> str:
    data = {k: v for k, v in event.items() if k != "id"}
    return f"id: {event['id']}\nevent: {event['type']}\ndata: {json.dumps(data)}\n\n"
