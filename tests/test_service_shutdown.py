"""SIGTERM to ``cellcal serve`` stops the robot first (issue 22, row 1): the run being
captured stops after the station in flight and becomes ``interrupted`` (so ``resume``
continues it), every event listener gets its final event, and the process exits although
listeners were connected; a second signal exits at once. Real ``cellcal serve --mock``
subprocesses; every wait is for a condition, bounded only against a hang."""

from __future__ import annotations

import signal
import socket
import sqlite3
import threading
from pathlib import Path
from typing import Any

import httpx
import pytest

from service.cli.client import Event, parse_events
from service.serving.local import LocalService, ServeOptions, local_service

KEY = "shutdown-key-0123456789abcdef"
AUTH = {"Authorization": f"Bearer {KEY}"}
#: Bound against a hang only (the machine may be loaded); no assertion depends on it.
HANG_S = 120.0

pytestmark = pytest.mark.timeout(600)


class Listener(threading.Thread):
    """Reads an event stream in the background; ``events`` grows as they arrive."""

    def __init__(self, url: str, *, after: int | None = None) -> None:
        super().__init__(daemon=True)
        self.url = url
        self.headers = AUTH | ({} if after is None else {"Last-Event-ID": str(after)})
        self.events: list[Event] = []
        self.changed = threading.Condition()
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            with httpx.stream("GET", self.url, headers=self.headers,
                              timeout=httpx.Timeout(30, read=None)) as r:
                for event in parse_events(r.iter_lines()):
                    with self.changed:
                        self.events.append(event)
                        self.changed.notify_all()
        except BaseException as exc:
            self.error = exc
        with self.changed:
            self.changed.notify_all()

    def stations(self) -> int:
        """Station events received so far."""
        with self.changed:
            return self._stations()

    def _stations(self) -> int:
        return sum(e.type == "station" for e in self.events)

    def wait_for(self, stations: int) -> None:
        """Until ``stations`` station events have come (or the stream has ended)."""
        with self.changed:
            assert self.changed.wait_for(
                lambda: self._stations() >= stations or not self.is_alive(), HANG_S)
        assert self.stations() >= stations, self.events


def _stations_in(run: dict[str, Any]) -> int:
    """The stations a run's state (its ``state`` event or its REST view) counts as seen."""
    return run["stations_captured"] + run["stations_skipped"]


def _post(service: LocalService, path: str, body: Any = None) -> httpx.Response:
    return httpx.post(service.url + path, json=body, headers=AUTH, timeout=60)


def _stalled_upload(service: LocalService) -> socket.socket:
    """A connection whose request is never complete (a body announced, not sent): uvicorn's
    own shutdown would wait for it for good."""
    host, port = httpx.URL(service.url).host, httpx.URL(service.url).port
    sock = socket.create_connection((host, port), timeout=30)
    sock.sendall(b"POST /runs HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer " + KEY.encode()
                 + b"\r\nContent-Type: application/json\r\nContent-Length: 100000\r\n\r\n{")
    return sock


@pytest.fixture
def service_dir(tmp_path: Path) -> Path:
    return tmp_path / "data"


def test_sigterm_stops_the_run_ends_every_stream_and_exits(service_dir: Path) -> None:
    # a grace period no loaded machine runs out of: the process ends as soon as all has ended
    options = ServeOptions(args=("--graceful-timeout", "90"))
    with local_service(service_dir, KEY, options) as service:
        run_id = _post(service, "/runs", {"stations": 200}).json()["id"]
        follower = Listener(f"{service.url}/runs/{run_id}/events")
        follower.start()
        follower.wait_for(3)  # the robot is capturing
        seen = follower.stations()
        service.proc.send_signal(signal.SIGTERM)
        follower.join(HANG_S)
        code = service.proc.wait(HANG_S)
        log = service.log.read_text()
    assert follower.error is None and not follower.is_alive()
    last = follower.events[-1]
    # the listener's last event is the run's final state: interrupted, with every station
    # it was told of stored, and no more than the one in flight (plus one stored before the
    # signal whose event was still on its way) after the signal
    assert (last.type, last.data["state"]) == ("state", "interrupted"), follower.events[-3:]
    after_signal = follower.stations() - seen
    assert after_signal <= 2, after_signal
    # a new stream opens with the run's state (its counts so far), then the stations live:
    # under load the first station can be stored before the listener subscribes
    first = follower.events[0]
    assert first.type == "state", follower.events[:2]
    told = _stations_in(first.data) + follower.stations()  # every station the stream told of
    assert _stations_in(last.data) == told
    assert code == -signal.SIGTERM, log
    # the order: the robot stopped before uvicorn began closing connections
    assert log.index("stopping the robot") < log.index("Shutting down"), log
    assert '" 500' not in log, log

    # a restarted service has the run interrupted with exactly those stations; resume goes on
    with local_service(service_dir, KEY, ServeOptions(log=service_dir.parent / "again.log")) \
            as again:
        run = httpx.get(f"{again.url}/runs/{run_id}", headers=AUTH, timeout=60).json()
        assert run["state"] == "interrupted"
        assert _stations_in(run) == told
        assert _post(again, f"/runs/{run_id}/resume").status_code == 200
        assert _post(again, f"/runs/{run_id}/cancel").status_code == 200


