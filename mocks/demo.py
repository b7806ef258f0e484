"""``cellcal demo``: the whole service flow on a simulated cell, checked against its truth.

The service runs as a real ``cellcal serve --mock`` (uvicorn) in a subprocess on a free
loopback port, with a generated API key and a temporary data directory that are gone when the
demo ends, also on Ctrl-C. The demo is its client over HTTP: plan and capture stations
(progress from the run's event stream), calibrate, run the dot-hit validation, export the
result, then compare with the mock scene's truth.

``cellcal demo --poses-only`` is the older pose-level comparison of every hand-eye method.
"""

from __future__ import annotations

import contextlib
import json
import secrets
import shutil
import signal
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import Any

import httpx
import numpy as np
from tqdm import tqdm

from calib import POSE_METHODS, calibrate_hand_eye, pose_error
from mocks.posesim import default_cell, simulate
from mocks.scene import MockScene, WorkspaceBox, read_scene
from service.exports import FORMATS
from service.serving.local import ServeOptions, ServiceStartError, local_service
from service.settings import Settings

#: Seconds to wait for the service to answer /health, and for a calibration or validation.
JOB_TIMEOUT_S = 90.0
#: Longest silence on the event stream (the service sends a keep-alive every 15 s).
EVENT_GAP_S = 60.0


class DemoError(RuntimeError):
    """A step of the demo failed; the message says which and why."""


def run_demo(*, stations: int = 15, scene: Path | None = None, out: Path | None = None) -> int:
    """Run the service flow on a mock cell and print a summary; 0, or 1 after one error line.

    ``out`` receives the result JSON and its exports (default: a new temporary directory,
    kept).
    """
    started = time.monotonic()
    out = Path(tempfile.mkdtemp(prefix="cellcal-demo-")) if out is None else out
    try:
        out.mkdir(parents=True, exist_ok=True)
        with _service(scene) as client:
            outcome = _flow(client, stations, out)
        truth = read_scene(scene)
    except (DemoError, httpx.HTTPError, OSError) as exc:
        print(f"cellcal: error: demo: {exc}", file=sys.stderr)
        return 1
    print(_summary(truth, outcome, time.monotonic() - started))
    return 0


# ---- the service in a subprocess -----------------------------------------------------------

@contextlib.contextmanager
def _service(scene: Path | None) -> Iterator[httpx.Client]:
    """``cellcal serve --mock`` on a free loopback port; stopped and its data removed on exit.

    SIGTERM to the demo unwinds like Ctrl-C, so the service is stopped either way.
    """
    data = Path(tempfile.mkdtemp(prefix="cellcal-demo-data-"))
    previous = _raise_on_sigterm()
    try:
        try:
            blind, env = _blind(read_scene(scene), data)
        except ValueError:  # the service says what is wrong with the scene, as a user meets it
            blind, env = scene, None
        with local_service(data / "service", secrets.token_urlsafe(24),
                           ServeOptions(scene=blind, env=env,
                                        log=data / "serve.log")) as service, \
                httpx.Client(base_url=service.url, timeout=30.0,
                             headers={"Authorization": f"Bearer {service.key}"}) as client:
            print(f"service: {service.url} (mock cell{'' if scene is None else f' {scene}'}; "
                  f"data in {data}, removed on exit)", file=sys.stderr, flush=True)
            yield client
    except ServiceStartError as exc:
        raise DemoError(str(exc)) from None
    finally:
        shutil.rmtree(data, ignore_errors=True)
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _blind(scene: MockScene, data: Path) -> tuple[Path | None, dict[str, str] | None]:
    """The scene as a blind cell, written to ``data``: the service learns only its setup and
    board, as on a real cell, and plans from a cold start. Its safety box is the service's
    workspace box (``CELLCAL_WORKSPACE_MIN`` / ``_MAX``, the defaults unless set), which
    the dot-hit probe must reach too: a move outside it would be a protective stop."""
    settings = Settings()
    box = WorkspaceBox(lo=settings.workspace_min, hi=settings.workspace_max)
    path = data / "blind-scene.json"
    path.write_text(scene.model_copy(update={"blind": True, "workspace": box})
                    .model_dump_json())
    return path, None


def _raise_on_sigterm() -> Callable[[int, FrameType | None], Any] | int | None:
    """Make SIGTERM raise ``KeyboardInterrupt`` (main thread only); the previous handler."""
    def interrupt(signum: int, frame: FrameType | None) -> None:
        raise KeyboardInterrupt

    with contextlib.suppress(ValueError):  # not the main thread
        return signal.signal(signal.SIGTERM, interrupt)
    return None


# ---- the flow, as a cell controller would drive it ----------------------------------------

def _call(client: httpx.Client, method: str, path: str, expect: int,
          **kwargs: Any) -> httpx.Response:
    r = client.request(method, path, **kwargs)
    if r.status_code != expect:
        try:
            detail = r.json()["detail"]
        except (ValueError, KeyError, TypeError):
            detail = r.text.strip()
        raise DemoError(f"{method} {path}: HTTP {r.status_code}: {detail}")
    return r


