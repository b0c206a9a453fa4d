"""tools/setup_env.sh is quiet: one line per stage, pip's output in .venv/setup.log, and on a
failure the log's last lines and its path (run on a copy with a stub Python, no network)."""

from __future__ import annotations

import os
import shutil
import stat
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
NOISE = 176  # lines of setuptools warnings a pip install printed before

STUB_PYTHON = f"""#!/usr/bin/env bash
if [ "$1" = "-m" ] && [ "$2" = "pip" ]; then
  for i in $(seq 1 {NOISE}); do echo "WARNING: setuptools noise $i" >&2; done
  if [ -n "${{FAIL_INSTALL:-}}" ] && [[ "$*" == *" -e "* ]]; then
    echo "ERROR: No matching distribution found for gtsam>=4.2" >&2
    exit 1
  fi
fi
exit 0
"""


def _executable(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    path.chmod(path.stat().st_mode | stat.S_IXUSR)


@pytest.fixture
def tree(tmp_path):
    """A copy of the script beside a .venv whose python is a stub, and an ldconfig that finds the
    system libraries (so apt is never called)."""
    (tmp_path / "tools").mkdir()
    shutil.copy(REPO / "tools" / "setup_env.sh", tmp_path / "tools" / "setup_env.sh")
    _executable(tmp_path / ".venv" / "bin" / "python", STUB_PYTHON)
    _executable(
        tmp_path / "bin" / "ldconfig", "#!/bin/sh\necho 'libusb-1.0.so.0 => x'; echo 'libgomp.so.1 => x'\n"
    )
    env = {**os.environ, "PATH": f"{tmp_path / 'bin'}:{os.environ['PATH']}"}
    return tmp_path, env


def test_setup_prints_one_line_per_stage_and_logs_pip(tree):
    root, env = tree
    done = subprocess.run(["bash", "tools/setup_env.sh"], cwd=root, env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert 3 <= len(lines) <= 6 and all(x.startswith("setup: ") for x in lines), done.stdout
    assert done.stderr == ""
    log = (root / ".venv" / "setup.log").read_text()
    assert log.count("WARNING: setuptools noise") == 2 * NOISE


def test_setup_failure_shows_the_logs_tail_and_path(tree):
    root, env = tree
    env["FAIL_INSTALL"] = "1"
    done = subprocess.run(["bash", "tools/setup_env.sh"], cwd=root, env=env, capture_output=True, text=True)
    assert done.returncode != 0
    assert "installing frslam failed" in done.stderr
    assert "No matching distribution found for gtsam" in done.stderr
    assert str(root / ".venv" / "setup.log") in done.stderr
    assert len(done.stderr.splitlines()) <= 30 and "WARNING" not in done.stdout
