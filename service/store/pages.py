"""Keyset cursors for newest-first listings (``GET /runs``, ``GET /calibrations``).

A page ends at its last row; the cursor names that row by ``(created_at, id)`` and the next
page is the rows strictly before it in that order, read from the ``(created_at, id)`` index,
so a page costs the same at the 10th row as at the 10,000th, and rows added meanwhile never
shift a page (as an offset would).
"""

from __future__ import annotations

import datetime as dt
import re
from dataclasses import dataclass
from typing import Any

from sqlalchemy import Select, tuple_

from service.errors import UnprocessableError

_EPOCH = dt.datetime(1970, 1, 1, tzinfo=dt.UTC)
_CURSOR = re.compile(r"([0-9]{1,19})\.([0-9a-f]{32})")


@dataclass(frozen=True)
class Cursor:
    """Where a page ended: the last row's creation time and id."""

    created_at: dt.datetime
    id: str

    def encode(self) -> str:
        """``<microseconds since 1970>.<id>``: opaque to clients, safe in a URL."""
        return f"{(self.created_at - _EPOCH) // dt.timedelta(microseconds=1)}.{self.id}"

    @classmethod
    def decode(cls, text: str) -> Cursor:
        """The cursor ``encode`` wrote (422 ``invalid_cursor`` for anything else)."""
        match = _CURSOR.fullmatch(text)
        try:
            if match is not None:
                return cls(_EPOCH + dt.timedelta(microseconds=int(match[1])), match[2])
        except OverflowError:  # after the year 9999: not a time this service wrote
            pass
        raise UnprocessableError(f"cursor {text[:80]!r} is not a cursor this service gave; "
                                 "start again without one.", code="invalid_cursor")

    @classmethod
    def of(cls, row: Any) -> Cursor:
        return cls(row.created_at, row.id)


def newest_first(query: Select[Any], model: Any, *, cursor: Cursor | None,
                 limit: int) -> Select[Any]:
    """``query`` ordered newest first by ``model``'s ``(created_at, id)``, from after
    ``cursor``, at most ``limit`` rows."""
    if cursor is not None:
        # one row-value comparison, which both databases answer from the index (a range that
        # starts at the cursor); the same condition spelt with OR was a filter over every
        # newer row: a page near the oldest end of 5,000 calibrations read 4,750 rows
        query = query.where(tuple_(model.created_at, model.id)
                            < tuple_(cursor.created_at, cursor.id))
    return query.order_by(model.created_at.desc(), model.id.desc()).limit(limit)