def _poll(client: httpx.Client, path: str, what: str) -> dict[str, Any]:
    """GET ``path`` until its state is no longer ``running``; the document if ``done``."""
    deadline = time.monotonic() + JOB_TIMEOUT_S
    while (doc := _call(client, "GET", path, 200).json())["state"] == "running":
        if time.monotonic() > deadline:
            raise DemoError(f"{what} did not finish within {JOB_TIMEOUT_S:g} s")
        time.sleep(0.2)
    if doc["state"] != "done":
        raise DemoError(f"{what} {doc['state']}: {doc['error']}")
    return doc


def _timed(label: str, step: Callable[[], dict[str, Any]]) -> dict[str, Any]:
    print(f"{label} ...", end="", file=sys.stderr, flush=True)
    t0 = time.monotonic()
    doc = step()
    print(f" {time.monotonic() - t0:.1f} s", file=sys.stderr)
    return doc


@dataclass(frozen=True)
class _Outcome:
    """What the flow produced: the run, the result document, the dot-hit report (None
    eye-to-hand), the files written (the result first) into ``out``."""

    run: dict[str, Any]
    result: dict[str, Any]
    report: dict[str, Any] | None
    files: list[str]
    out: Path


def _flow(client: httpx.Client, stations: int, out: Path) -> _Outcome:
    """Capture, calibrate, validate (eye-in-hand), export into ``out``."""
    run_id = _call(client, "POST", "/runs", 201, json={"stations": stations}).json()["id"]
    run = _watch_capture(client, run_id, stations)
    cal_id = _call(client, "POST", f"/runs/{run_id}/calibrations", 202, json={}).json()["id"]
    result = _timed("calibrating", lambda: _poll(client, f"/calibrations/{cal_id}",
                                                 "the calibration"))["result"]
    report = None
    if result["setup"] == "eye_in_hand":  # eye-to-hand, the board rides on the tool
        val_id = _call(client, "POST", f"/calibrations/{cal_id}/validations", 202,
                       json={}).json()["id"]
        report = _timed("dot-hit validation", lambda: _poll(client, f"/validations/{val_id}",
                                                            "the validation"))["result"]
    files = []
    for fmt in FORMATS:
        r = _call(client, "GET", f"/calibrations/{cal_id}/export", 200, params={"format": fmt})
        files.append(r.headers["content-disposition"].split('filename="')[1].rstrip('"'))
        (out / files[-1]).write_bytes(r.content)
    return _Outcome(run=run, result=result, report=report, files=files, out=out)


def _watch_capture(client: httpx.Client, run_id: str, stations: int) -> dict[str, Any]:
    """Follow the run's server-sent events with a progress bar; the final state event."""
    state: dict[str, Any] = {}
    with tqdm(total=stations, desc="capturing", unit="station", file=sys.stderr) as bar, \
            client.stream("GET", f"/runs/{run_id}/events",
                          timeout=httpx.Timeout(30.0, read=EVENT_GAP_S)) as r:
        if r.status_code != 200:
            raise DemoError(f"GET /runs/{run_id}/events: HTTP {r.status_code}")
        for line in r.iter_lines():
            if not line.startswith("data: "):
                continue
            event = json.loads(line.removeprefix("data: "))
            if event["type"] == "state":
                state = event
                bar.total = event["stations_planned"]
                bar.n = event["stations_captured"] + event["stations_skipped"]
                bar.refresh()
            else:
                bar.update(1)
    if state.get("state") != "done":
        error = (state.get("error") or {}).get("detail", "the event stream ended early")
        raise DemoError(f"capture run {state.get('state', 'lost')}: {error}")
    return state


# ---- the summary -----------------------------------------------------------------------------

def _dot_hit_errors(truth: MockScene, report: dict[str, Any]) -> dict[str, float]:
    """Per probed point: the distance (m) from the probe tip the robot reported to the true
    board point (``corner_i_j`` at grid index (i, j) of the true κ, ν-scaled board, ``centre``
    the middle of the outer corners), eye-in-hand, where the board lies in the base frame."""
    t = truth.target
    s = t.square_size_m * t.kappa
    true: dict[str, np.ndarray] = {}
    for p in report["points"]:
        if p["id"].startswith("corner_"):
            i, j = (int(v) for v in p["id"].split("_")[1:])
            true[p["id"]] = np.array([i * s * t.nu, j * s, 0.0])
    true["centre"] = np.mean(list(true.values()), axis=0)
    Y = truth.target_pose_matrix
    return {p["id"]: float(np.linalg.norm(np.asarray(p["reached"])
                                          - (Y[:3, :3] @ true[p["id"]] + Y[:3, 3])))
            for p in report["points"]}


