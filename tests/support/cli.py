"""``cellcal`` as a user meets it: a child process with its peak memory, and the one-line
error it prints."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from tests.support.helpers import ends_with_this_process


def assert_one_line_error(err: str, text: str) -> None:
    """``err`` is one ``cellcal: error:`` line that names ``text``, with no traceback."""
    assert err.startswith("cellcal: error: ") and err.count("\n") == 1, err
    assert text in err and "Traceback" not in err


#: Memory a calibration of bad files may take (issue 11 acceptance), bytes.
MEMORY_LIMIT = 500e6
#: Only a hang (the FIFO of the old code) reaches this; it is no speed requirement.
HANG_TIMEOUT_S = 120

#: Runs ``argv`` in its own child and writes that child's peak RSS (kB) to the file ``argv[1]``.
#: Linux keeps the high-water RSS of a process across ``exec``, so a child started from this
#: test process would report at least the test process's own RSS (hundreds of MB after other
#: tests ran in it); a child of this small launcher starts afresh.
_PEAK_RSS_LAUNCHER = """
import ctypes, os, signal, subprocess, sys
child = subprocess.Popen(sys.argv[2:],  # dies with this launcher (PR_SET_PDEATHSIG)
                         preexec_fn=lambda: ctypes.CDLL(None).prctl(1, signal.SIGKILL, 0, 0, 0))
_, status, usage = os.wait4(child.pid, 0)
with open(sys.argv[1], "w") as f:
    f.write(str(usage.ru_maxrss))
sys.exit(os.waitstatus_to_exitcode(status))
"""


def run_cli(*args: str) -> tuple[int, str, str, float]:
    """Run ``cellcal`` in a child process: exit code, stdout, stderr, its peak RSS in bytes.

    The peak is ``cellcal``'s own ``ru_maxrss`` (from ``wait4`` in ``_PEAK_RSS_LAUNCHER``).
    """
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err, \
            tempfile.TemporaryDirectory() as scratch:
        peak_file = Path(scratch) / "peak_kb"
        proc = subprocess.Popen([sys.executable, "-c", _PEAK_RSS_LAUNCHER, str(peak_file),
                                 sys.executable, "-m", "service.cli", *args],
                                stdin=subprocess.DEVNULL, stdout=out, stderr=err,
                                start_new_session=True, preexec_fn=ends_with_this_process())
        try:
            proc.wait(HANG_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)  # the launcher and cellcal
            proc.wait()
            pytest.fail(f"cellcal {' '.join(args)} still running after {HANG_TIMEOUT_S} s")
        out.seek(0)
        err.seek(0)
        return (proc.returncode, out.read().decode(), err.read().decode(),
                float(peak_file.read_text()) * 1024.0)  # kB on Linux