def test_sigterm_ends_streams_of_jobs_that_are_not_ending(service_dir: Path) -> None:
    """A paused run's stream (its state is not final) ends with the ``shutdown`` event, which
    has no id, so a client resuming with Last-Event-ID keeps its place; an upload that never
    ends is dropped at the end of the grace period, not answered 500."""
    with local_service(service_dir, KEY, ServeOptions(args=("--graceful-timeout", "3"))) \
            as service:
        run_id = _post(service, "/runs", {"stations": 200}).json()["id"]
        assert _post(service, f"/runs/{run_id}/pause").status_code == 200
        listener = Listener(f"{service.url}/runs/{run_id}/events")
        listener.start()
        with listener.changed:
            assert listener.changed.wait_for(lambda: listener.events, HANG_S)
        stalled = _stalled_upload(service)
        service.proc.send_signal(signal.SIGTERM)
        listener.join(HANG_S)
        assert service.proc.wait(HANG_S) == -signal.SIGTERM
        stalled.close()
        log = service.log.read_text()
    assert log.index("Shutting down") < log.index("dropping 1 connection"), log
    assert '" 500' not in log, log
    assert listener.error is None
    first, last = listener.events[0], listener.events[-1]
    assert (first.type, first.data["state"]) == ("state", "paused")
    assert last.type == "shutdown" and last.id is None and "shutting down" in last.data["detail"]


@pytest.mark.slow
def test_sigterm_with_the_database_locked_ends_the_streams_and_the_process(
        service_dir: Path) -> None:
    """SIGTERM while another process holds the SQLite write lock (issue 22, a variant of rows
    1 and 4): each step of the shutdown waited for the database's 30 s busy timeout, the
    process took 50 s with a 10 s grace period and the listener's stream was dropped without
    a final event. Now the stream ends with one, and the end of the grace period ends the
    process (a 30 s lock outlasts it)."""
    with local_service(service_dir, KEY, ServeOptions(args=("--graceful-timeout", "10"))) \
            as service:
        run_id = _post(service, "/runs", {"stations": 200}).json()["id"]
        follower = Listener(f"{service.url}/runs/{run_id}/events")
        follower.start()
        follower.wait_for(2)
        lock = sqlite3.connect(service_dir / "cellcal.db", isolation_level=None, timeout=HANG_S)
        try:
            lock.execute("BEGIN EXCLUSIVE")
            service.proc.send_signal(signal.SIGTERM)
            follower.join(HANG_S)
            code = service.proc.wait(HANG_S)
        finally:
            lock.close()  # rolls back
        log = service.log.read_text()
    assert follower.error is None and not follower.is_alive()
    assert follower.events[-1].type in ("state", "shutdown"), follower.events[-3:]
    assert code == -signal.SIGTERM
    assert "grace period over before the shutdown ended: exiting now" in log, log


def test_a_second_signal_exits_at_once(service_dir: Path) -> None:
    """The grace period is long and a connection keeps uvicorn waiting: the second SIGTERM
    ends the process without waiting for it."""
    with local_service(service_dir, KEY, ServeOptions(args=("--graceful-timeout", "600"))) \
            as service:
        stalled = _stalled_upload(service)
        assert httpx.get(f"{service.url}/health", timeout=60).status_code == 200
        service.proc.send_signal(signal.SIGTERM)
        _wait_for_log(service, "Waiting for connections to close")
        service.proc.send_signal(signal.SIGTERM)
        code = service.proc.wait(HANG_S)  # far below the 600 s grace period
        stalled.close()
        log = service.log.read_text()
    assert code == -signal.SIGTERM
    assert "second signal SIGTERM: exiting at once" in log


def _wait_for_log(service: LocalService, text: str) -> None:
    """Until the service's log has ``text`` (or the process has ended)."""
    done = threading.Event()
    while not done.wait(0.1):
        if text in service.log.read_text() or service.proc.poll() is not None:
            done.set()
    assert text in service.log.read_text()


def test_graceful_timeout_must_be_seconds(capsys) -> None:
    from service.cli import main as cli

    with pytest.raises(SystemExit):
        cli.main(["serve", "--mock", "--graceful-timeout", "soon"])
    assert "'soon' is not a number of seconds" in capsys.readouterr().err
