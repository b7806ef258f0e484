"""Short ids: any unique prefix of a run, calibration or validation id names it, as in git.

The page and the CLI's tables show the first 8 characters of an id; people type those back.
:class:`ShortIds` is plain ASGI middleware that rewrites the id segment of a path
(``/runs/<id>/...``, ``/calibrations/<id>/...``, ``/validations/<id>/...``) to the full id before
routing, so every route, manager and event stream sees full ids only and nothing downstream
learns about prefixes. A prefix that names no record is left alone (the route answers 404 as
for any unknown id); one that names several is refused with 409 ``ambiguous_id``, listing them.
It sits behind the request guard, so nobody without the key learns which ids exist.
"""

from __future__ import annotations

import re
from collections.abc import Callable

from sqlalchemy import select
from starlette.concurrency import run_in_threadpool
from starlette.responses import Response
from starlette.types import ASGIApp, Receive, Scope, Send

from service.errors import ConflictError
from service.store.db import Database
from service.store.records import CalibrationRecord, RunRecord, ValidationRecord

#: The collection of each kind of id, and the table that holds it.
RECORDS = {"runs": RunRecord, "calibrations": CalibrationRecord, "validations": ValidationRecord}
#: Ids are 32 lowercase hex digits (``uuid4().hex``); a prefix is 4 to 31 of them (a full id
#: needs no lookup).
_PREFIX = re.compile(r"[0-9a-f]{4,31}")
#: How many candidates an ambiguous answer names at most.
MAX_CANDIDATES = 10


class AmbiguousIdError(ConflictError, code="ambiguous_id"):
    """A prefix that names more than one record (409)."""


def _split(path: str) -> tuple[str, str, str] | None:
    """``/runs/1a2b/events`` -> ``("runs", "1a2b", "/events")`` when the segment may be a
    prefix; None for every other path."""
    parts = path.split("/", 3)
    if len(parts) < 3 or parts[0] or parts[1] not in RECORDS or not _PREFIX.fullmatch(parts[2]):
        return None
    return parts[1], parts[2], "/" + parts[3] if len(parts) == 4 else ""


class ShortIds:
    """Rewrite a unique id prefix in the path to the full id (see the module's docstring)."""

    def __init__(self, app: ASGIApp, *,
                 refuse: Callable[[Exception], Response]) -> None:
        self.app = app
        self.refuse = refuse

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        split = _split(scope["path"]) if scope["type"] == "http" else None
        if split is not None:
            collection, prefix, rest = split
            db = scope["app"].state.db
            matches = await run_in_threadpool(_matches, db, RECORDS[collection], prefix)
            if len(matches) > 1:
                shown = ", ".join(matches[:MAX_CANDIDATES])
                more = " and more" if len(matches) > MAX_CANDIDATES else ""
                error = AmbiguousIdError(f"The id prefix {prefix} names more than one of "
                                         f"{collection}: {shown}{more}; give more characters.")
                await self.refuse(error)(scope, receive, send)
                return
            if len(matches) == 1:
                path = f"/{collection}/{matches[0]}{rest}"
                scope = {**scope, "path": path, "raw_path": path.encode()}
        await self.app(scope, receive, send)


def _matches(db: Database, record: type[RunRecord | CalibrationRecord | ValidationRecord],
             prefix: str) -> list[str]:
    """The ids of ``record`` that start with ``prefix`` (at most ``MAX_CANDIDATES + 1``)."""
    with db.session() as s:
        return list(s.scalars(select(record.id).where(record.id.startswith(prefix, autoescape=True))
                              .order_by(record.id).limit(MAX_CANDIDATES + 1)))
