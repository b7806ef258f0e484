"""The service's capture loop in-process: where a station's time goes, and what would meet
the target (sections (b) and (c) of ``benchmarks.service``, which runs them).

(b) ``service.runtime.Runtime`` on a temporary SQLite database with the mock devices, timers
    around the capture loop's stages, then cProfile of the capture thread and the time of the
    ``GET /runs/{id}`` handler body.
(c) The loop's device and image work without HTTP and database, serial and pipelined.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import cProfile
import gc
import os
import pstats
import secrets
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from unittest import mock

import cv2
import numpy as np

from calib import Checkerboard, detect_checkerboard
from mocks.scene import default_scene

#: Run states after which a run changes no more.
FINAL = ("done", "failed", "cancelled", "interrupted")
TIME_GET_REPS = 240  # in-process calls of the GET /runs/{id} handler body


def clean_env(**extra: str) -> dict[str, str]:
    """This environment without any ``CELLCAL_*`` setting of the caller, plus ``extra``."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("CELLCAL_")}
    return {**env, **extra}

# ---- (b) the capture loop in-process -------------------------------------------------------

@contextlib.contextmanager
def in_process_jobs(tmp: Path) -> Iterator[Any]:
    """The service's ``Runtime`` as the app builds it (mock devices, SQLite in ``tmp``),
    closed after."""
    from service.runtime import Runtime
    from service.settings import Settings

    with mock.patch.dict(os.environ, clean_env(), clear=True):
        settings = Settings(data_dir=tmp, robot="mock://", camera="mock://", scene=None,
                            database_url=None, api_key=secrets.token_urlsafe(24))
    rt = Runtime.open(settings)
    try:
        yield rt
    finally:
        rt.close()


def capture_in_process(jobs: Any, poses: list[list[float]],
                       timeout: float) -> tuple[str, float]:
    """Create a run through the run manager and wait for it; returns its id and the wall
    time (s)."""
    from service.schemas import RunCreate
    from service.store.records import RunRecord

    t0 = time.perf_counter()
    run_id = jobs.runs.create(RunCreate(poses=poses)).id
    deadline = time.monotonic() + timeout
    while True:
        with jobs.db.session() as s:
            state = s.get(RunRecord, run_id).state
        if state in FINAL:
            break
        if time.monotonic() > deadline:
            raise RuntimeError(f"in-process run still {state} after {timeout:.0f} s")
        time.sleep(0.02)
    wall = time.perf_counter() - t0
    with jobs.db.session() as s:
        run = s.get(RunRecord, run_id)
        if run.state != "done" or any(st.state != "captured" for st in run.stations):
            raise RuntimeError(f"in-process run ended {run.state} or skipped stations")
    return run_id, wall


@dataclass
class HandlerTiming:
    """The ``GET /runs/{id}`` handler body, in-process, on a finished run (ms)."""

    median: float
    p99: float
    full_gcs: int  # generation-2 collections during the calls
    full_gc_ms: float  # their median duration
    frozen_p99: float  # p99 after gc.freeze() (startup objects out of the collector's scans)
    counted_median: float  # prototype: counts and errors from SQL, corners never loaded


