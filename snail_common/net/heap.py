"""Hand freed memory back to the OS, so a daemon's resident size follows its load.

A daemon's sessions allocate and free many MiB-sized buffers (table frames, label
arrays). glibc's malloc keeps freed heap pages mapped, and after a burst of concurrent
sessions the resident size stays at that peak for good: ``snail-bench soak`` saw both
daemons grow by a third over ten minutes of steady load. ``malloc_trim(0)`` returns every
free page, also from the middle of the heap (glibc >= 2.8). Elsewhere (musl, macOS) this
does nothing.

It did not reach the worker threads' own arenas: after a fleet of 16 clients the
evaluator kept 40 MB resident in its two workers' arenas for good (118 MB at rest before,
148 MB after, idle and trimmed). A daemon therefore keeps one arena for all its threads
(``M_ARENA_MAX`` 1, set before any worker starts): with it, 124 MB before and 126 MB
after two such fleets, the garbler 159 and 160 MB. Its threads allocate little per frame
(the engines' buffers live for a run), so the one lock costs nothing measurable.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import time

TRIM_EVERY_S = 2.0  # at most this often under load; it takes a few ms on a large heap


M_ARENA_MAX = -8  # glibc's mallopt parameter


def _libc_function(name: str) -> ctypes._CFuncPtr | None:
    library = ctypes.util.find_library("c")
    try:
        return getattr(ctypes.CDLL(library), name) if library else None
    except (OSError, AttributeError):
        return None


def one_arena() -> bool:
    """Make every thread started from now on allocate from the main arena (glibc), so
    that ``malloc_trim`` returns all freed memory; whether it could."""
    mallopt = _libc_function("mallopt")
    return mallopt is not None and bool(mallopt(M_ARENA_MAX, 1))


class HeapTrimmer:
    """Calls ``malloc_trim`` as sessions end, at most every ``every_s`` (a single client's
    run of short invocations pays for it once in many)."""

    def __init__(self, every_s: float = TRIM_EVERY_S) -> None:
        self._trim = _libc_function("malloc_trim")
        self._every_s = every_s
        self._last = time.monotonic()

    @property
    def available(self) -> bool:
        return self._trim is not None

    def session_ended(self) -> bool:
        """A session ended: trim if the last trim is ``every_s`` old; whether it did."""
        if time.monotonic() - self._last < self._every_s:
            return False
        return self.trim()

    def trim(self) -> bool:
        """Trim now (the daemon has gone idle: the last session's pages too); whether
        there is a trim to call."""
        if self._trim is None:
            return False
        self._last = time.monotonic()
        self._trim(0)
        return True
