"""Child processes that end with their parent: the service's calibration workers, and the
services and emulators that tests, the demo and benchmarks start.

Linux delivers a chosen signal to a process when the *thread* that forked it ends
(``prctl(PR_SET_PDEATHSIG)``). The request is made in the child, so a parent that died before
it was armed is caught by comparing the parent id with the one the child was forked from.
"""

from __future__ import annotations

import ctypes
import os
import sys

#: ``prctl`` option from ``<linux/prctl.h>``.
_PR_SET_PDEATHSIG = 1


def die_with_parent(sig: int, parent_pid: int) -> None:
    """In a child of ``parent_pid``: receive ``sig`` when the parent thread ends; exit at
    once if the parent is already gone. Only the exit check holds on systems other than
    Linux."""
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None).prctl(_PR_SET_PDEATHSIG, sig, 0, 0, 0)
    if os.getppid() != parent_pid:
        os._exit(1)