def time_get_run(jobs: Any, run_id: str, reps: int = TIME_GET_REPS) -> HandlerTiming:
    """Time the handler body (new session, load the run and its stations, serialize) ``reps``
    times, with the full garbage collections that happen meanwhile; then again after
    ``gc.freeze()``; and a prototype that counts stations in SQL instead of loading them."""
    from sqlalchemy import func, select

    from service.api.runs import run_public
    from service.store.records import RunRecord, StationRecord

    def handler() -> None:
        with jobs.db.session() as s:
            run_public(s, run_id).model_dump_json()

    def counted() -> None:
        with jobs.db.session() as s:
            run = s.get(RunRecord, run_id)
            dict(s.execute(select(StationRecord.state, func.count()).where(
                StationRecord.run_id == run_id).group_by(StationRecord.state)).all())
            s.scalars(select(StationRecord.index).where(StationRecord.run_id == run_id,
                                                        StationRecord.error.is_not(None))).all()
            del run

    full_gcs: list[float] = []
    started: list[float] = []

    def on_gc(phase: str, info: dict[str, int]) -> None:
        if info["generation"] == 2:
            if phase == "start":
                started.append(time.perf_counter())
            elif started:
                full_gcs.append(time.perf_counter() - started.pop())

    def timings(fn: Callable[[], None]) -> np.ndarray:
        fn()
        t = []
        for _ in range(reps):
            t0 = time.perf_counter()
            fn()
            t.append(time.perf_counter() - t0)
        return np.array(t) * 1e3

    gc.callbacks.append(on_gc)
    try:
        plain = timings(handler)
    finally:
        gc.callbacks.remove(on_gc)
    gc.collect()
    gc.freeze()
    try:
        frozen = timings(handler)
    finally:
        gc.unfreeze()
    return HandlerTiming(
        median=float(np.median(plain)), p99=float(np.percentile(plain, 99)),
        full_gcs=len(full_gcs),
        full_gc_ms=float(np.median(full_gcs)) * 1e3 if full_gcs else 0.0,
        frozen_p99=float(np.percentile(frozen, 99)),
        counted_median=float(np.median(timings(counted))))


@dataclass
class Stages:
    per_station_ms: dict[str, float]  # median ms per station and stage
    wall: float
    n: int
    profile: list[tuple[str, int, float, float]]  # name, calls, tottime, cumtime (s)
    profiled: int  # stations in the profiled run
    handler: HandlerTiming


