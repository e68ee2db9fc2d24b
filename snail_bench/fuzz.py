"""``snail-bench fuzz``: coverage-guided fuzzing of the parsers in fuzz_targets.py with
atheris (libFuzzer for Python; ``pip install 'snail[fuzz]'``).

Each target runs in a process of its own (libFuzzer exits the process when it is done),
from a corpus seeded with valid inputs, under a per-input time limit and a memory limit:
a crash, a hang or an allocation past the limit ends the run with the input that caused
it saved in the corpus folder. ``python -m snail_bench.fuzz TARGET [libFuzzer flags]``
is that process.
"""

from __future__ import annotations

import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

INPUT_TIMEOUT_S = 5
RSS_LIMIT_MB = 1024
_DONE = re.compile(rb"Done (\d+) runs in (\d+) second")


def fuzz(target: str, runs: int, seconds: int, corpus: Path | None = None) -> dict:
    """Fuzz ``target`` for ``runs`` inputs or ``seconds``, whichever ends first."""
    from .fuzz_targets import TARGETS, seeds

    if target not in TARGETS:
        raise ValueError(f"target: expected one of {', '.join(TARGETS)}, got {target!r}")
    with tempfile.TemporaryDirectory(prefix="snail-fuzz-") as scratch:
        folder = corpus or Path(scratch) / "corpus"
        folder.mkdir(parents=True, exist_ok=True)
        for k, seed in enumerate(seeds(target)):
            (folder / f"seed-{k}").write_bytes(seed)
        artifacts = (corpus or Path(scratch)) / "crashes"
        artifacts.mkdir(exist_ok=True)
        start = time.monotonic()
        done = subprocess.run(
            [sys.executable, "-m", "snail_bench.fuzz", target, f"-runs={runs}",
             f"-max_total_time={seconds}", f"-timeout={INPUT_TIMEOUT_S}",
             f"-rss_limit_mb={RSS_LIMIT_MB}", "-print_final_stats=1",
             f"-artifact_prefix={artifacts}/", str(folder)],
            capture_output=True, check=False)
        wall = time.monotonic() - start
        found = _DONE.search(done.stderr)
        crashes = sorted(p.name for p in artifacts.iterdir())
        report = {"runs": int(found[1]) if found else None, "seconds": round(wall, 1),
                  "ok": done.returncode == 0 and not crashes, "exit": done.returncode,
                  "findings": crashes}
        if not report["ok"]:
            report["log_tail"] = done.stderr.decode(errors="replace")[-2000:]
        return report


def _main(argv: list[str]) -> None:
    import atheris

    with atheris.instrument_imports(include=["snail_common", "snail_client", "snail_bench"]):
        from snail_bench.fuzz_targets import TARGETS

    target = TARGETS[argv[1]]
    atheris.Setup([argv[0], *argv[2:]], target)
    atheris.Fuzz()


if __name__ == "__main__":
    _main(sys.argv)
