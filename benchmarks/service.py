"""Service capture throughput and API latency: the real ``cellcal serve --mock`` over HTTP.

Acceptance target (issue "The calibration service"): with instant mock motion and 1280x1024
images, at least 10 stations per second captured end to end (move, grab, detect, store), and
while a run captures, p99 latency of ``GET /runs/{id}`` under 50 ms.

(a) End to end: ``cellcal serve --mock`` in a subprocess on a free 127.0.0.1 port, over a
    temporary data directory with a generated API key. The mock robot and camera are instant
    by default (no motion time, no settling, no frame wait), so a station costs what the
    service computes: render, detect, PNG, database. After a 3-station warm-up run, one run
    with explicit poses (``mocks.scene.sample_station_poses`` on the default scene, so every
    frame shows the board) is timed from ``POST /runs`` until the run is ``done`` (the run's
    ``updated_at``), while a second thread polls ``GET /runs/{id}`` at a fixed rate.
(b) Where the time goes: the same capture loop in-process (``service.runtime.Runtime`` on a
    temporary SQLite database and the same mock devices) with timers around its stages, then under
    cProfile.
(c) What would meet the target: the loop's device and image work (move, grab, detect, PNG)
    without HTTP and database, serial as in the service, and pipelined with detection and the
    PNG on a worker thread while the next frame is grabbed.

    python -m benchmarks.service            # 80 stations, about 1 min
    python -m benchmarks.service --quick    # 20 stations
    python -m benchmarks.service --history  # latency over a plant's history (service_history)

Prints tables and writes benchmarks/results/service.png. Sends requests only to 127.0.0.1,
bounded in number and time; the server process and the temporary directory are removed on
every exit, Ctrl-C included.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as dt
import os
import secrets
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import httpx
import matplotlib
import numpy as np

from benchmarks.service_loop import (
    FINAL,
    TIME_GET_REPS,
    Stages,
    WhatIf,
    clean_env,
    stage_breakdown,
    what_if,
)
from calib import ur_pose_from_matrix
from mocks.scene import default_scene, sample_station_poses

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from benchmarks import interrupt_on_sigterm, results_dir

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
OUT = results_dir()
TARGET_RATE = 10.0  # stations per second, end to end
TARGET_P99_MS = 50.0  # GET /runs/{id} while capturing
STARTUP_TIMEOUT_S = 30.0


# ---- (a) the real service over HTTP --------------------------------------------------------

@contextlib.contextmanager
def serve(data_dir: Path, key: str) -> Iterator[str]:
    """``cellcal serve --mock`` on a free loopback port; yields the base URL, always reaped."""
    from service.serving.local import ServeOptions, local_service

    with local_service(data_dir / "data", key,
                       ServeOptions(env=clean_env(), startup_timeout=STARTUP_TIMEOUT_S)) as service:
        yield service.url


@dataclass
class Poll:
    t: float  # s since POST /runs was sent
    latency: float  # s, request sent to response parsed
    late: float  # s the request started after its slot (client-side delay)
    status: int
    state: str
    captured: int


@dataclass(frozen=True)
class PollPlan:
    """Which run to poll: its id, when POST /runs was sent (perf-counter s), at ``hz`` polls a
    second, at most ``max_polls`` times."""

    run_id: str
    t_post: float
    hz: float
    max_polls: int


def poll_run(client: httpx.Client, plan: PollPlan, stop: threading.Event,
             out: list[Poll]) -> None:
    """GET /runs/{id} every 1/hz s until the run ends, ``stop`` is set or ``max_polls``."""
    run_id, t_post = plan.run_id, plan.t_post
    period = 1.0 / plan.hz
    start = time.perf_counter()
    for k in range(plan.max_polls):
        delay = start + k * period - time.perf_counter()
        if delay > 0 and stop.wait(delay):
            return
        t0 = time.perf_counter()
        r = client.get(f"/runs/{run_id}")
        doc = r.json()
        t1 = time.perf_counter()
        out.append(Poll(t0 - t_post, t1 - t0, max(-delay, 0.0), r.status_code,
                        doc.get("state", "?"), doc.get("stations_captured", -1)))
        if r.status_code != 200 or doc.get("state") in FINAL:
            return


def wait_final(client: httpx.Client, run_id: str, timeout: float) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while True:
        doc = client.get(f"/runs/{run_id}").json()
        if doc["state"] in FINAL:
            return doc
        if time.monotonic() > deadline:
            raise RuntimeError(f"run {run_id} still {doc['state']} after {timeout:.0f} s")
        time.sleep(0.1)


def epoch(stamp: str) -> float:
    return dt.datetime.fromisoformat(stamp.replace("Z", "+00:00")).timestamp()


@dataclass
class HttpResult:
    n: int
    captured: int
    skipped: int
    state: str
    wall: float  # s, POST sent to the run's done transition (updated_at)
    post_latency: float
    polls: list[Poll]
    station_t: np.ndarray  # captured_at of each station, s since POST
    warmup_rate: float
    idle: list[Poll]  # GET /runs/{id} on the finished run, service idle


def run_http(poses: list[list[float]], warmup: list[list[float]], hz: float,
             timeout: float) -> HttpResult:
    key = secrets.token_urlsafe(24)
    with tempfile.TemporaryDirectory(prefix="cellcal-bench-") as tmp, \
            serve(Path(tmp), key) as url, \
            httpx.Client(base_url=url, headers={"Authorization": f"Bearer {key}"},
                         timeout=10.0) as client, \
            httpx.Client(base_url=url, headers={"Authorization": f"Bearer {key}"},
                         timeout=10.0) as poller:
        # Warm-up: first render (ray cache), first detection, SQLAlchemy statement caches.
        t = time.time()
        r = client.post("/runs", json={"poses": warmup})
        r.raise_for_status()
        warm = wait_final(client, r.json()["id"], timeout)
        warmup_rate = len(warmup) / (epoch(warm["updated_at"]) - t)

        polls: list[Poll] = []
        stop = threading.Event()
        t_wall, t_perf = time.time(), time.perf_counter()
        r = client.post("/runs", json={"poses": poses})
        post_latency = time.perf_counter() - t_perf
        r.raise_for_status()
        run_id = r.json()["id"]
        thread = threading.Thread(target=poll_run, name="poller", args=(
            poller, PollPlan(run_id, t_perf, hz, int(hz * timeout)), stop, polls))
        thread.start()
        try:
            thread.join(timeout + 5.0)
        finally:
            stop.set()
            thread.join()
        run = wait_final(client, run_id, 5.0)
        stations = client.get(f"/runs/{run_id}/stations").json()
        # Baseline: the same request on the finished run, nothing else running.
        idle: list[Poll] = []
        poll_idle = int(min(hz * 3.0, 60))
        for _ in range(poll_idle):
            t0 = time.perf_counter()
            poller.get(f"/runs/{run_id}").json()
            idle.append(Poll(0.0, time.perf_counter() - t0, 0.0, 200, "done", 0))
            time.sleep(1.0 / hz)
    station_t = np.array(sorted(epoch(s["captured_at"]) - t_wall for s in stations))
    return HttpResult(
        n=len(poses), captured=run["stations_captured"], skipped=run["stations_skipped"],
        state=run["state"], wall=epoch(run["updated_at"]) - t_wall, post_latency=post_latency,
        polls=polls, station_t=station_t, warmup_rate=warmup_rate, idle=idle)


# ---- report --------------------------------------------------------------------------------

def machine_busy(seconds: float = 2.0) -> float:
    """Fraction of all cores busy over ``seconds`` while this process sleeps (Linux; else
    the 1-minute load average per core)."""

    def sample() -> tuple[int, int]:
        fields = [int(v) for v in Path("/proc/stat").read_text().split("\n")[0].split()[1:]]
        return sum(fields) - fields[3] - fields[4], sum(fields)

    try:
        b0, t0 = sample()
        time.sleep(seconds)
        b1, t1 = sample()
        return (b1 - b0) / max(t1 - t0, 1)
    except (OSError, ValueError, IndexError):
        return os.getloadavg()[0] / (os.cpu_count() or 1)


def pct(values: np.ndarray, q: float) -> float:
    return float(np.percentile(values, q)) if len(values) else float("nan")


def report(http: HttpResult, stages: Stages, wi: WhatIf, hz: float) -> dict[str, float]:
    rate = http.captured / http.wall
    capturing = [p for p in http.polls if p.state == "capturing"]
    lat = np.array([p.latency for p in capturing]) * 1e3
    late = np.array([p.late for p in capturing]) * 1e3
    cycle = np.diff(http.station_t) * 1e3
    p50, p95, p99 = pct(lat, 50), pct(lat, 95), pct(lat, 99)
    ok_rate, ok_lat = rate >= TARGET_RATE, p99 < TARGET_P99_MS

    print(f"\n(a) cellcal serve --mock over HTTP, {http.n} stations (1280x1024, instant mock "
          f"motion); run {http.state}: {http.captured} captured, {http.skipped} skipped")
    print(f"    POST /runs {http.post_latency * 1e3:.1f} ms; first station stored "
          f"{http.station_t[0] * 1e3:.0f} ms after POST; warm-up run {http.warmup_rate:.2f} "
          f"stations/s")
    print(f"    station cycle (captured_at differences): median {np.median(cycle):.0f} ms, "
          f"p90 {pct(cycle, 90):.0f} ms, max {cycle.max():.0f} ms")
    print(f"    GET /runs/{{id}} while capturing: {len(lat)} requests at {hz:g} Hz, "
          f"max client-side start delay {late.max():.1f} ms")
    print()
    print("| metric | measured | target | result |")
    print("|---|---|---|---|")
    print(f"| stations/s, POST to done ({http.wall:.2f} s) | {rate:.2f} | >= {TARGET_RATE:g} "
          f"| {'PASS' if ok_rate else 'FAIL'} |")
    print(f"| GET /runs/{{id}} p50 | {p50:.1f} ms | | |")
    print(f"| GET /runs/{{id}} p95 | {p95:.1f} ms | | |")
    print(f"| GET /runs/{{id}} p99 | {p99:.1f} ms | < {TARGET_P99_MS:g} ms "
          f"| {'PASS' if ok_lat else 'FAIL'} |")
    print(f"| GET /runs/{{id}} max | {lat.max():.1f} ms | | |")
    n_st = np.array([p.captured for p in capturing], dtype=float)
    slope, icpt = np.polyfit(n_st, lat, 1) if len(set(n_st)) > 1 else (np.nan, np.nan)
    print(f"    latency grows with the stations stored: {icpt:.1f} ms + {slope:.3f} ms per "
          "station (least squares)")
    idle = np.array([p.latency for p in http.idle]) * 1e3
    print(f"    same request on the finished run, service idle ({len(idle)} requests): "
          f"p50 {pct(idle, 50):.1f} ms, p99 {pct(idle, 99):.1f} ms")

    print(f"\n(b) the service's capture loop in-process ({stages.n} stations, "
          f"{stages.n / stages.wall:.2f} stations/s without HTTP load), mean ms per station:")
    print("\n| stage | ms | share |")
    print("|---|---|---|")
    total = stages.per_station_ms["total per station"]
    for name, ms in stages.per_station_ms.items():
        share = "" if name.startswith("total") else f"{ms / total:.0%}"
        print(f"| {name} | {ms:.1f} | {share} |")
    print(f"\ncProfile of the capture thread, top functions by own time "
          f"({stages.profiled} stations):")
    print("\n| function | calls | own s | cumulative s |")
    print("|---|---|---|---|")
    for name, nc, tt, ct in stages.profile:
        print(f"| {name} | {nc} | {tt:.3f} | {ct:.3f} |")

    h = stages.handler
    print(f"\nGET /runs/{{id}} handler body in-process on the finished {stages.n}-station run "
          "(session, run + every station with its corners, serialize):")
    print(f"    median {h.median:.1f} ms, p99 {h.p99:.1f} ms; {h.full_gcs} full garbage "
          f"collections in {TIME_GET_REPS} calls, median {h.full_gc_ms:.0f} ms each; p99 "
          f"{h.frozen_p99:.1f} ms after gc.freeze()")
    print(f"    prototype, counts and errors from SQL (corners never loaded): median "
          f"{h.counted_median:.1f} ms")
    print(f"\n(c) the loop's device and image work without HTTP and database, in-process, "
          f"{wi.n} stations:")
    print("\n| loop | stations/s |")
    print("|---|---|")
    print(f"| serial: move + grab, detect, PNG encode + write (as the service) "
          f"| {wi.serial_rate:.2f} |")
    print(f"| pipelined: detect + PNG on a worker thread, 2 in flight | "
          f"{wi.pipelined_rate:.2f} |")
    return {"rate": rate, "p50": p50, "p95": p95, "p99": p99}


def plot(http: HttpResult, stages: Stages, hz: float, path: Path) -> None:
    capturing = [p for p in http.polls if p.state == "capturing"]
    t = np.array([p.t for p in capturing])
    lat = np.array([p.latency for p in capturing]) * 1e3
    fig, axes = plt.subplots(1, 3, figsize=(18, 5), width_ratios=[1.2, 1.0, 1.1],
                             layout="constrained")

    ax = axes[0]
    ax.plot(t, lat, ".", ms=3, color="tab:blue", label=f"GET /runs/{{id}} ({hz:g} Hz)")
    ax.axhline(TARGET_P99_MS, color="tab:red", ls="--", lw=1, label="p99 target 50 ms")
    ax.set_xlabel("time since POST /runs (s)")
    ax.set_ylabel("latency (ms)")
    ax.set_ylim(0, max(TARGET_P99_MS * 1.2, lat.max() * 1.1))
    ax2 = ax.twinx()
    ax2.step(http.station_t, np.arange(1, len(http.station_t) + 1), where="post",
             color="tab:green", label="stations stored")
    ax2.plot([0, http.station_t[-1]], [0, TARGET_RATE * http.station_t[-1]], color="tab:green",
             ls=":", lw=1, label="10 stations/s target")
    ax2.set_ylim(0, max(len(http.station_t), 1) * 1.1)
    ax2.set_ylabel("stations stored")
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, loc="upper left", fontsize=8)
    rate = http.captured / http.wall
    ax.set_title(f"capture {rate:.2f} stations/s, API latency over time")

    ax = axes[1]
    ax.hist(lat, bins=np.linspace(0.0, max(60.0, lat.max() * 1.05), 61), color="tab:blue")
    for q, ls in ((50, "-"), (99, "--")):
        ax.axvline(pct(lat, q), color="k", ls=ls, lw=1, label=f"p{q} {pct(lat, q):.1f} ms")
    ax.axvline(TARGET_P99_MS, color="tab:red", ls="--", lw=1, label="p99 target")
    ax.set_xlabel("GET /runs/{id} latency while capturing (ms)")
    ax.set_ylabel("requests")
    ax.legend(fontsize=8)
    ax.set_title("latency histogram")

    ax = axes[2]
    items = [(k, v) for k, v in stages.per_station_ms.items() if not k.startswith("total")]
    ax.barh([k for k, _ in items][::-1], [v for _, v in items][::-1], color="tab:orange")
    ax.axvline(1e3 / TARGET_RATE, color="tab:red", ls="--", lw=1,
               label="whole budget per station (100 ms)")
    ax.set_xlabel("ms per station (mean, in-process)")
    ax.legend(fontsize=8, loc="lower right")
    ax.set_title(f"capture loop stages: {stages.per_station_ms['total per station']:.0f} "
                 "ms per station")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="20 stations instead of 80")
    parser.add_argument("--stations", type=int, help="stations in the timed run")
    parser.add_argument("--hz", type=float, default=20.0, help="GET /runs/{id} rate")
    parser.add_argument("--timeout", type=float, default=120.0,
                        help="give up on a run after this many seconds")
    parser.add_argument("--history", action="store_true",
                        help="latency over a stored history on SQLite and PostgreSQL instead "
                             "(benchmarks/service_history.py)")
    parser.add_argument("--seconds", type=float,
                        help="--history: load time of one block (default 40, --quick 4)")
    parser.add_argument("--rounds", type=int,
                        help="--history: rounds of a block on each history size, by turns "
                             "(default 4, --quick 2)")
    parser.add_argument("--client", choices=("threads", "light", "both"), default="both",
                        help="--history: the load generator: httpx threads in this process, "
                             "a separate asyncio process, or each in turn (default)")
    parser.add_argument("--backend", choices=("sqlite", "postgresql", "both"), default="both",
                        help="--history: the database(s) measured (default both, in turn)")
    args = parser.parse_args()
    if args.history:
        from benchmarks.service_history import run_history

        return run_history(quick=args.quick, seconds=args.seconds, rounds=args.rounds,
                           clients=("threads", "light") if args.client == "both"
                           else (args.client,),
                           backends=("sqlite", "postgresql") if args.backend == "both"
                           else (args.backend,))
    n = args.stations or (20 if args.quick else 80)

    interrupt_on_sigterm()  # run every finally: reap the server, remove temp dirs
    T = sample_station_poses(default_scene(), n + 3, np.random.default_rng(2026))
    poses = ur_pose_from_matrix(T).tolist()
    busy = machine_busy()
    print(f"cellcal service benchmark: {n} stations, {os.cpu_count()} cores, "
          f"OpenCV {cv2.__version__}, {cv2.getNumThreads()} OpenCV threads; CPU used by other "
          f"processes before the start: {busy:.0%}", flush=True)
    if busy > 0.1:
        print("warning: the machine is busy; timings will be slower and noisier than on an "
              "idle machine", flush=True)
    warmup = poses[n:]
    http = run_http(poses[:n], warmup, args.hz, args.timeout)
    stages = stage_breakdown(poses[:n], warmup, args.timeout, keep=min(n, 10))
    wi = what_if(poses[:n], warmup)
    report(http, stages, wi, args.hz)
    path = OUT / "service.png"
    plot(http, stages, args.hz, path)
    print(f"CPU used by other processes after the end: {machine_busy():.0%}")
    print(f"\nwrote {path}")
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        sys.exit(130)
