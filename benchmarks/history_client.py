"""The history benchmark's load from a separate, light client process: one asyncio event loop,
HTTP/1.1 parsed by ``h11`` over keep-alive connections (``--client light`` of
``python -m benchmarks.service --history``).

Why: the default load runs 26 ``httpx`` client threads in the benchmark's own Python process.
On this 2-core machine that process takes CPU the server needs, and a thread that got its
answer waits for the client's GIL before it stops its clock, so the figures include the
client's own cost. A dashboard in a plant runs on another computer. This client does the same
requests (the same mix, pauses, listeners and run opener, ``service_history.load``) for about
half the CPU per request (0.9 against 2.0 ms, measured on this machine) and without threads
contending for one GIL, so its latencies are closer to what a dashboard on its own computer
meets; the benchmark reports both clients.

Run as ``python -m benchmarks.history_client`` with the load's JSON on stdin; writes the
latencies as JSON on stdout.
"""

from __future__ import annotations

import asyncio
import json
import random
import sys
import time
from collections.abc import Callable
from typing import Any
from urllib.parse import urlsplit

import h11

#: The client model, shared with the threaded load (``service_history``): a client's pause
#: after each GET and the run opener's period (s), and the cells of the seeded history.
THINK_S, POST_EVERY_S = 0.2, 0.5
CELLS = 20


class Connection:
    """One keep-alive HTTP/1.1 connection to the service."""

    def __init__(self, host: str, port: int, key: str) -> None:
        self.host, self.port = host, port
        self.headers = [("Host", f"{host}:{port}"), ("Authorization", f"Bearer {key}")]
        self.reader: asyncio.StreamReader | None = None
        self.writer: asyncio.StreamWriter | None = None
        self.h11 = h11.Connection(h11.CLIENT)

    async def _send(self, method: str, path: str, body: bytes) -> None:
        if self.writer is None or self.h11.our_state is h11.MUST_CLOSE:
            await self.close()
            self.reader, self.writer = await asyncio.open_connection(self.host, self.port)
            self.h11 = h11.Connection(h11.CLIENT)
        headers = [*self.headers, ("Content-Length", str(len(body)))]
        if body:
            headers.append(("Content-Type", "application/json"))
        assert self.writer is not None
        self.writer.write(self.h11.send(h11.Request(method=method, target=path,
                                                    headers=headers)))
        self.writer.write(self.h11.send(h11.Data(data=body)) if body else b"")
        self.writer.write(self.h11.send(h11.EndOfMessage()))
        await self.writer.drain()

    async def _next(self) -> Any:
        assert self.reader is not None
        while True:
            event = self.h11.next_event()
            if event is not h11.NEED_DATA:
                return event
            self.h11.receive_data(await self.reader.read(65536))

    async def request(self, method: str, path: str, body: bytes = b"") -> tuple[int, bytes]:
        """Send one request, read the whole answer; its status and body."""
        await self._send(method, path, body)
        status, chunks = 0, []
        while True:
            event = await self._next()
            if isinstance(event, h11.Response):
                status = event.status_code
            elif isinstance(event, h11.Data):
                chunks.append(event.data)
            elif isinstance(event, h11.EndOfMessage | h11.ConnectionClosed):
                break
        if self.h11.our_state is h11.DONE and self.h11.their_state is h11.DONE:
            self.h11.start_next_cycle()
        return status, b"".join(chunks)

    async def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None


class Load:
    """The shared state of one load: where to send, what was measured, the newest run."""

    def __init__(self, spec: dict[str, Any]) -> None:
        url = urlsplit(spec["url"])
        self.host, self.port, self.key = url.hostname or "127.0.0.1", url.port or 80, spec["key"]
        self.spec = spec
        self.by_kind: dict[str, list[float]] = {}
        self.errors: dict[str, int] = {}
        self.newest_run: str | None = None
        self.stop = asyncio.Event()
        self.mix = get_mix(spec["cal_ids"], spec["run_ids"], spec["deep"])

    def connection(self) -> Connection:
        return Connection(self.host, self.port, self.key)

    def add(self, kind: str, seconds: float, status: int) -> None:
        self.by_kind.setdefault(kind, []).append(seconds)
        if status >= 300:
            self.errors[kind] = self.errors.get(kind, 0) + 1

    async def pause(self, seconds: float) -> bool:
        """Wait ``seconds`` or until the load stops; True if it stopped."""
        try:
            await asyncio.wait_for(self.stop.wait(), seconds)
        except TimeoutError:
            return False
        return True


