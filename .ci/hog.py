#!/usr/bin/env python3
"""Run a command beside a CPU hog: ``--load N`` busy processes at normal priority for as
long as the command runs (docs/development.md, timing-sensitive tests).

The suite must pass on a machine whose cores are all taken by something else, as CI's
shared runners are: ``python3 .ci/hog.py --load 2 -- bash .ci/run`` proves it on a 2-core
machine. The hogs spin in pure Python (one core each, no memory, no I/O) and end with the
command, whose exit status is this script's.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import signal
import subprocess
import sys
import time


def spin() -> None:
    """Burn one core until killed."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C goes to the command, we follow
    x = 0
    while True:
        x = (x * 1103515245 + 12345) & 0x7FFFFFFF


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--load", type=int, default=os.cpu_count() or 1, metavar="N",
                        help="busy processes beside the command (default: one per core)")
    parser.add_argument("command", nargs=argparse.REMAINDER,
                        help="the command to run, after --")
    args = parser.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        parser.error("command: give the command to run after --")
    if args.load < 0:
        parser.error(f"--load: must be 0 or more, got {args.load}")
    fork = multiprocessing.get_context("fork")  # children of this process, as they look
    hogs = [fork.Process(target=spin, daemon=True) for _ in range(args.load)]
    for hog in hogs:
        hog.start()
    began = time.monotonic()
    print(f"hog: {args.load} busy processes beside {' '.join(command)}", file=sys.stderr)
    try:
        status = subprocess.call(command)
    except KeyboardInterrupt:
        status = 130
    finally:
        for hog in hogs:
            hog.kill()
            hog.join()
    print(f"hog: the command exited {status} after {time.monotonic() - began:.0f} s",
          file=sys.stderr)
    return status


if __name__ == "__main__":
    sys.exit(main())
