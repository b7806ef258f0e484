"""Posted images, bounded before they are decoded and searched in a worker with a memory limit.

An image a cell controller posts (``service.runs.external``) is untrusted: a striped
49-megapixel PNG is 155 kB on the wire, and the board search over it took 105 CPU-s and
9.7 GB (issue 22). So:

* the pixel count in the PNG or JPEG header is checked in the request, before anything is
  decoded: beyond ``Settings.max_image_pixels`` the post is answered 413 ``image_too_large`` at
  once and nothing is stored;
* decoding and the board search run in a worker process (``service.jobs.workers.WorkerPool``)
  whose address space is capped at ``Settings.image_worker_memory_mb``: an allocation beyond
  it fails in the worker (413 ``image_too_large``, saying so), not in the host;
* an image of more than ``SEARCH_PIXELS`` is searched on a reduced copy (``cv2.pyrDown``)
  first, and at full size only if the board is there: a search that finds nothing runs every
  fallback search, 37-44 CPU-s at 24 MP (checker texture, stripes, an upscaled photo) against
  0.9-1.3 s for one that finds the board; on the reduced copy those textures cost 1.8-2.4 CPU-s
  (measured). A regular checker grid larger than the board made every fallback search run
  slowly at any size (32-pixel checkers: 12.8 CPU-s at 1 MP, 8-pixel ones 26.9); the detector
  now counts the grid's corners when its default searches fail, and skips the fallbacks when
  the count is beyond the board's (``calib.boards.lattice``: 0.7-0.8 CPU-s for those). What
  stays costly is left to the CPU budget: an image whose reduced copy shows the board but
  whose full size does not, and any image the fallback searches run on, as on a real image
  without its board (about 2-5 CPU-s per searched megapixel);
* each search has a CPU budget, ``Settings.image_cpu_s``: the kernel ends a worker that
  passes it (``RLIMIT_CPU``), and the post is answered 422 ``image_too_complex``; the pool
  starts a fresh worker for the next image.

The workers are shared by all runs; ``service.runs.external`` lets each run use one at a
time, so uploads to one run never queue behind another's.
"""

from __future__ import annotations

import concurrent.futures as cf
import resource
import threading
from dataclasses import dataclass

import cv2
import numpy as np

from calib import (
    ChecksConfiguration,
    Detection,
    Target,
    board_from_target,
    opencv_out_of_memory,
)
from service.api.guard import PayloadTooLargeError
from service.errors import UnprocessableError
from service.jobs.workers import WorkerPool
from service.settings import Settings
from service.stationsets.images import ImageFileError, decode_image_bytes, image_size

#: Workers of the pool: two, so a second run is served while one run's image is searched.
WORKERS = 2
#: Largest image searched for the board at full size before a reduced copy has shown it,
#: pixels (more than the real image sets of ../shared/data, 2.3 MP at most).
SEARCH_PIXELS = 3_000_000


class ImageTooLargeError(PayloadTooLargeError, code="image_too_large"):
    """A posted image with more pixels than allowed, or one whose search needs more memory
    than an image worker has (413)."""


class ImageTooComplexError(UnprocessableError, code="image_too_complex"):
    """A posted image whose board search ran out of its CPU budget (422)."""


@dataclass(frozen=True)
class Developed:
    """What a worker made of a posted image: the grey image (H, W) uint8 and its detection,
    or why there is none (``problem``: a skipped station's reason), or ``out_of_memory``;
    ``seen``: for a board not found, what the image shows instead (the service does not search
    an untrusted image itself)."""

    image: np.ndarray | None = None
    detection: Detection | None = None
    problem: str | None = None
    out_of_memory: bool = False
    seen: str | None = None  # what the image shows instead of the board (``Board.mismatch``)


def check_pixels(data: bytes, max_pixels: int) -> None:
    """Refuse (413 ``image_too_large``) an image whose header announces more than
    ``max_pixels``; unreadable headers are left to the decoder, which says why."""
    size = image_size(data)
    if size is not None and size[0] * size[1] > max_pixels:
        width, height = size
        raise ImageTooLargeError(
            f"The image is {width}x{height} = {width * height / 1e6:.0f} MP, more than the "
            f"{max_pixels / 1e6:g} MP allowed (CELLCAL_MAX_IMAGE_PIXELS); nothing was stored.")


@dataclass(frozen=True)
class ImageJob:
    """One posted image as a worker process receives it (pickled): the encoded ``data``, the
    run's board ``target``, the pixel limit and the CPU budget (seconds) of its search."""

    data: bytes
    target: Target
    max_pixels: int
    cpu_s: float


def develop(job: ImageJob) -> Developed:
    """Worker entry: decode the job's image and search it for its board, within ``cpu_s``
    more seconds of CPU (the kernel ends the worker beyond)."""
    used = resource.getrusage(resource.RUSAGE_SELF)
    soft = int(used.ru_utime + used.ru_stime + job.cpu_s) + 1
    resource.setrlimit(resource.RLIMIT_CPU, (soft, resource.RLIM_INFINITY))
    try:
        image = decode_image_bytes(job.data, "image", max_pixels=job.max_pixels)
    except ImageFileError as exc:
        return Developed(problem=f"{exc}.")
    except MemoryError:
        return Developed(out_of_memory=True)
    board = board_from_target(job.target)
    try:
        reduced = image
        while reduced.shape[0] * reduced.shape[1] > SEARCH_PIXELS:
            reduced = cv2.pyrDown(reduced)
        detection = board.detect(reduced)
        if reduced is not image and detection.ok:
            detection = board.detect(image)
        seen = (board.mismatch(reduced) if not detection.ok
                and isinstance(board, ChecksConfiguration) else None)
        return Developed(image=image, detection=detection, seen=seen)
    except MemoryError:
        return Developed(out_of_memory=True)
    except cv2.error as exc:
        if opencv_out_of_memory(exc):
            return Developed(out_of_memory=True)
        raise


class ImageWorkers:
    """The pool that decodes and searches posted images (started on first use)."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self._pool: WorkerPool | None = None
        self._lock = threading.Lock()

    def develop(self, data: bytes, target: Target) -> Developed:
        """Decode and search ``data`` (whose header ``check_pixels`` passed) in a worker; 413
        if it needs more memory than a worker has, 422 if it runs out of its CPU budget."""
        settings = self.settings
        future = self._submit(ImageJob(data, target, settings.max_image_pixels,
                                       settings.image_cpu_s))
        try:
            developed: Developed = future.result()
        except cf.process.BrokenProcessPool:
            self._discard()
            raise ImageTooComplexError(
                f"Searching the image for the board took more than {settings.image_cpu_s:g} "
                "CPU-s (CELLCAL_IMAGE_CPU_S), or its worker died; nothing was stored.") from None
        if developed.out_of_memory:
            raise ImageTooLargeError(
                "Decoding the image and searching it for the board needs more than the "
                f"{settings.image_worker_memory_mb} MB an image worker may use "
                "(CELLCAL_IMAGE_WORKER_MEMORY_MB); nothing was stored.")
        return developed

    def _submit(self, job: ImageJob) -> cf.Future[Developed]:
        with self._lock:
            if self._pool is None:
                self._pool = WorkerPool(WORKERS, lambda message: None,
                                        memory_bytes=self.settings.image_worker_memory_mb
                                        * 2**20)
            return self._pool.submit(develop, job)

    def _discard(self) -> None:
        """Drop a broken pool; the next image starts a new one."""
        with self._lock:
            if self._pool is not None:
                self._pool.shutdown()
                self._pool = None

    def shutdown(self) -> None:
        self._discard()
