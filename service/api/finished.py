"""Public views of finished calibrations, kept in memory (issue 21).

A calibration that is ``done`` or ``failed`` never changes: ``store.writes`` updates only a
running one and deletes none. Its view (``CalibrationPublic``, the result document validated
into ``calib.Result`` and back) is therefore made once per service and database and served
from here by ``GET /calibrations/{id}`` and ``GET /calibrations/active``; validating a result
document costs more than the rest of such a request. A running calibration is read every time.
"""

from __future__ import annotations

import threading
from collections import OrderedDict

from sqlalchemy.orm import Session

from service.schemas import CalibrationPublic
from service.store import queries

#: Views kept, least recently read dropped first (a result document is 1-100 kB).
KEPT = 256

_views: OrderedDict[tuple[str, str], CalibrationPublic] = OrderedDict()
_lock = threading.Lock()


def calibration_view(s: Session, *, cal_id: str) -> CalibrationPublic:
    """The calibration's public view (404 for an unknown id), from memory once finished."""
    key = (s.get_bind().url.render_as_string(), cal_id)
    with _lock:
        view = _views.get(key)
        if view is not None:
            _views.move_to_end(key)
            return view
    view = CalibrationPublic.model_validate(queries.get_calibration(s, cal_id=cal_id))
    if view.state != "running":
        with _lock:
            _views[key] = view
            while len(_views) > KEPT:
                _views.popitem(last=False)
    return view
