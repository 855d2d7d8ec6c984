"""pavemap.shutdown: the quick exit must not lose what a process wrote."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

CHILD = r"""
import sys
from pavemap.shutdown import prepare_quick_exit

log = open(sys.argv[1], "w")  # buffered, never closed: the interpreter's exit flushes it
log.write("written before the exit\n")
state = {"log": log, "big": [list(range(100)) for _ in range(10_000)]}
prepare_quick_exit()
print("done")
"""


def test_quick_exit_still_flushes_a_file_left_open(tmp_path: Path) -> None:
    out = tmp_path / "left-open.txt"
    p = subprocess.run([sys.executable, "-c", CHILD, str(out)], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == "done"
    assert out.read_text() == "written before the exit\n"


def test_cli_exit_status_survives_the_quick_exit(tmp_path: Path) -> None:
    p = subprocess.run([sys.executable, "-m", "pavemap.cli", "no-such-command"], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 2, (p.returncode, p.stderr)
