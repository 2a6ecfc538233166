"""The pose-graph PCM tests (``tests/posegraph_pcm_cases.py``), run in a fresh interpreter.

Run inside the whole suite's process, the first PCM + GNC solve of those cases ended the
process with a segmentation fault in CI (twice, at the same test), while the same cases pass in
a process of their own and after the posegraph, GTSAM, pycolmap and π³ test files; the cause is
not found yet.  Until it is, they run here in a child interpreter, so that a crash is reported as
this test's failure with the child's output instead of ending the suite.
"""

from __future__ import annotations

import os
import pathlib
import subprocess
import sys

import pytest

pytestmark = pytest.mark.slow

HERE = pathlib.Path(__file__).resolve().parent


def test_pcm_cases_pass_in_a_fresh_interpreter(shared_dir):
    env = {**os.environ, "SWIFTJAX_SHARED": str(shared_dir)}
    cmd = [
        sys.executable,
        "-X",
        "faulthandler",
        "-m",
        "pytest",
        str(HERE / "posegraph_pcm_cases.py"),
        "-q",
        "-p",
        "no:cacheprovider",
        "-o",
        "python_files=posegraph_pcm_cases.py",
    ]
    proc = subprocess.run(cmd, cwd=HERE.parent, env=env, capture_output=True, text=True, timeout=1200)
    assert proc.returncode == 0, f"exit {proc.returncode}\n{proc.stdout[-6000:]}\n{proc.stderr[-4000:]}"
    assert " passed" in proc.stdout and "failed" not in proc.stdout, proc.stdout[-2000:]
