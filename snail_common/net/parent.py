"""An embedded daemon ends with the process that started it.

``snail-client localize`` and ``snail-bench`` start both daemons as subprocesses and stop
them on the way out; killed with SIGKILL (or by the OOM killer) they cannot, and the
daemons lived on, holding their ports and gigabytes of circuits. The starter sets
``SNAIL_EXIT_WITH_PARENT`` to its pid in the daemon's environment; the daemon then asks
Linux for SIGTERM when its parent dies (``PR_SET_PDEATHSIG``), which shuts it down as
usual, and exits at once if the parent is already gone. Elsewhere it does nothing. Other
long children (``snail-bench paper`` compiling a circuit for minutes) ask the same way.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import signal
import sys
import threading

PARENT_ENV = "SNAIL_EXIT_WITH_PARENT"
_PR_SET_PDEATHSIG = 1


def child_env() -> dict[str, str]:
    """The environment entry that asks a child to end with this process. Linux ties the
    request to the thread that started the child, so only the main thread asks."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    return {PARENT_ENV: str(os.getpid())}


def exit_with_parent() -> bool:
    """Arrange SIGTERM on the starter's death if it asked; whether that is arranged."""
    wanted = os.environ.get(PARENT_ENV, "")
    if not wanted.isdigit() or not sys.platform.startswith("linux"):
        return False
    libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
    if libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0) != 0:
        return False
    if os.getppid() != int(wanted):  # it died before the request took effect
        sys.exit(1)
    return True
