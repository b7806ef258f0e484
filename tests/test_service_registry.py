"""The calibration registry: ``GET /calibrations`` (filters, newest first, pages),
``POST /calibrations/{id}/activate`` and ``GET /calibrations/active`` with its history.

Runs and calibrations are written straight into the database (solves are tested elsewhere),
with creation times set, so the order is known.
"""

from __future__ import annotations

import datetime as dt
from typing import Any

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import event, select, text

from service.api.active import HISTORY
from service.store import queries, writes
from service.store.pages import Cursor, newest_first
from service.store.records import CalibrationRecord, RunRecord
from tests.support.results import full_result, pose_only_result
from tests.support.service import CELL

pytestmark = [pytest.mark.timeout(20), pytest.mark.usefixtures("database")]

T0 = dt.datetime(2026, 1, 5, 8, 0, tzinfo=dt.UTC)



def add_run(client: TestClient, *, setup: str = "eye_in_hand", robot: str = "mock://",
            cell: str = CELL) -> str:
    run = RunRecord(cell=cell, robot=robot, state="done", setup=setup,
                    target={"inner_corners": [11, 8], "square_size_m": 0.03}, poses=[])
    with client.app.state.db.session() as s:
        s.add(run)
        s.commit()
    return run.id


def add_calibration(client: TestClient, run_id: str, *, minute: int, state: str = "done",
                    **columns: Any) -> str:
    """A calibration of ``run_id`` created ``minute`` minutes after T0 (a joint solve with
    ``full_result`` unless ``columns`` say otherwise); its id."""
    values = {"cell": CELL, "options": {"method": "joint"},
              "error": "boom" if state == "failed" else None,
              "result": full_result() if state == "done" else None, **columns}
    cal = CalibrationRecord(run_id=run_id, state=state,
                            created_at=T0 + dt.timedelta(minutes=minute), **values)
    with client.app.state.db.session() as s:
        s.add(cal)
        s.commit()
    return cal.id


def ids(page: dict[str, Any]) -> list[str]:
    return [item["id"] for item in page["items"]]


@pytest.mark.pg_fast
def test_listing_is_newest_first_with_summaries(client: TestClient) -> None:
    run_id = add_run(client)
    old = add_calibration(client, run_id, minute=1, result=pose_only_result(),
                          options={"method": "sm"})
    new = add_calibration(client, run_id, minute=2)
    running = add_calibration(client, run_id, minute=3, state="running")
    page = client.get("/calibrations").json()
    assert ids(page) == [running, new, old]
    assert (page["total"], page["offset"], page["next_offset"]) == (3, 0, None)
    by_id = {item["id"]: item for item in page["items"]}
    assert by_id[new]["rms_px"] == pytest.approx(0.05)
    assert by_id[old]["rms_px"] is None  # pose-only: no camera model
    assert (by_id[old]["method"], by_id[new]["method"]) == ("sm", "joint")
    assert by_id[new]["setup"] == "eye_in_hand" and by_id[new]["robot"] == "mock://"
    assert "result" not in by_id[new]
    assert not any(item["active"] for item in page["items"])


def test_filters_by_run_state_and_setup(client: TestClient) -> None:
    hand, fixed = add_run(client), add_run(client, setup="eye_to_hand")
    a = add_calibration(client, hand, minute=1)
    b = add_calibration(client, hand, minute=2, state="failed")
    c = add_calibration(client, fixed, minute=3, result=full_result(setup="eye_to_hand"))
    assert ids(client.get("/calibrations", params={"run_id": hand}).json()) == [b, a]
    assert ids(client.get("/calibrations", params={"state": "done"}).json()) == [c, a]
    assert ids(client.get("/calibrations", params={"setup": "eye_to_hand"}).json()) == [c]
    both = client.get("/calibrations", params={"run_id": hand, "state": "failed"}).json()
    assert ids(both) == [b] and both["total"] == 1
    assert client.get("/calibrations", params={"run_id": "nope"}).json()["total"] == 0


