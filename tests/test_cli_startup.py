"""``cellcal --version`` and ``--help`` load no numerics, OpenCV or service: a command loads
only what it needs, when it runs (the start-up time itself is measured in
``benchmarks/end_to_end.py``, not here)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

HEAVY = ("numpy", "scipy", "cv2", "calib", "fastapi", "sqlalchemy")
#: Not needed to say the version: it is a constant (service.version), not package metadata.
METADATA = "importlib.metadata"
_PROBE = """
import sys
from service.cli.main import main
try:
    main({argv!r})
except SystemExit:
    pass
print(" ".join(sorted({{m.split(".")[0] for m in sys.modules}} | {{m for m in sys.modules
                                                             if m == "importlib.metadata"}})))
"""


def _modules_after(argv: list[str]) -> set[str]:
    out = subprocess.run([sys.executable, "-c", _PROBE.format(argv=argv)], capture_output=True,
                         text=True, check=True)
    return set(out.stdout.split())


@pytest.mark.parametrize("argv", [["--version"], ["--help"], ["runs", "--help"]])
def test_version_help_and_client_commands_load_no_numerics(argv):
    assert not _modules_after(argv) & set(HEAVY)


@pytest.mark.parametrize("argv", [["--version"], ["--help"]])
def test_version_and_help_read_no_package_metadata(argv):
    assert METADATA not in _modules_after(argv)


def test_a_command_loads_what_it_needs():
    loaded = _modules_after(["calibrate", "--help"])
    assert {"calib", "numpy", "cv2"} <= loaded
    # the solver's imports (scipy) wait until the images are being read and detected
    assert not {"fastapi", "scipy"} & loaded
    # and so do the result's pydantic models (0.02 s), which the station set does not need
    out = subprocess.run([sys.executable, "-c", "import sys, service.cli.calibrate; "
                          "print('calib.result' in sys.modules)"], capture_output=True,
                         text=True, check=True)
    assert out.stdout.strip() == "False"


_BLAS_THREADS = """
from service.cli.main import build_parser
build_parser(["calibrate", "x"])  # loads the command: numpy, OpenCV
import scipy.linalg
from threadpoolctl import threadpool_info
print(sorted({i["num_threads"] for i in threadpool_info() if i["internal_api"] == "openblas"}))
"""


@pytest.mark.parametrize(("given", "threads"), [(None, "[1]"), ("2", "[2]")])
def test_blas_runs_on_one_thread_unless_told_otherwise(given, threads):
    """Every OpenBLAS the command loads (numpy's, scipy's, OpenCV's) starts with one thread;
    an OPENBLAS_NUM_THREADS the user set wins."""
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    if given is not None:
        env["OPENBLAS_NUM_THREADS"] = given
    out = subprocess.run([sys.executable, "-c", _BLAS_THREADS], capture_output=True, text=True,
                         check=True, env=env)
    assert out.stdout.strip() == threads


def test_the_installed_package_has_the_version_the_command_says():
    from importlib.metadata import version

    from service.version import VERSION

    assert version("cellcal") == VERSION
