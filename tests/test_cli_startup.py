"""``cellcal --version`` and ``--help`` load no numerics, OpenCV or service: a command loads
only what it needs, when it runs (the start-up time itself is measured in
``benchmarks/end_to_end.py``, not here)."""

from __future__ import annotations

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


def test_the_installed_package_has_the_version_the_command_says():
    from importlib.metadata import version

    from service.version import VERSION

    assert version("cellcal") == VERSION