@pytest.mark.pg_fast
def test_pages_cover_every_calibration_once(client: TestClient) -> None:
    run_id = add_run(client)
    made = [add_calibration(client, run_id, minute=m) for m in range(7)]
    seen, offset = [], 0
    while offset is not None:
        page = client.get("/calibrations", params={"limit": 3, "offset": offset}).json()
        assert page["total"] == 7 and len(page["items"]) <= 3
        seen += ids(page)
        offset = page["next_offset"]
    assert seen == made[::-1]


@pytest.mark.pg_fast
def test_cursors_cover_every_calibration_once_ties_and_new_rows_included(
        client: TestClient) -> None:
    """Keyset pages: rows created at the same instant are told apart by id, and a row added
    while paging does not shift the pages."""
    run_id = add_run(client)
    made = [add_calibration(client, run_id, minute=m // 2) for m in range(7)]  # pairs tie
    expected = sorted(made, key=lambda c: (made.index(c) // 2, c), reverse=True)
    seen, cursor = [], None
    while True:
        page = client.get("/calibrations", params={"limit": 3, **(
            {"cursor": cursor} if cursor else {})}).json()
        seen += ids(page)
        if len(seen) == 3:
            add_calibration(client, run_id, minute=9)  # newer: on no page after the first
        if (cursor := page["next_cursor"]) is None:
            break
    assert seen == expected


def test_runs_pages_follow_the_link_header(client: TestClient) -> None:
    made = [add_run(client) for _ in range(5)]
    seen, url = [], "/runs?limit=2"
    while url:
        r = client.get(url)
        seen += [run["id"] for run in r.json()]
        url = r.links.get("next", {}).get("url")
    assert sorted(seen) == sorted(made) and len(seen) == 5
    for cursor in ("12.nope", "9" * 19 + "." + "0" * 32):  # not one; after the year 9999
        bad = client.get("/calibrations", params={"cursor": cursor})
        assert (bad.status_code, bad.json()["code"]) == (422, "invalid_cursor")


@pytest.mark.parametrize("params", [{"state": "finished"}, {"setup": "eye_on_hand"},
                                    {"limit": 0}, {"limit": 201}, {"offset": -1}])
def test_bad_listing_parameters_are_422(client: TestClient, params: dict[str, Any]) -> None:
    r = client.get("/calibrations", params=params)
    assert r.status_code == 422
    assert r.json()["code"] == "invalid_request"


def test_no_active_calibration_is_404(client: TestClient) -> None:
    r = client.get("/calibrations/active")
    assert r.status_code == 404
    assert r.json()["code"] == "no_active_calibration"


@pytest.mark.pg_fast
def test_activation_history_says_what_was_active_when(client: TestClient) -> None:
    run_id = add_run(client)
    first = add_calibration(client, run_id, minute=1)
    second = add_calibration(client, run_id, minute=2)
    r = client.post(f"/calibrations/{first}/activate")
    assert r.status_code == 200, r.text
    assert r.json()["calibration"]["id"] == first
    client.post(f"/calibrations/{second}/activate")
    again = client.post(f"/calibrations/{second}/activate").json()  # idempotent
    active = client.get("/calibrations/active").json()
    assert active == again
    assert active["robot"] == "mock://"
    assert active["calibration"]["id"] == second
    assert active["calibration"]["state"] == "done"
    assert active["calibration"]["result"] == full_result()
    history = active["history"]
    assert [h["calibration_id"] for h in history] == [second, first]
    assert history[0]["active_until"] is None
    assert history[0]["active_from"] == active["activated_at"]
    assert history[1]["active_until"] == history[0]["active_from"]
    assert history[1]["active_from"] <= history[1]["active_until"]
    listed = {item["id"]: item["active"] for item in client.get("/calibrations").json()["items"]}
    assert listed == {first: False, second: True}
    # going back to the first one adds a period; the history is never rewritten
    client.post(f"/calibrations/{first}/activate")
    history = client.get("/calibrations/active", params={"history": 2}).json()["history"]
    assert [h["calibration_id"] for h in history] == [first, second]


def test_the_active_calibration_brings_a_page_of_its_history(client: TestClient) -> None:
    """By default the last ``HISTORY`` periods (a controller polling for its calibration
    reads them every time, however many re-checks the cell has had); ``history`` asks for
    more."""
    run_id = add_run(client)
    made = [add_calibration(client, run_id, minute=m) for m in range(HISTORY + 3)]
    for cal_id in made:
        client.post(f"/calibrations/{cal_id}/activate")
    newest = [h["calibration_id"] for h in client.get("/calibrations/active").json()["history"]]
    assert newest == made[::-1][:HISTORY]
    more = client.get("/calibrations/active", params={"history": 500}).json()["history"]
    assert [h["calibration_id"] for h in more] == made[::-1]


@pytest.mark.parametrize("state", ["running", "failed"])
def test_only_a_finished_calibration_can_be_activated(client: TestClient, state: str) -> None:
    cal_id = add_calibration(client, add_run(client), minute=1, state=state)
    r = client.post(f"/calibrations/{cal_id}/activate")
    assert r.status_code == 409
    assert r.json()["code"] == "invalid_state"
    assert client.get("/calibrations/active").status_code == 404


def test_activating_an_unknown_calibration_is_404(client: TestClient) -> None:
    r = client.post("/calibrations/nope/activate")
    assert r.status_code == 404
    assert r.json()["code"] == "not_found"


@pytest.mark.pg_fast
def test_each_cell_and_setup_has_its_own_active_calibration(client: TestClient) -> None:
    here = add_calibration(client, add_run(client), minute=1)
    there = add_calibration(client, add_run(client, cell="press-7"), minute=2, cell="press-7")
    fixed = add_calibration(client, add_run(client, setup="eye_to_hand"), minute=3)
    for cal_id in (here, there, fixed):
        assert client.post(f"/calibrations/{cal_id}/activate").status_code == 200
    assert client.get("/calibrations/active").json()["calibration"]["id"] == here
    other = client.get("/calibrations/active", params={"cell": "press-7"}).json()
    assert (other["cell"], other["setup"], other["calibration"]["id"]) == (
        "press-7", "eye_in_hand", there)
    assert [h["calibration_id"] for h in other["history"]] == [there]
    assert client.get("/calibrations/active", params={"setup": "eye_to_hand"}).json()[
        "calibration"]["id"] == fixed

    def listed(**params: Any) -> list[str]:
        return ids(client.get("/calibrations", params=params).json())

    assert listed(active=True) == [fixed, there, here]
    assert listed(cell="press-7", active=True) == [there]
    assert listed(cell=CELL, active=True) == [fixed, here]
    assert listed(active=False) == []
    assert listed(cell="no-such-cell") == []


@pytest.mark.parametrize("method, path", [("GET", "/calibrations"),
                                          ("GET", "/calibrations/active"),
                                          ("POST", "/calibrations/x/activate")])
def test_registry_needs_the_key(client: TestClient, method: str, path: str) -> None:
    r = client.request(method, path, headers={"Authorization": ""})
    assert r.status_code == 401


def statements(client: TestClient) -> list[str]:
    """The SQL the service runs from now on."""
    seen: list[str] = []
    event.listen(client.app.state.db.engine, "before_cursor_execute",
                 lambda conn, cursor, sql, *rest: seen.append(sql))
    return seen


@pytest.mark.pg_fast
def test_a_finished_calibration_is_read_once_a_running_one_every_time(
        client: TestClient) -> None:
    run_id = add_run(client)
    done, running = add_calibration(client, run_id, minute=1), \
        add_calibration(client, run_id, minute=2, state="running")
    client.post(f"/calibrations/{done}/activate")
    first = client.get(f"/calibrations/{done}").json()
    seen = statements(client)
    assert client.get(f"/calibrations/{done}").json() == first
    assert client.get("/calibrations/active").json()["calibration"] == first
    assert not [sql for sql in seen if "FROM calibrations" in sql]  # kept, not read again

    assert client.get(f"/calibrations/{running}").json()["state"] == "running"
    with client.app.state.db.session() as s:
        writes.finish_calibration(s, cal_id=running, state="failed", error="stopped")
    assert client.get(f"/calibrations/{running}").json()["state"] == "failed"
    assert len([sql for sql in seen if "FROM calibrations" in sql]) == 2


@pytest.mark.pg_fast
def test_a_page_and_its_total_are_one_statement(client: TestClient) -> None:
    """A page of calibrations brings its total along in the same statement (one round trip
    to the database, not two); a page past the end still says how many there are."""
    hand, fixed = add_run(client), add_run(client, setup="eye_to_hand")
    for minute in range(5):
        add_calibration(client, hand if minute % 2 else fixed, minute=minute)
    seen = statements(client)
    page = client.get("/calibrations", params={"limit": 2, "setup": "eye_to_hand"}).json()
    assert (len(page["items"]), page["total"]) == (2, 3)
    assert len([sql for sql in seen if "FROM calibrations" in sql]) == 1
    later = client.get("/calibrations", params={"limit": 2, "cursor": page["next_cursor"],
                                                "setup": "eye_to_hand"}).json()
    assert (len(later["items"]), later["total"]) == (1, 3)
    assert len([sql for sql in seen if "FROM calibrations" in sql]) == 2
    past = client.get("/calibrations", params={"offset": 9}).json()
    assert (past["items"], past["total"]) == ([], 5)


@pytest.mark.pg_fast
def test_a_listing_counts_no_further_than_its_limit(client: TestClient,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """Past ``COUNT_LIMIT`` matches a page says "at least that many" (the count stops, so a
    listing's cost does not grow with the history), and the pages still reach every row;
    at or under the limit the total is exact."""
    monkeypatch.setattr(queries, "COUNT_LIMIT", 4)
    run_id = add_run(client)
    made = [add_calibration(client, run_id, minute=m) for m in range(7)]
    seen, offset = [], 0
    while offset is not None:
        page = client.get("/calibrations", params={"limit": 3, "offset": offset}).json()
        assert (page["total"], page["total_exact"]) == (4, False)
        seen += ids(page)
        offset = page["next_offset"]
    assert seen == made[::-1]
    some = client.get("/calibrations", params={"state": "done", "limit": 2,
                                               "cursor": Cursor(T0 + dt.timedelta(minutes=4),
                                                                 made[4]).encode()}).json()
    assert (some["total"], some["total_exact"]) == (4, False)  # the filter, not the cursor
    first = add_run(client)
    few = [add_calibration(client, first, minute=10 + m) for m in range(4)]
    mine = client.get("/calibrations", params={"run_id": first, "limit": 2}).json()
    assert (mine["total"], mine["total_exact"], mine["next_offset"]) == (4, True, 2)
    last = client.get("/calibrations", params={"run_id": first, "limit": 2, "offset": 2}).json()
    assert ids(last) == few[1::-1] and last["next_offset"] is None


@pytest.mark.pg_fast
def test_a_cursor_page_is_read_from_its_index_range(client: TestClient) -> None:
    """The page after a cursor starts in the ``(created_at, id)`` index at the cursor
    instead of filtering every newer row (a deep page cost what the newer rows cost)."""
    run_id = add_run(client)
    cursor = Cursor(T0, add_calibration(client, run_id, minute=0))
    query = newest_first(select(CalibrationRecord.id), CalibrationRecord, cursor=cursor,
                         limit=50)
    engine = client.app.state.db.engine
    with engine.connect() as conn:
        if engine.dialect.name == "postgresql":  # a tiny table: make it take an index at all
            conn.exec_driver_sql("SET enable_seqscan = off")
            plan = "\n".join(conn.execute(text(f"EXPLAIN {compiled(query, engine)}")).scalars())
            assert "Index Cond: (ROW(created_at, (id)::text) <" in plan, plan
        else:
            plan = "\n".join(row[-1] for row in conn.execute(
                text(f"EXPLAIN QUERY PLAN {compiled(query, engine)}")))
            assert "SEARCH calibrations" in plan, plan
            assert "ix_calibrations_created ((created_at,id)<(?,?))" in plan, plan


def compiled(query: Any, engine: Any) -> str:
    """``query`` as SQL text with its parameters written in."""
    return str(query.compile(engine, compile_kwargs={"literal_binds": True}))