def stage_breakdown(poses: list[list[float]], warmup: list[list[float]], timeout: float,
                    keep: int) -> Stages:
    """Time the stages of the service's own capture loop, then profile it (the default scene's
    board is a ``Checkerboard``: its ``detect`` is what the capture worker calls)."""
    import mocks.camera as camera_mod
    import service.runs.capture as capture_mod
    from service.runs.capture import Capture

    times: dict[str, list[float]] = defaultdict(list)
    samples: list[np.ndarray] = []  # rendered frames, to time the PNG encoding alone

    def timed(name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            t = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                times[name].append(time.perf_counter() - t)
        return wrapper

    def render(params: Any, T: np.ndarray, **kwargs: Any) -> np.ndarray:
        image = render_board(params, T, **kwargs)
        if len(samples) < keep:
            samples.append(image)
        return image

    render_board = camera_mod.render_board
    with tempfile.TemporaryDirectory(prefix="cellcal-bench-") as tmp:
        with in_process_jobs(Path(tmp) / "timed") as jobs:
            capture_in_process(jobs, warmup, timeout)  # warm-up
            times.clear()
            with mock.patch.object(Capture, "_store", timed("store", Capture._store)), \
                    mock.patch.object(Capture, "_owns", timed("owns", Capture._owns)), \
                    mock.patch.object(capture_mod, "capture_station",
                                      timed("capture", capture_mod.capture_station)), \
                    mock.patch.object(camera_mod, "render_board", timed("render", render)), \
                    mock.patch.object(Checkerboard, "detect",
                                      timed("detect", Checkerboard.detect)), \
                    mock.patch.object(capture_mod, "write_png",
                                      timed("png", capture_mod.write_png)):
                run_id, wall = capture_in_process(jobs, poses, timeout)
            handler = time_get_run(jobs, run_id)

        n = len(poses)
        # Means, so that the stages add up to the wall time per station.
        med = {k: float(np.mean(v)) * 1e3 for k, v in times.items()}
        t = time.perf_counter()
        for img in samples:
            cv2.imencode(".png", img)
        encode = (time.perf_counter() - t) / max(len(samples), 1) * 1e3
        total = wall / n * 1e3
        stages = {
            "move + settle + pose reads": med["capture"] - med["render"],
            "grab (mock render)": med["render"],
            "detect corners": med["detect"],
            "PNG encode": min(encode, med["png"]),
            "PNG write (tmp + rename)": max(med["png"] - encode, 0.0),
            "DB: ownership check + insert + commit": med["store"] - med["png"],
        }
        stages["rest: reload run + indices each loop, waits"] = max(
            total - sum(stages.values()), 0.0)
        stages["total per station"] = total

        # cProfile of the capture thread (the profiler is per thread: enable it inside).
        prof = cProfile.Profile()
        with in_process_jobs(Path(tmp) / "profiled") as jobs:
            capture_in_process(jobs, warmup, timeout)
            plain = Capture.run

            def profiled(capture: Capture) -> None:
                prof.enable()
                try:
                    plain(capture)
                finally:
                    prof.disable()

            profiled_n = min(n, max(n // 2, 10))
            with mock.patch.object(Capture, "run", profiled):
                capture_in_process(jobs, poses[:profiled_n], timeout)
    rows = []
    for (path, _line, func), (_cc, nc, tt, ct, _callers) in pstats.Stats(prof).stats.items():
        name = func if path == "~" else f"{Path(path).name}:{func}"
        rows.append((name, nc, tt, ct))
    rows.sort(key=lambda r: -r[2])
    return Stages(stages, wall, n, rows[:12], profiled_n, handler)


# ---- (c) what would meet the target --------------------------------------------------------

@dataclass
class WhatIf:
    serial_rate: float  # stations/s: move + grab, detect, PNG encode + write, one thread
    pipelined_rate: float  # the same with detect + PNG on a worker thread
    n: int


def what_if(poses: list[list[float]], warmup: list[list[float]]) -> WhatIf:
    """The capture loop's device and image work without HTTP or database, serial and pipelined.

    Pipelined: this thread moves and grabs; one worker thread detects and writes the PNG of
    the previous station meanwhile (at most two stations in flight), as a capture thread with
    a detection/storage worker would.
    """
    from mocks.camera import MockCamera
    from mocks.devices import MockRobot
    from service.runs.capture import write_png

    scene = default_scene()
    inner = tuple(scene.target.inner_corners)
    robot = MockRobot(scene)
    robot.connect()
    camera = MockCamera(scene, robot)
    camera.open()

    def grab(pose: list[float]) -> np.ndarray:
        robot.move_linear(np.asarray(pose))
        robot.wait_settled()
        return camera.grab()

    def work(image: np.ndarray, path: Path) -> bool:
        ok = detect_checkerboard(image, inner).ok
        write_png(path, image)
        return ok

    rates = []
    try:
        with tempfile.TemporaryDirectory(prefix="cellcal-bench-") as tmp:
            for pose in warmup:
                work(grab(pose), Path(tmp) / "warm.png")
            t = time.perf_counter()
            found = [work(grab(pose), Path(tmp) / f"s{k:03d}.png")
                     for k, pose in enumerate(poses)]
            rates.append(len(poses) / (time.perf_counter() - t))
            t = time.perf_counter()
            with cf.ThreadPoolExecutor(1) as pool:
                futures: list[cf.Future[bool]] = []
                for k, pose in enumerate(poses):
                    image = grab(pose)
                    while sum(not f.done() for f in futures) >= 2:
                        cf.wait(futures, return_when=cf.FIRST_COMPLETED)
                    futures.append(pool.submit(work, image, Path(tmp) / f"p{k:03d}.png"))
                found += [f.result() for f in futures]
            rates.append(len(poses) / (time.perf_counter() - t))
    finally:
        robot.close()
        camera.close()
    if not all(found):
        raise RuntimeError("the board was not found in every frame")
    return WhatIf(serial_rate=rates[0], pipelined_rate=rates[1], n=len(poses))
