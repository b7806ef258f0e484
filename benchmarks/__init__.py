"""Benchmarks: ``python -m benchmarks.NAME`` prints its tables and writes its figure to
``benchmarks/results/`` (figures and commands in ``benchmarks/README.md``).

Every benchmark takes ``--quick``, a smoke-sized run; ``make test-slow`` runs each one that way
(``tests/test_benchmarks.py``) so none rots unnoticed. With ``CELLCAL_BENCH_OUT`` set, a
benchmark writes there instead, so a test's quick run never replaces the recorded figures.
"""

from __future__ import annotations

import os
import signal
from pathlib import Path
from typing import Any


def results_dir() -> Path:
    """Where a benchmark writes its tables and figures (``CELLCAL_BENCH_OUT`` or
    ``benchmarks/results/``)."""
    return Path(os.environ.get("CELLCAL_BENCH_OUT") or Path(__file__).parent / "results")


def interrupt_on_sigterm() -> None:
    """Turn SIGTERM into KeyboardInterrupt, so a benchmark stopped with ``kill`` runs its
    ``finally`` and ``with`` exits (reaps its server, terminates its worker pool) instead of
    leaving its children running."""

    def on_term(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, on_term)
