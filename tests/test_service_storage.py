"""Storage faults are loud (issue 22, rows 5 and 8; ``service.store.storage``).

A deleted data directory went unnoticed, a full disk showed ``capturing`` for 145 s and then
``internal_error``, cancel answered 503, and a read-only directory made the station-set
download a 500. Here each fault is made for real where a test can (the directory is deleted)
and through the storage check's seams where it cannot (no tmpfs in a test: the free space and
the writers' ``OSError`` are provoked); ``tools/storage-faults`` does the real tmpfs and
read-only mount as root.
"""

from __future__ import annotations

import errno
import shutil
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.jobs.calibrations import Calibrations
from service.jobs.validations import Validations
from service.runs import capture
from service.store import storage
from tests.support.service import (
    AUTH,
    external_run,
    finished,
    poses,
    post,
    robot_pose,
    settings,
    start_run,
    wait_calibration,
    wait_doc,
    wait_run,
)


@contextmanager
def service(tmp_path: Path) -> Iterator[TestClient]:
    """A service whose data directory is ``tmp_path / "data"`` and whose database is beside
    it (so the run's fate stays readable when the directory goes)."""
    app = create_app(settings(tmp_path / "data",
                              database_url=f"sqlite:///{tmp_path / 'cellcal.db'}"))
    with TestClient(app, raise_server_exceptions=False) as client:
        client.headers.update(AUTH)
        yield client


def refused(r: Any, code: str) -> None:
    assert r.status_code == 503, r.text
    assert r.json()["code"] == code


def degraded(client: TestClient, code: str) -> None:
    health = client.get("/health")
    assert health.status_code == 200
    assert health.json()["status"] == "degraded"
    assert health.json()["problem"]["code"] == code


@pytest.mark.timeout(120)
def test_a_deleted_data_directory_fails_the_run_and_new_ones(tmp_path: Path) -> None:
    with service(tmp_path) as client:
        assert client.get("/health").json()["status"] == "ok"
        run_id = start_run(client, 40)
        wait_run(client, run_id, lambda r: r["stations_captured"] >= 2)
        # Gone from its path at once: a plain rmtree races the capture, which may write a new
        # file between rmtree's listing and its rmdir (ENOTEMPTY in the test, not the service).
        (tmp_path / "data").rename(tmp_path / "deleted")
        shutil.rmtree(tmp_path / "deleted", ignore_errors=True)
        run = wait_run(client, run_id, finished)
        assert run["state"] == "failed" and run["error"]["code"] == "storage_unavailable"
        assert "deleted or replaced" in run["error"]["detail"]
        assert run["stations_captured"] + run["stations_skipped"] < 40
        degraded(client, "storage_unavailable")
        refused(client.post("/runs", json={"poses": poses(3)}), "storage_unavailable")
        # every other new job too (issue 22, a variant of row 5: each was accepted, done and
        # stored in the database file that had lost its name), checked before its ids are
        for path in (f"/runs/{run_id}/calibrations", "/calibrations/x/activate",
                     "/calibrations/x/checks", "/calibrations/x/validations"):
            refused(client.post(path), "storage_unavailable")
        (tmp_path / "data").mkdir()  # another directory in its place: still not the data
        degraded(client, "storage_unavailable")


