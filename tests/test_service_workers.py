"""Calibration workers of a real ``cellcal serve`` (issue 11).

* After ``kill -9`` of the service during a calibration, its worker and the multiprocessing
  resource tracker used to keep running (23 of 23 trials): here the server is killed and its
  former children are watched until they are gone.
* Calibrations queued without limit (71 in a fuzz run): here the worker is frozen (SIGSTOP) so
  the queue fills deterministically, and the next request gets 429.
"""

from __future__ import annotations

import os
import signal
from pathlib import Path

import httpx
import numpy as np

from calib.geometry import ur_pose_from_matrix
from mocks.scene import default_scene, sample_station_poses
from service.jobs.workers import WorkerPool
from service.serving.local import LocalService, ServeOptions, local_service
from tests.support.helpers import wait_for
from tests.support.service import finished, wait_run

KEY = "orphan-key-0123456789abcdef"
#: Issue 11 acceptance: no orphan 15 s after the kill.
ORPHAN_DEADLINE_S = 15.0


Process = tuple[int, int]  # pid and start time (clock ticks): a pid may be reused


def _processes() -> dict[Process, int]:
    """Every live process (zombies are dead already) with its parent pid, from /proc."""
    parents = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:  # gone meanwhile
            continue
        if fields[0] != "Z":  # fields: state, ppid, ..., starttime is the 20th
            parents[(int(entry.name), int(fields[19]))] = int(fields[1])
    return parents


def descendants(pid: int) -> set[Process]:
    """Every live process below ``pid`` (children, grandchildren, ...)."""
    parents = _processes()
    found: set[Process] = set()
    frontier = {pid}
    while frontier:
        level = {p for p, parent in parents.items() if parent in frontier} - found
        found |= level
        frontier = {p[0] for p in level}
    return found


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


def _captured_run(client: httpx.Client) -> str:
    """A finished capture run of 5 stations of the mock cell; its id."""
    poses = ur_pose_from_matrix(
        sample_station_poses(default_scene(), 5, np.random.default_rng(4))).tolist()
    run = client.post("/runs", json={"poses": poses}).json()
    assert wait_run(client, run["id"], finished, 120)["state"] == "done"
    return run["id"]


def _workers(server: int) -> set[Process]:
    """The server's calibration worker processes (multiprocessing spawn children)."""
    return {p for p in descendants(server) if "spawn_main" in _cmdline(p[0])}


def _client(service: LocalService) -> httpx.Client:
    return httpx.Client(base_url=service.url, headers={"Authorization": f"Bearer {KEY}"},
                        timeout=30)


def test_kill_9_during_a_calibration_leaves_no_process(tmp_path):
    with local_service(tmp_path / "data", KEY) as service, _client(service) as client:
        run_id = _captured_run(client)
        cal = client.post(f"/runs/{run_id}/calibrations", json={})
        assert cal.status_code == 202, cal.text
        server = service.proc.pid
        workers = wait_for("a calibration worker", lambda: _workers(server), 60)
        before = descendants(server)
        assert workers <= before
        os.kill(server, signal.SIGKILL)
        service.proc.wait(10)
        wait_for("the server's former children to end",  # the last: what still runs
                 lambda: {pid: _cmdline(pid) for pid, _ in before & set(_processes())},
                 ORPHAN_DEADLINE_S, until=lambda alive: not alive)


def test_calibration_queue_is_bounded(tmp_path):
    limit = 2
    env = {**os.environ, "CELLCAL_MAX_QUEUED_CALIBRATIONS": str(limit)}
    with (local_service(tmp_path / "data", KEY, ServeOptions(env=env)) as service,
          _client(service) as client):
        run_id = _captured_run(client)
        path = f"/runs/{run_id}/calibrations"
        assert client.post(path, json={}).status_code == 202
        (worker,) = wait_for("the calibration worker", lambda: _workers(service.proc.pid), 60)
        os.kill(worker[0], signal.SIGSTOP)  # nothing finishes from now on
        try:
            answers = [client.post(path, json={}) for _ in range(limit + 1)]
            running = [c for c in client.get(path).json() if c["state"] == "running"]
        finally:
            os.kill(worker[0], signal.SIGCONT)
        codes = [a.status_code for a in answers]
        assert codes.count(202) <= limit and codes[-1] == 429, codes
        assert len(running) == limit
        assert answers[-1].json() == {
            "detail": f"{limit} calibrations are already queued or running, the limit "
                      "(CELLCAL_MAX_QUEUED_CALIBRATIONS); retry when one has finished.",
            "code": "queue_full"}
        wait_for("the queued calibrations", lambda: all(
            c["state"] != "running" for c in client.get(path).json()), 120)
        assert client.post(path, json={}).status_code == 202  # room again


def test_a_pool_whose_idle_worker_died_starts_new_workers():
    """A worker killed while idle (the out-of-memory killer, an operator's ``kill``) broke its
    ``ProcessPoolExecutor`` for good: every later calibration, report and posted image was
    answered 500, and each calibration asked for stayed ``running`` (issue 22, a variant of
    row 4). The pool starts new workers at the next task instead."""
    pool = WorkerPool(1, lambda message: None)
    try:
        first = pool.submit(os.getpid).result(timeout=60)
        os.kill(first, signal.SIGKILL)
        # the executor has seen the death once it has reaped the worker
        wait_for("the dead worker reaped", lambda: not Path(f"/proc/{first}").exists(), 60)
        second = pool.submit(os.getpid).result(timeout=60)
    finally:
        pool.shutdown()
    assert second != first
