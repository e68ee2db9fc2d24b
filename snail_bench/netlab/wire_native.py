"""The lab's wire as a small C program (``wire.c``), compiled on first use.

The Python wire (``wire.py``) spends about half of its CPU per forwarded frame in the
interpreter, on a machine whose cores the garbler and the evaluator already fill, so a
zero-delay run through it came out slower than the direct one. ``wire.c`` does the same
job with batched system calls. It is built once per source version with the system's C
compiler into the snail cache folder; where no compiler works the lab falls back to the
Python wire and says so (``"forwarder": "python"`` in the netem JSON, a line on stderr).
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from snail_common.circuit.cache import cache_dir

SOURCE = Path(__file__).with_name("wire.c")
CFLAGS = ("-O2", "-Wall", "-Wextra")


class NoNativeWire(Exception):
    """The C wire cannot be built here (the message says why)."""


def native_wire(folder: Path | None = None) -> Path:
    """The built C wire (compiled now if this source version has no binary yet);
    NoNativeWire if it cannot be built."""
    source = SOURCE.read_bytes()
    tag = hashlib.sha256(source + " ".join(CFLAGS).encode()).hexdigest()[:12]
    target = (folder or cache_dir() / "netlab") / f"wire-{tag}"
    if target.exists():
        return target
    compiler = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if compiler is None:
        raise NoNativeWire("no C compiler (cc, gcc or $CC) to build the lab's C wire")
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
        out = Path(tmp) / "wire"
        proc = subprocess.run([compiler, *CFLAGS, "-o", str(out), str(SOURCE)],
                              capture_output=True, text=True)
        if proc.returncode != 0:
            detail = (proc.stderr.strip().splitlines() or [f"exit {proc.returncode}"])[0]
            raise NoNativeWire(f"{compiler} could not build {SOURCE.name}: {detail}")
        os.replace(out, target)  # atomic: a concurrent build leaves one whole binary
    return target


def wire_command(prefer_native: bool = True) -> tuple[list[str], str]:
    """The forwarder's command (``--link`` arguments follow) and its kind, "native" or
    "python"; the fallback to Python is said on stderr."""
    if prefer_native:
        try:
            return [str(native_wire())], "native"
        except (NoNativeWire, OSError) as exc:
            print(f"netlab: using the Python wire (slower, its CPU shows in the control "
                  f"run): {exc}", file=sys.stderr)
    return [sys.executable, "-m", "snail_bench.netlab.wire"], "python"