def get_mix(cal_ids: list[str], run_ids: list[str], deep: str) -> list[tuple[str, Callable[
        [random.Random], str]]]:
    """(kind, path maker): the GETs a plant dashboard and the cells' controllers send."""
    def cell(r: random.Random) -> str:
        return f"cell-{r.randrange(CELLS):02d}"

    return [
        ("GET /runs", lambda r: "/runs?limit=50"),
        ("GET /runs/{id}", lambda r: f"/runs/{r.choice(run_ids)}"),
        ("GET /calibrations", lambda r: "/calibrations?limit=50"),
        ("GET /calibrations?cursor (deep)", lambda r: f"/calibrations?limit=50&cursor={deep}"),
        ("GET /calibrations?cell&active", lambda r: f"/calibrations?cell={cell(r)}&active=true"),
        ("GET /calibrations/{id}", lambda r: f"/calibrations/{r.choice(cal_ids)}"),
        ("GET /calibrations/active", lambda r: f"/calibrations/active?cell={cell(r)}"),
    ]


async def dashboard(ld: Load, seed: int) -> None:
    """A GET from the mix, then a pause of about ``THINK_S``."""
    rng, conn = random.Random(seed), ld.connection()
    while not await ld.pause(THINK_S * rng.uniform(0.5, 1.5)):
        kind, path_of = rng.choice(ld.mix)
        path = path_of(rng)
        t0 = time.perf_counter()
        status, _ = await conn.request("GET", path)
        ld.add(kind, time.perf_counter() - t0, status)
    await conn.close()


async def run_opener(ld: Load) -> None:
    """Opens an external run and finishes it, every ``POST_EVERY_S``."""
    conn = ld.connection()
    while not await ld.pause(POST_EVERY_S):
        t0 = time.perf_counter()
        status, body = await conn.request("POST", "/runs", b'{"mode": "external"}')
        ld.add("POST /runs", time.perf_counter() - t0, status)
        if status == 201:
            ld.newest_run = json.loads(body)["id"]
            await conn.request("POST", f"/runs/{ld.newest_run}/finish")
    await conn.close()


async def listener(ld: Load) -> None:
    """Follows the newest run's event stream to its end, then the next newer run's."""
    followed = None
    while not ld.stop.is_set():
        if ld.newest_run is None or ld.newest_run == followed:
            await ld.pause(0.05)
            continue
        followed, conn = ld.newest_run, ld.connection()
        try:
            await conn.request("GET", f"/runs/{followed}/events")
        finally:
            await conn.close()


async def run(spec: dict[str, Any]) -> dict[str, Any]:
    """The load for ``spec["seconds"]``; the latencies by kind, the non-2xx answers and the
    CPU seconds this process used meanwhile."""
    ld = Load(spec)
    cpu0 = time.process_time()
    tasks = [asyncio.create_task(dashboard(ld, k)) for k in range(spec["clients"])]
    tasks += [asyncio.create_task(listener(ld)) for _ in range(spec["listeners"])]
    tasks.append(asyncio.create_task(run_opener(ld)))
    await asyncio.sleep(spec["seconds"])
    ld.stop.set()
    _, pending = await asyncio.wait(tasks, timeout=60.0)
    for task in pending:  # a listener still inside a stream
        task.cancel()
    await asyncio.gather(*pending, return_exceptions=True)
    return {"by_kind": ld.by_kind, "errors": ld.errors, "cpu_s": time.process_time() - cpu0}


def main() -> int:
    spec = json.load(sys.stdin)
    json.dump(asyncio.run(run(spec)), sys.stdout)
    return 0


if __name__ == "__main__":
    sys.exit(main())
