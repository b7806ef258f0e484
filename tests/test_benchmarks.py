"""Benchmarks that cannot rot: each one imports and offers ``--quick`` (fast suite), and each
``--quick`` run completes and writes its figure (slow suite, ``make test-slow``), into a
temporary directory so the recorded figures stay as they are (``CELLCAL_BENCH_OUT``)."""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: Each benchmark (``python -m benchmarks.NAME``) and the figure its run writes.
BENCHMARKS = {
    "charuco": "charuco.png",
    "cold_start": "cold_start.png",
    "cold_start_bound": "cold_start_bound.png",
    "end_to_end": "end_to_end.png",
    "handeye_accuracy": "handeye_accuracy.png",
    "kappa_nu": "kappa_nu.png",
    "real_cv": "real_cv.png",
    "service": "service.png",
    "uncertainty": "uncertainty.png",
}
#: Scripts with a ``main`` that are not benchmarks: the OpenCV peer ``end_to_end`` times, the
#: light load generator of ``service --history``, and the paired server-CPU comparison of git
#: revisions under that history's GETs (a tool for one change, no figure).
PEER_SCRIPTS = {"opencv_pipeline", "history_client", "history_cpu"}


def test_every_benchmark_module_is_listed() -> None:
    found = {p.stem for p in (ROOT / "benchmarks").glob("*.py")
             if "\ndef main(" in p.read_text()}
    assert found - PEER_SCRIPTS == set(BENCHMARKS)


@pytest.mark.parametrize("name", sorted(BENCHMARKS))
def test_benchmark_imports_and_offers_quick(name: str, monkeypatch: pytest.MonkeyPatch,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    module = importlib.import_module(f"benchmarks.{name}")
    monkeypatch.setattr(sys, "argv", [name, "--help"])
    with pytest.raises(SystemExit) as exit_:
        module.main()
    assert exit_.value.code == 0
    assert "--quick" in capsys.readouterr().out


@pytest.mark.slow
@pytest.mark.timeout(1800)
@pytest.mark.parametrize("name", sorted(BENCHMARKS))
def test_quick_benchmark_run_writes_its_figure(name: str, tmp_path: Path) -> None:
    env = {**os.environ, "CELLCAL_BENCH_OUT": str(tmp_path), "OPENBLAS_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-m", f"benchmarks.{name}", "--quick"], cwd=ROOT,
                          env=env, capture_output=True, text=True, timeout=1700)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert (tmp_path / BENCHMARKS[name]).stat().st_size > 0


@pytest.mark.slow
@pytest.mark.timeout(1800)
def test_quick_history_run_reports_every_pair_and_writes_its_figure(tmp_path: Path) -> None:
    """``service --history --quick`` runs to its end on both databases and both clients. Its
    exit status says whether the latency targets were met, which depends on the machine, so
    the test asserts the run's verdict lines and figure instead."""
    env = {**os.environ, "CELLCAL_BENCH_OUT": str(tmp_path), "OPENBLAS_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-m", "benchmarks.service", "--history", "--quick"],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=1700)
    assert proc.returncode in (0, 1), proc.stderr[-2000:]
    verdicts = [line for line in proc.stdout.splitlines() if "all GETs p50 / p99" in line]
    assert [line.split(",")[0] for line in verdicts] == ["sqlite"] * 2 + ["postgresql"] * 2
    assert (tmp_path / "service_history.png").stat().st_size > 0