@pytest.mark.timeout(120)
def test_a_full_disk_fails_the_run_refuses_new_ones_and_cancel_works(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    with service(tmp_path) as client:
        run_id = external_run(client)
        pose = robot_pose(client)
        assert post(client, run_id, pose=pose).status_code == 201
        monkeypatch.setattr(storage, "_free_bytes", lambda path: 5 * 2**20)  # 5 MB left
        refused(post(client, run_id, pose=pose), "disk_full")
        degraded(client, "disk_full")
        assert not (tmp_path / "data" / ".space-reserve").exists()  # given back for the end
        r = client.post(f"/runs/{run_id}/cancel")
        assert r.status_code == 200 and r.json()["state"] == "cancelled"
        refused(client.post("/runs", json={"poses": poses(3)}), "disk_full")
        monkeypatch.undo()
        assert client.get("/health").json()["status"] == "ok"
        assert (tmp_path / "data" / ".space-reserve").exists()

        # the disk fills between the check and the write: the writer's ENOSPC fails the run
        def no_space(path: Path, image: Any) -> None:
            raise OSError(errno.ENOSPC, "No space left on device", str(path))

        monkeypatch.setattr(capture, "write_png", no_space)
        run_id = start_run(client, 10)
        run = wait_run(client, run_id, finished)
        assert run["state"] == "failed" and run["error"]["code"] == "disk_full"
        assert run["stations_captured"] == 0  # nothing stored without its image


@pytest.mark.timeout(120)
def test_a_read_only_data_directory_is_503_not_500(tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    with service(tmp_path) as client:
        run_id = start_run(client, 4)
        assert wait_run(client, run_id, finished)["state"] == "done"

        def read_only(*args: Any, **kwargs: Any) -> Any:
            raise OSError(errno.EROFS, "Read-only file system")

        monkeypatch.setattr(storage.tempfile, "TemporaryFile", read_only)
        monkeypatch.setattr("service.api.runs.tempfile.mkdtemp", read_only)
        degraded(client, "storage_unavailable")
        refused(client.get(f"/runs/{run_id}/stationset"), "storage_unavailable")
        refused(client.post("/runs", json={"poses": poses(3)}), "storage_unavailable")
        assert client.get(f"/runs/{run_id}").json()["state"] == "done"  # reads still answer


@pytest.mark.timeout(300)
def test_a_job_that_ends_without_its_data_directory_is_not_done(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A calibration solving, or a re-check moving, when the data directory goes ended
    ``done`` (issue 22, a variant of row 5): it is moved away at the last moment before each
    job's outcome is stored (nothing raced), and moved back between the two."""
    data, away = tmp_path / "data", tmp_path / "away"
    with service(tmp_path) as client:
        run_id = start_run(client, 8)
        assert wait_run(client, run_id, finished)["state"] == "done"
        cal_id = client.post(f"/runs/{run_id}/calibrations").json()["id"]
        assert wait_calibration(client, cal_id)["state"] == "done"

        check = Validations._check

        def check_then_move(self: Validations, *args: Any) -> Any:
            result = check(self, *args)
            data.rename(away)
            return result

        monkeypatch.setattr(Validations, "_check", check_then_move)
        r = client.post(f"/calibrations/{cal_id}/checks", json={"stations": 3})
        assert r.status_code == 202, r.text
        val = wait_doc(client, f"/validations/{r.json()['id']}")
        assert val["state"] == "failed" and val["result"] is None
        assert val["error_code"] == "storage_unavailable", val
        assert "deleted or replaced" in val["error"]
        away.rename(data)
        monkeypatch.undo()
        assert client.get("/health").json()["status"] == "ok"

        done = Calibrations._done

        def move_then_done(self: Calibrations, *args: Any) -> None:
            data.rename(away)
            done(self, *args)

        monkeypatch.setattr(Calibrations, "_done", move_then_done)
        cal_id = client.post(f"/runs/{run_id}/calibrations").json()["id"]
        cal = wait_calibration(client, cal_id)
        assert cal["state"] == "failed" and cal["result"] is None
        assert cal["error_code"] == "storage_unavailable", cal
        assert "deleted or replaced" in cal["error"]
        listed = client.get("/calibrations", params={"run_id": run_id}).json()["items"]
        assert [c["error_code"] for c in listed if c["id"] == cal_id] == ["storage_unavailable"]


@pytest.mark.timeout(60)
def test_a_hanging_data_directory_holds_the_new_job_not_the_service(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A new job's storage check (a file made in the data directory, its free space) ran on
    the event loop: a directory that hangs (a network mount, a failing disk) held every
    request there, ``/health`` too, which should answer ``degraded`` just then. Now only the
    job's own request waits."""
    entered, release = threading.Event(), threading.Event()

    def hanging(self: storage.Storage) -> None:
        entered.set()
        release.wait(30)

    with service(tmp_path) as client:
        monkeypatch.setattr(storage.Storage, "check", hanging)
        job = threading.Thread(target=client.post, args=("/calibrations/x/activate",))
        job.start()
        answers: list[int] = []
        try:
            assert entered.wait(10)
            health = threading.Thread(
                target=lambda: answers.append(client.get("/health").status_code))
            health.start()
            health.join(10)
        finally:
            release.set()
            job.join(30)
        assert answers == [200], "/health waited for the hanging storage check"


@pytest.mark.parametrize("scheme", ["sqlite", "sqlite+pysqlite"])
def test_the_database_file_is_watched_in_any_sqlite_spelling(tmp_path: Path,
                                                             scheme: str) -> None:
    """``sqlite+pysqlite:///`` names the same database to SQLAlchemy (and the service opens
    it), but the storage check read only ``sqlite:///``: a database file deleted under such a
    URL went unnoticed, and jobs ended ``done`` in it."""
    data, db = tmp_path / "data", tmp_path / "cellcal.db"
    data.mkdir()
    db.touch()
    watch = storage.Storage(settings(data, database_url=f"{scheme}:///{db}"))
    assert watch.gone() is None
    db.unlink()
    assert "The database file" in str(watch.gone())
    assert storage.sqlite_file("postgresql://cellcal@db.plant/cellcal") is None
