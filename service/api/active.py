"""The calibration registry: list calibrations, make one the cell's current one, read the
current one with the history of what was active when."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Depends, Query

from service.api.deps import SessionDep, SettingsDep, writable_storage
from service.api.finished import calibration_view
from service.api.routing import OneThreadRoute
from service.schemas import (
    ActiveCalibration,
    CalibrationPage,
    CalibrationQuery,
    CalibrationSummary,
)
from service.store import active, queries
from service.store.pages import Cursor

#: Periods of what was active when that ``GET /calibrations/active`` brings by default: a
#: cell controller polling for its current calibration reads them every time, and a plant's
#: year of re-checks would make that answer grow with the history (issue 21); ask for up to
#: 500 with ``history``.
HISTORY = 10
History = Annotated[int, Query(ge=1, le=500, description="periods of what was active when, "
                                                         "newest first")]

router = APIRouter(prefix="/calibrations", tags=["calibrations"], route_class=OneThreadRoute)


@router.get("")
def list_calibrations(session: SessionDep,
                      query: Annotated[CalibrationQuery, Query()]) -> CalibrationPage:
    """Calibrations, newest first, a page at a time (summaries: read one for its result)."""
    rows, total = queries.page_calibrations(
        session, where=queries.CalibrationFilter(run_id=query.run_id, cell=query.cell,
                                               active=query.active, state=query.state,
                                               setup=query.setup),
        limit=query.limit, offset=query.offset,
        cursor=None if query.cursor is None else Cursor.decode(query.cursor))
    items = [CalibrationSummary.model_validate(row._mapping) for row in rows]
    end, exact = query.offset + len(items), total <= queries.COUNT_LIMIT
    more = len(items) == query.limit
    further = end < total if exact else more  # past the count's limit: while pages are full
    return CalibrationPage(items=items, total=min(total, queries.COUNT_LIMIT), total_exact=exact,
                           limit=query.limit, offset=query.offset,
                           next_offset=end if further and query.cursor is None else None,
                           next_cursor=Cursor.of(rows[-1]).encode() if more else None)


@router.get("/active", responses={404: {"description": "no calibration was activated"}})
def get_active(session: SessionDep, settings: SettingsDep,
               cell: Annotated[str | None, Query(
                   max_length=255, description="default: this service's cell")] = None,
               setup: Annotated[Literal["eye_in_hand", "eye_to_hand"] | None, Query(
                   description="default: this service's setup")] = None,
               history: History = HISTORY) -> ActiveCalibration:
    """The calibration a cell controller should use now, and what was active when."""
    return _active(session, cell=cell or settings.cell,
                   setup=setup or settings.calibration_setup(), history=history)


@router.post("/{cal_id}/activate", dependencies=[Depends(writable_storage)], responses={
    404: {"description": "no such calibration"},
    409: {"description": "the calibration is running or failed"}})
def activate(cal_id: str, session: SessionDep,
             history: History = HISTORY) -> ActiveCalibration:
    """Make a finished calibration the current one of its cell and setup (idempotent)."""
    cell, setup = active.activate(session, cal_id=cal_id)
    return _active(session, cell=cell, setup=setup, history=history)


def _active(session: SessionDep, *, cell: str, setup: str, history: int) -> ActiveCalibration:
    now, periods = active.current(session, cell=cell, setup=setup, history=history)
    return ActiveCalibration(cell=cell, setup=setup, robot=now.robot,
                             activated_at=now.activated_at,
                             calibration=calibration_view(session, cal_id=now.calibration_id),
                             history=periods)
