"""The daemons' heap trimming: freed memory in the middle of the heap goes back to the OS
(``snail-bench soak`` saw resident size ratchet up under steady load without it)."""

from __future__ import annotations

import sys

import pytest

from snail_common.net.heap import HeapTrimmer


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 / 2**20


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/statm")
def test_trimming_returns_freed_heap_pages():
    trimmer = HeapTrimmer(every_s=0)
    if not trimmer.available:
        pytest.skip("no malloc_trim in this C library (not glibc)")
    chunks = [bytearray(64 << 10) for _ in range(2000)]  # 125 MiB on the heap, not mmap
    kept = chunks[::10]  # live chunks all along the heap: free() alone returns nothing
    del chunks
    before = _rss_mb()
    assert trimmer.session_ended()
    assert before - _rss_mb() > 80
    assert len(kept) == 200


def test_trimming_is_rate_limited():
    trimmer = HeapTrimmer(every_s=3600)
    assert not trimmer.session_ended()  # the last trim (its creation) is recent


def test_a_daemon_process_can_keep_one_arena():
    """glibc (Linux): M_ARENA_MAX is accepted, so worker threads allocate from the arena
    that malloc_trim empties; elsewhere nothing is changed and it says so."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", "from snail_common.net.heap import one_arena;"
                          "print(one_arena())"], capture_output=True, text=True, check=True)
    import platform

    glibc = platform.libc_ver()[0] == "glibc"
    assert out.stdout.strip() == str(glibc)
