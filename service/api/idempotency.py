"""Idempotent starts (issue 19 item 7): a request that starts work (a run, a calibration, a
dot-hit validation, a re-check) sent again with the same ``Idempotency-Key`` gets the first
answer, so a double click or a client's retry after a lost answer starts nothing twice.

:class:`Idempotency` is ASGI middleware behind the short-id rewrite (paths hold full ids). The
key is reserved in the database (``IdempotencyRecord``, one row per cell and key) before the
request runs, so the rule holds across threads, service instances and restarts:

- a new key: the request runs; a 2xx answer is stored with the key, any other answer frees
  the key so the client can retry;
- the same key and the same request (method, path, body): the stored answer again, marked
  ``Idempotent-Replayed: true``; 409 ``request_in_progress`` while the first is still running;
- the same key with another request: 422 ``idempotency_key_reused``.

Keys are kept ``KEEP`` (a day), as common practice for payment APIs; a reservation whose
request never finished (the process died) is taken over after ``ABANDONED``.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import hashlib
import json
import re
from collections.abc import Callable
from typing import Any

from starlette.concurrency import run_in_threadpool
from starlette.responses import Response
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.errors import ConflictError, ServiceError, UnprocessableError
from service.store import writes
from service.store.db import Database
from service.store.records import IdempotencyRecord

HEADER = "idempotency-key"
#: The requests that start work.
STARTS = re.compile(r"/runs|/runs/[0-9a-f]{32}/calibrations"
                    r"|/calibrations/[0-9a-f]{32}/(validations|checks)")
_KEY = re.compile(r"[\x21-\x7e]{1,255}")
#: STARTS as OpenAPI path templates (``/runs/{run_id}/calibrations``).
START_TEMPLATES = re.compile(STARTS.pattern.replace("[0-9a-f]{32}", r"\{[a-z_]+\}"))
#: The header as an OpenAPI parameter of the operations that start work.
PARAMETER = {
    "name": "Idempotency-Key", "in": "header", "required": False,
    "description": "Any client-chosen key, e.g. a UUID. The same key with the same request "
                   "within a day answers the first answer again (Idempotent-Replayed: true) "
                   "and starts nothing; 409 request_in_progress while the first is still "
                   "being answered; 422 idempotency_key_reused with another request.",
    "schema": {"type": "string", "minLength": 1, "maxLength": 255,
               "pattern": "^[\\x21-\\x7e]+$"}}
KEEP = dt.timedelta(days=1)
ABANDONED = dt.timedelta(minutes=10)


class InvalidKeyError(ServiceError, code="invalid_idempotency_key"):
    """An ``Idempotency-Key`` that is empty, longer than 255 or not printable ASCII (400)."""


class KeyReusedError(UnprocessableError, code="idempotency_key_reused"):
    """The key was used for another request (422)."""


class InProgressError(ConflictError, code="request_in_progress"):
    """The first request with this key is still being answered (409)."""


def request_hash(method: str, path: str, body: bytes) -> str:
    """SHA-256 of what was asked; a JSON body counts by its content, not its spacing."""
    with contextlib.suppress(ValueError, RecursionError):  # not JSON, or nested too deep
        body = json.dumps(json.loads(body), sort_keys=True, separators=(",", ":")).encode()
    return hashlib.sha256(b"%s %s\n%s" % (method.encode(), path.encode(), body)).hexdigest()


class Idempotency:
    """Answer a repeated start from the database (see the module's docstring)."""

    def __init__(self, app: ASGIApp, *, refuse: Callable[[Exception], Response]) -> None:
        self.app = app
        self.refuse = refuse

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        key = _key(scope)
        if key is None:
            await self.app(scope, receive, send)
            return
        if not _KEY.fullmatch(key):
            await self.refuse(InvalidKeyError(
                "Idempotency-Key must be 1 to 255 printable ASCII characters without spaces"))(
                scope, receive, send)
            return
        body = await _read_body(receive)
        db: Database = scope["app"].state.db
        cell: str = scope["app"].state.settings.cell
        digest = request_hash(scope["method"], scope["path"], body)
        try:
            stored = await run_in_threadpool(_reserve, db, cell, key, digest)
        except ServiceError as exc:
            await self.refuse(exc)(scope, receive, send)
            return
        if stored is not None:
            await _replay(stored, send)
            return
        await self._first(scope, body, send, (db, cell, key))

    async def _first(self, scope: Scope, body: bytes, send: Send,
                     where: tuple[Database, str, str]) -> None:
        """Run the request whose key was just reserved; keep its answer if it succeeded."""
        answer: dict[str, Any] = {"status": 500, "body": b""}

        async def receive_body() -> Message:
            return {"type": "http.request", "body": body, "more_body": False}

        async def keep(message: Message) -> None:
            if message["type"] == "http.response.start":
                answer["status"] = message["status"]
            elif message["type"] == "http.response.body":
                answer["body"] += message.get("body", b"")
            await send(message)

        try:
            await self.app(scope, receive_body, keep)
        finally:
            await run_in_threadpool(_settle, *where, answer["status"], answer["body"])


def _key(scope: Scope) -> str | None:
    """The request's Idempotency-Key when it starts work, else None."""
    if scope["type"] != "http" or scope["method"] != "POST" or not STARTS.fullmatch(scope["path"]):
        return None
    for name, value in scope["headers"]:
        if name.decode("latin-1").lower() == HEADER:
            return str(value.decode("latin-1"))
    return None


async def _read_body(receive: Receive) -> bytes:
    body = b""
    while True:
        message = await receive()
        body += message.get("body", b"")
        if not message.get("more_body"):
            return body


def _reserve(db: Database, cell: str, key: str, digest: str) -> IdempotencyRecord | None:
    """Reserve ``key`` for this request (None) or return the row of the earlier request with
    it; raises when that one was another request or is still running."""
    for _ in range(2):  # a key freed between the two steps is reserved at the second try
        with db.session() as s:
            mine = IdempotencyRecord(cell=cell, key=key, request_hash=digest)
            if writes.reserve_idempotency_key(s, mine, keep=KEEP, abandoned=ABANDONED):
                return None
            row = s.get(IdempotencyRecord, (cell, key))
        if row is not None:
            break
    if row is None:
        raise InProgressError(f"Idempotency-Key {key} is changing hands; ask again")
    if row.request_hash != digest:
        raise KeyReusedError(f"Idempotency-Key {key} was used for another request "
                             "(other path or body); use a new key for a new request")
    if row.status is None:
        raise InProgressError(f"the first request with Idempotency-Key {key} is still being "
                              "answered; ask again in a moment")
    return row


def _settle(db: Database, cell: str, key: str, status: int, body: bytes) -> None:
    with db.session() as s:
        writes.settle_idempotency_key(s, cell=cell, key=key, status=status, body=body.decode())


async def _replay(row: IdempotencyRecord, send: Send) -> None:
    body = (row.body or "").encode()
    await send({"type": "http.response.start", "status": row.status, "headers": [
        (b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
        (b"idempotent-replayed", b"true")]})
    await send({"type": "http.response.body", "body": body})
