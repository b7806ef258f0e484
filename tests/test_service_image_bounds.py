"""Posted images are bounded before they are decoded, and searched in a worker with a memory
limit and a CPU budget (issue 22, row 3; ``service.jobs.image_worker``).

A striped 49-megapixel PNG is 155 kB on the wire; its board search took 105 CPU-s and 9.7 GB
in the service. Now the header alone refuses it (413), and an image under the pixel cap that
still needs too much memory or CPU is refused by its worker, not by the host. The service's
memory is read from ``/proc`` (its peak RSS, ``VmHWM``) only as an upper bound that load cannot
break; how fast a refusal comes is measured by ``tools/image-attack``, not asserted here.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.serving.local import local_service
from tests.support.service import AUTH, external_run, post, robot_pose, settings

KEY = "image-bounds-key-0123456789"


def striped_png(width: int, height: int) -> bytes:
    """A PNG of vertical stripes: tiny on the wire, costly to search for a board."""
    image = np.zeros((height, width), np.uint8)
    image[:, ::8] = 255
    return cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 9])[1].tobytes()


def checker_png(width: int, height: int, square: int = 16) -> bytes:
    """A PNG of ``square``-pixel checkers: a board-like texture, a few kB on the wire."""
    y, x = np.ogrid[:height, :width]
    image = ((x // square + y // square) % 2 * 255).astype(np.uint8)
    return cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 9])[1].tobytes()


def peak_rss_mb(pid: int) -> float:
    """The process's peak resident memory so far (``VmHWM``), MB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmHWM")


def assert_too_large(r: httpx.Response | Any, why: str) -> None:
    assert r.status_code == 413, r.text
    assert r.json()["code"] == "image_too_large" and why in r.json()["detail"]


@pytest.mark.timeout(120)
def test_49_mp_png_is_refused_from_its_header_alone(tmp_path: Path) -> None:
    image = striped_png(7000, 7000)
    assert len(image) < 4 * 2**20  # under the body limit: only the pixel cap can stop it
    with (local_service(tmp_path / "data", KEY) as service,
          httpx.Client(base_url=service.url, headers={"Authorization": f"Bearer {KEY}"},
                       timeout=60) as client):
        run_id = client.post("/runs", json={"mode": "external"}).json()["id"]
        pose = client.get("/devices").json()["robot"]["tcp_pose"]
        files = {"image": ("big.png", image, "image/png")}
        data = {"pose": json.dumps(pose)}
        before = peak_rss_mb(service.proc.pid)
        url = f"/runs/{run_id}/stations"
        assert_too_large(client.post(url, data=data, files=files), "7000x7000 = 49 MP")
        answers: list[httpx.Response] = []
        posts = [threading.Thread(target=lambda: answers.append(
            client.post(url, data=data, files=files))) for _ in range(4)]
        for t in posts:
            t.start()
        for t in posts:
            t.join()
        for r in answers:
            assert_too_large(r, "more than the 25 MP allowed (CELLCAL_MAX_IMAGE_PIXELS)")
        assert len(answers) == 4
        assert peak_rss_mb(service.proc.pid) - before < 100
        assert client.get(url).json() == []  # nothing stored
        assert client.get("/health").status_code == 200


@contextmanager
def limited(tmp_path: Path, **limits: Any) -> Iterator[TestClient]:
    """An in-process service whose image workers have the given ``limits``."""
    app = create_app(settings(tmp_path, max_body_bytes=8 * 2**20, **limits))
    with TestClient(app) as c:
        c.headers.update(AUTH)
        yield c


def assert_serves_a_next_image(client: TestClient, run_id: str, pose: list[float]) -> None:
    """The pool starts a fresh worker: an ordinary frame is searched and stored."""
    r = post(client, run_id, pose=pose, image=cv2.imencode(
        ".png", np.full((480, 640), 128, np.uint8))[1].tobytes())
    assert r.status_code == 201, r.text
    assert r.json()["state"] == "skipped" and r.json()["error"]["code"] == "not_detected"
    assert [s["index"] for s in client.get(f"/runs/{run_id}/stations").json()] == [0]


@pytest.mark.timeout(180)
def test_a_search_beyond_the_workers_memory_is_refused(tmp_path: Path) -> None:
    with limited(tmp_path, image_worker_memory_mb=900) as client:
        run_id, pose = external_run(client), robot_pose(client)
        # 16 MP, under the pixel cap: its search needs gigabytes (a worker has 900 MB)
        assert_too_large(post(client, run_id, pose=pose, image=striped_png(4000, 4000)),
                         "more than the 900 MB an image worker may use")
        assert_serves_a_next_image(client, run_id, pose)


@pytest.mark.timeout(180)
def test_a_search_beyond_its_cpu_budget_is_refused(tmp_path: Path) -> None:
    with limited(tmp_path, image_cpu_s=1.0) as client:
        run_id, pose = external_run(client), robot_pose(client)
        # 2.3 MP: fits in memory, but its search needs more than 1 CPU-s
        r = post(client, run_id, pose=pose, image=striped_png(1920, 1200))
        assert r.status_code == 422, r.text
        assert r.json()["code"] == "image_too_complex"
        assert_serves_a_next_image(client, run_id, pose)


@pytest.mark.slow  # the default budget: 20 CPU-s of search before the refusal
@pytest.mark.timeout(900)
def test_a_dense_checker_texture_under_the_pixel_cap_is_refused_by_default(tmp_path: Path) -> None:
    """24 MP of 16-pixel checkers, 37 kB on the wire and under the 25 MP cap, so it is decoded
    and searched: every fallback search runs at full size, 45 CPU-s and 4.8 GB without limits
    (``tools/image-attack``). The default worker limits refuse it, and serve the next image."""
    with limited(tmp_path) as client:
        run_id, pose = external_run(client), robot_pose(client)
        r = post(client, run_id, pose=pose, image=checker_png(6000, 4000))
        assert (r.status_code, r.json()["code"]) in {(422, "image_too_complex"),
                                                     (413, "image_too_large")}, r.text
        assert client.get(f"/runs/{run_id}/stations").json() == []
        assert_serves_a_next_image(client, run_id, pose)
