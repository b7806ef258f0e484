"""Shared test helpers: random rigid transforms and the one pose tolerance check."""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
from pydantic import BaseModel
from scipy.spatial.transform import Rotation

from calib.geometry import make_transform, pose_error
from mocks.posesim import Cell, default_cell, robot_poses, sample_camera_poses
from service.serving.parent_death import die_with_parent

T = TypeVar("T")


def ends_with_this_process(sig: int = signal.SIGKILL, *,
                            then: Callable[[], None] | None = None) -> Callable[[], None]:
    """A ``preexec_fn`` for a process a test starts: it receives ``sig`` when the test's
    thread ends, so a test run killed mid-way (a CI timeout) leaves it not behind; ``then``
    runs next (issue 22, row 12)."""
    parent = os.getpid()

    def setup() -> None:
        die_with_parent(sig, parent)
        if then is not None:
            then()
    return setup


def random_transforms(rng: np.random.Generator, n: int, *, scale: float = 1.0) -> np.ndarray:
    """n random rigid transforms (n, 4, 4): uniform rotations, Gaussian translations (m)."""
    R = Rotation.random(n, random_state=rng).as_matrix()
    return make_transform(R, rng.normal(0.0, scale, (n, 3)))


def assert_pose_close(T_est: np.ndarray, T_true: np.ndarray, *, rot: float, trans: float) -> None:
    """Rotation angle below ``rot`` rad and translation distance below ``trans`` m."""
    dr, dt = pose_error(T_est, T_true)
    assert np.all(dr < rot), f"rotation error {np.max(dr):.3e} rad >= {rot:.1e}"
    assert np.all(dt < trans), f"translation error {np.max(dt):.3e} m >= {trans:.1e}"


def exact_stations(setup: str, n: int, seed: int) -> tuple[Cell, np.ndarray, np.ndarray]:
    """A simulated cell and ``n`` noise-free stations: (cell, T_base_tcp, T_cam_target)."""
    cell = default_cell(setup)
    C = sample_camera_poses(cell, n, np.random.default_rng(seed))
    return cell, robot_poses(cell, C), C


#: The first and the longest pause between two polls of a condition, s.
FIRST_POLL_S, LONGEST_POLL_S = 0.02, 0.2


def poll_pauses(first: float = FIRST_POLL_S) -> Iterator[float]:
    """Pauses between the polls of a wait: ``first`` s, then each 1.5x the last, up to
    ``LONGEST_POLL_S``. A condition met soon is seen soon; a long wait (a run, a solve) asks
    5 times a second instead of 20-50, and each ask of a service costs 2-5 ms of CPU."""
    pause = first
    while True:
        yield pause
        pause = min(1.5 * pause, LONGEST_POLL_S)


def wait_for(what: str, condition: Callable[[], T], timeout: float = 120.0, *,
             until: Callable[[T], object] = bool, first: float = FIRST_POLL_S) -> T:
    """Poll ``condition`` until ``until`` holds for what it returns (by default: until it is
    truthy) and return that; fail after ``timeout`` s naming ``what`` and the last value (a
    guard against hangs, not a speed requirement). The one way tests wait for a condition."""
    deadline = time.monotonic() + timeout
    pauses = poll_pauses(first)
    while not until(value := condition()):
        assert time.monotonic() < deadline, _timed_out(what, value)
        time.sleep(next(pauses))
    return value


def _timed_out(what: str, last: object) -> str:
    seen = "" if last is None or isinstance(last, bool) else f" (last: {last!r})"
    return f"timed out waiting for {what}{seen}"


#: ``../shared`` beside the repository (CI and developers have it there), e.g. the real images.
SHARED = Path(os.environ.get("CELLCAL_SHARED", Path(__file__).resolve().parents[3] / "shared"))
OPENCV_LEFT = SHARED / "data" / "opencv-left"


def undeclared_fields(model: Any, path: str = "result") -> list[str]:
    """Fields of a parsed document (pydantic, ``extra="allow"``) that its schema does not
    declare, as dotted paths; a quality finding's figures are free by design."""
    out: list[str] = []
    if isinstance(model, BaseModel):
        if not path.endswith("findings[]"):
            out += [f"{path}.{k}" for k in model.model_extra or {}]
        for name in type(model).model_fields:
            out += undeclared_fields(getattr(model, name), f"{path}.{name}")
    elif isinstance(model, list):
        for item in model:
            out += undeclared_fields(item, f"{path}[]")
    return sorted(set(out))
