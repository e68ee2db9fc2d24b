"""``.ci/hog.py`` (docs/development.md): the command runs beside the busy processes, its exit
status is the hog's, and the hogs end with it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

HOG = Path(__file__).resolve().parent.parent / ".ci" / "hog.py"


def test_the_command_runs_beside_the_hogs_and_its_status_is_returned():
    # the command sees the hogs: more processes of the hog's than itself are running
    count = ("import os, sys; me = os.getppid(); kids = [p for p in os.listdir('/proc') "
             "if p.isdigit() and open(f'/proc/{p}/stat').read().split()[3] == str(me)]; "
             "sys.exit(len(kids))")
    proc = subprocess.run([sys.executable, str(HOG), "--load", "2", "--", sys.executable,
                           "-c", count], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 3, proc.stderr  # two hogs and the command itself
    assert "hog: 2 busy processes" in proc.stderr and "exited 3" in proc.stderr


def test_no_command_is_a_usage_error_that_says_so():
    proc = subprocess.run([sys.executable, str(HOG), "--load", "1"], capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 2 and "command" in proc.stderr