def _summary(truth: MockScene, outcome: _Outcome, wall_s: float) -> str:
    """What a person wants to read: errors against the truth, with the reported σ."""
    run, result, report = outcome.run, outcome.result, outcome.report
    out, files = outcome.out, outcome.files
    unc = result["uncertainty"]
    cam, target = result["camera"], result["target"]
    he_r, he_t = pose_error(np.asarray(result["hand_eye"]["matrix"]), truth.hand_eye_matrix)
    tp_r, tp_t = pose_error(np.asarray(result["target_pose"]["matrix"]),
                            truth.target_pose_matrix)
    sd_r = np.degrees(np.linalg.norm(unc["hand_eye_rot_rad"]))
    sd_t = np.linalg.norm(unc["hand_eye_trans_m"]) * 1e3
    K, K_true = np.asarray(cam["K"]), truth.camera.k_matrix
    intr = "  ".join(f"{name} {K[i, j] - K_true[i, j]:+.2f} (σ {unc['camera'][name]:.2f})"
                     for name, i, j in (("fx", 0, 0), ("fy", 1, 1), ("cx", 0, 2),
                                        ("cy", 1, 2)))
    used = len(result["stations"])
    lines = [
        "",
        f"Calibration of a simulated {result['setup'].replace('_', '-')} cell: "
        f"{run['stations_captured']} stations captured, {used} used, method {result['method']}, "
        f"reprojection RMS {cam['rms_px']:.3f} px",
        "  error against the mock truth (estimate - true)",
        f"    hand-eye      {np.degrees(he_r):.4f} deg  {he_t * 1e3:.3f} mm   "
        f"(1-σ {sd_r:.4f} deg, {sd_t:.3f} mm, norm over axes)",
        f"    target pose   {np.degrees(tp_r):.4f} deg  {tp_t * 1e3:.3f} mm",
        f"    intrinsics    {intr} px",
        f"  board scale     κ {target['kappa']:.5f} ± {target['kappa_sigma']:.5f}   "
        f"true {truth.target.kappa:.5f}",
        f"  board aspect    ν {target['nu']:.5f} ± {target['nu_sigma']:.5f}   "
        f"true {truth.target.nu:.5f}",
        "",
    ]
    if report is None:
        lines.append("Dot-hit validation: skipped (eye-to-hand: the board rides on the tool)")
    else:
        errors = _dot_hit_errors(truth, report)
        lines.append(f"Dot-hit validation (SM eq. 24): probe tip "
                     f"{np.linalg.norm(report['probe'][:3]) * 1e3:.0f} mm from the TCP, error = "
                     "probe tip the robot reports to the true board point (the cell is blind: "
                     "the demo holds the truth)")
        lines += [f"    {name:<12} {e * 1e3:6.3f} mm" for name, e in errors.items()]
        values = np.array(list(errors.values()))
        lines.append(f"    {'mean':<12} {values.mean() * 1e3:6.3f} mm   max "
                     f"{values.max() * 1e3:.3f} mm")
    lines += ["",
              f"Result: {out / files[0]}",
              f"  exports next to it: {', '.join(files[1:])}",
              f"Wall time {wall_s:.1f} s",
              _verdict_line(result)]
    return "\n".join(lines)


def _verdict_line(result: dict[str, Any]) -> str:
    """The last line: the verdict and, unless it is a pass, why (each finding's message), so
    a warn is explained where it is read."""
    quality = result.get("quality") or {"verdict": "pass", "findings": []}
    findings = [f for f in quality["findings"] if f.get("severity") != "info"] or \
        quality["findings"]
    why = "; ".join(f"{f['message']} [{f['code']}]" for f in findings)
    return f"Verdict {quality['verdict']}" + (f": {why}" if why and quality["verdict"] != "pass"
                                              else "")


# ---- the pose-level comparison -----------------------------------------------------------

def run_pose_demo(*, seed: int = 1, stations: int = 15) -> int:
    """Every hand-eye method on simulated robot and camera poses, against the truth.

    The robot readings carry UR-class noise (0.05 deg / 0.25 mm) and the camera poses come
    from PnP on corners with 0.15 px noise, as in the hand-eye accuracy benchmark.
    """
    cell = default_cell("eye_in_hand")
    P, C = simulate(cell, stations, np.random.default_rng(seed))
    print(f"Simulated eye-in-hand cell: {stations} stations, robot noise 0.05 deg / 0.25 mm, "
          "camera poses from PnP on 0.15 px corner noise\n")
    rows = []
    for method in tqdm(POSE_METHODS, desc="calibrating", unit="method", leave=False):
        result = calibrate_hand_eye(P, C, method=method)
        dr, dt = pose_error(result.hand_eye, cell.hand_eye)
        yr, yt = pose_error(result.target_pose, cell.target_pose)
        rows.append((method, np.degrees(dr), dt * 1e3, np.degrees(yr), yt * 1e3, result))
    print(f"{'method':<11} {'hand-eye err':>21} {'target-pose err':>21}")
    for method, dr, dt, yr, yt, _ in rows:
        print(f"{method:<11} {dr:9.4f} deg {dt:7.3f} mm {yr:9.4f} deg {yt:7.3f} mm")
    refined = rows[-1][5]
    sd_t = np.linalg.norm(refined.sigmas["hand_eye_trans_m"]) * 1e3
    sd_r = np.degrees(np.linalg.norm(refined.sigmas["hand_eye_rot_rad"]))
    print(f"\nrefine (default) reports 1-sigma hand-eye uncertainty: {sd_r:.4f} deg, "
          f"{sd_t:.3f} mm (norm over axes)")
    return 0
