"""ChArUco detection speed: cellcal's ``Charuco.detect`` against ``CharucoDetector.detectBoard``.

cellcal's detection is OpenCV's ``CharucoDetector.detectBoard`` plus what makes its corners a
calibration input: every corner refined on the smoothed image, corners too near the border
dropped, the minimum-corner check and the quality figures (sharpness, coverage, contrast).
Target: at most 1.2x ``detectBoard`` alone on 1920x1200 images.

Images: a 12x9-square board (30 mm squares, 22 mm ``DICT_5X5_100`` markers) drawn by OpenCV
(``generateImage``, 100 px per square) and warped into a 1920x1200 frame by homographies of
varied scale, rotation and perspective, half of them cutting the board at the image border;
Gaussian blur 0.8 px and noise 2 grey levels. Both detectors run on the same grey image,
interleaved, the median of 9 runs each; the figure is the median over images of the ratio.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python -m benchmarks.charuco      # about 30 s

Prints a table and writes ``benchmarks/results/charuco.png`` and ``charuco.md``.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import cv2
import matplotlib
import numpy as np

from calib import Charuco

matplotlib.use("Agg")
import matplotlib.pyplot as plt

OUT = Path(__file__).parent / "results"
BOARD = Charuco((12, 9), 0.03, 0.022, "DICT_5X5_100")
SIZE = (1920, 1200)
PX = 100  # print pixels per square
REPEATS = 9


def views(n: int, seed: int = 0) -> list[np.ndarray]:
    """``n`` grey 1920x1200 images of the board: random similarity + perspective, every
    other one shifted so the board runs off the image."""
    rng = np.random.default_rng(seed)
    cols, rows = BOARD.squares
    flat = BOARD.opencv_board().generateImage((cols * PX, rows * PX), marginSize=0)
    flat = cv2.copyMakeBorder(flat, PX // 2, PX // 2, PX // 2, PX // 2, cv2.BORDER_CONSTANT,
                              value=255)
    h, w = flat.shape
    out = []
    for k in range(n):
        scale = rng.uniform(0.7, 0.95) * SIZE[1] / h
        a = rng.uniform(-np.pi, np.pi)
        centre = np.array(SIZE) / 2 + (rng.uniform(-0.45, 0.45, 2) * SIZE if k % 2 else 0)
        S = np.array([[scale * np.cos(a), -scale * np.sin(a), 0.0],
                      [scale * np.sin(a), scale * np.cos(a), 0.0], [0.0, 0.0, 1.0]])
        T0 = np.array([[1.0, 0.0, -w / 2], [0.0, 1.0, -h / 2], [0.0, 0.0, 1.0]])
        P = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [*rng.normal(0.0, 1.5e-4, 2), 1.0]])
        T1 = np.array([[1.0, 0.0, centre[0]], [0.0, 1.0, centre[1]], [0.0, 0.0, 1.0]])
        image = cv2.warpPerspective(flat, T1 @ P @ S @ T0, SIZE, flags=cv2.INTER_AREA,
                                    borderValue=110)
        image = cv2.GaussianBlur(image, (0, 0), 0.8) + rng.normal(0.0, 2.0, image.shape)
        out.append(np.clip(image, 0, 255).astype(np.uint8))
    return out


def _median_ms(fn: Callable[[], object]) -> float:
    times = []
    for _ in range(REPEATS):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def speed(images: Sequence[np.ndarray]) -> dict[str, np.ndarray]:
    """Per image: ms of ``detectBoard`` alone and of ``Charuco.detect``, corners found."""
    detector = cv2.aruco.CharucoDetector(BOARD.opencv_board())
    opencv, ours, n_cv, n_ours = [], [], [], []
    for image in images:
        detector.detectBoard(image)  # warm-up
        BOARD.detect(image)
        opencv.append(_median_ms(lambda im=image: detector.detectBoard(im)))
        ours.append(_median_ms(lambda im=image: BOARD.detect(im)))
        ids = detector.detectBoard(image)[1]
        n_cv.append(0 if ids is None else len(ids))
        det = BOARD.detect(image)
        n_ours.append(len(det.ids) if det.ok else 0)
    return {"opencv_ms": np.array(opencv), "cellcal_ms": np.array(ours),
            "opencv_corners": np.array(n_cv), "cellcal_corners": np.array(n_ours)}


def table(r: dict[str, np.ndarray]) -> str:
    ratio = r["cellcal_ms"] / r["opencv_ms"]
    rows = ["| image | detectBoard (ms) | Charuco.detect (ms) | ratio | corners OpenCV / cellcal |",
            "|---|---|---|---|---|"]
    for k, (a, b, q, m, n) in enumerate(zip(r["opencv_ms"], r["cellcal_ms"], ratio,
                                            r["opencv_corners"], r["cellcal_corners"],
                                            strict=True)):
        rows.append(f"| {k} | {a:.1f} | {b:.1f} | {q:.2f} | {m} / {n} |")
    rows.append(f"| **median** | {np.median(r['opencv_ms']):.1f} | "
                f"{np.median(r['cellcal_ms']):.1f} | **{np.median(ratio):.2f}** | |")
    return "\n".join(rows)


def plot(r: dict[str, np.ndarray], path: Path) -> None:
    fig, ax = plt.subplots(figsize=(7, 3.5))
    k = np.arange(len(r["opencv_ms"]))
    ax.bar(k - 0.2, r["opencv_ms"], 0.4, label="CharucoDetector.detectBoard")
    ax.bar(k + 0.2, r["cellcal_ms"], 0.4, label="cellcal Charuco.detect")
    ax.set_xlabel("image (odd: board cut by the image border)")
    ax.set_ylabel("ms per 1920x1200 image")
    ratio = np.median(r["cellcal_ms"] / r["opencv_ms"])
    ax.set_title(f"ChArUco detection: median ratio {ratio:.2f} (target <= 1.2)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, default=12)
    args = parser.parse_args(argv)
    r = speed(views(args.images))
    text = table(r)
    print(text)
    OUT.mkdir(exist_ok=True)
    (OUT / "charuco.md").write_text(text + "\n")
    plot(r, OUT / "charuco.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
