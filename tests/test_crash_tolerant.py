"""The suite's xdist scheduler (tests/crash_tolerant.py): a worker that crashes has its test
re-run, an ordinary failure is not re-run, and the run ends instead of hanging."""

import subprocess
import sys
import textwrap
from pathlib import Path

HERE = Path(__file__).resolve().parent
RUN_TIMEOUT_S = 120  # a hang (the scheduler waiting on a worker forever) fails here

CONFTEST = f"""
import sys
sys.path.insert(0, {str(HERE)!r})
from crash_tolerant import pytest_xdist_make_scheduler  # noqa: F401
"""

# `crash_once` segfaults the first time it runs (a marker file remembers), like a rare
# native crash; `always` segfaults every time; `fails` is an ordinary failure.
CRASH_ONCE = """
import os, pathlib
def test_before():
    pass
def test_crash_once():
    marker = pathlib.Path(os.environ["CRASH_MARKER"])
    if not marker.exists():
        marker.touch()
        os.kill(os.getpid(), 11)
def test_after():
    pass
"""
FILLER = """
import time
def test_a():
    time.sleep(0.2)
def test_b():
    pass
"""


def _run(tmp_path, files):
    (tmp_path / "conftest.py").write_text(CONFTEST)
    for name, text in files.items():
        (tmp_path / name).write_text(textwrap.dedent(text))
    command = [sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-q", "-n", "2"]
    command += ["--dist", "loadfile", "--reruns", "2", "--only-rerun", "crashed while running"]
    env = {"CRASH_MARKER": str(tmp_path / "crashed"), "PATH": "/usr/bin:/bin"}
    run = subprocess.run(
        command,
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=RUN_TIMEOUT_S,
        check=False,
    )
    return run.returncode, run.stdout.strip().splitlines()[-1]


def test_a_crashed_worker_has_its_test_rerun_and_the_run_passes(tmp_path):
    files = {"test_0crash.py": CRASH_ONCE, **{f"test_{k}.py": FILLER for k in range(1, 4)}}
    code, summary = _run(tmp_path, files)
    assert code == 0, summary
    assert "9 passed, 1 rerun" in summary


def test_a_test_that_always_crashes_fails_and_a_failure_is_not_rerun(tmp_path):
    files = {
        "test_0always.py": "import os\ndef test_always():\n    os.kill(os.getpid(), 11)\n",
        "test_1fails.py": "def test_fails():\n    assert 1 == 2\n",
        **{f"test_{k}.py": FILLER for k in range(2, 4)},
    }
    code, summary = _run(tmp_path, files)
    assert code == 1, summary
    assert "2 failed, 4 passed, 2 rerun" in summary
