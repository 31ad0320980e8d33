"""``make test`` runs the tests on two workers (pytest-xdist); the ROS tests must still run one at a time, on one
worker (tests/conftest.py's scheduler). Checked on a small copy of the layout, as xdist's own grouping once
stopped working without a sign (pytest-xdist issue 1386)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("xdist")

TESTS = Path(__file__).parent

PROBE = """
import os, time
import pytest

@pytest.mark.parametrize("i", range(4))
def test_probe(i):
    start = time.monotonic()
    time.sleep(0.2)
    with open(os.environ["PROBE_LOG"], "a") as f:
        f.write(f"{os.path.basename(os.path.dirname(__file__))} {os.environ['PYTEST_XDIST_WORKER']} {start} {time.monotonic()}\\n")
"""


def test_the_ros_tests_share_one_worker_and_never_overlap(tmp_path: Path) -> None:
    root = tmp_path / "repo"
    for folder in ("tests/ros", "tests/fms_sim", "tests/fms_dispatch"):
        (root / folder).mkdir(parents=True)
        name = folder.split("/")[1]
        (root / folder / f"test_{name}_a.py").write_text(PROBE)
        (root / folder / f"test_{name}_b.py").write_text(PROBE)
    shutil.copy(TESTS / "conftest.py", root / "tests" / "conftest.py")
    (root / "pyproject.toml").write_text("[tool.pytest.ini_options]\ntestpaths = ['tests']\n")
    log = tmp_path / "probe.log"
    res = subprocess.run([sys.executable, "-m", "pytest", "-q", "-n", "2", "-p", "no:cacheprovider"], cwd=root,
                         env={**os.environ, "PROBE_LOG": str(log)}, capture_output=True, text=True,
                         timeout=120)
    assert res.returncode == 0, res.stdout + res.stderr
    rows = [line.split() for line in log.read_text().splitlines()]
    assert len(rows) == 24
    ros = [(w, float(a), float(b)) for folder, w, a, b in rows if folder == "ros"]
    assert len(ros) == 8 and len({w for w, _, _ in ros}) == 1          # one worker ...
    spans = sorted((a, b) for _, a, b in ros)
    assert all(b1 <= a2 for (_, b1), (a2, _) in zip(spans, spans[1:]))  # ... one at a time
    others = {w for folder, w, _, _ in rows if folder != "ros"}
    assert len(others) == 2  # the other tests go to whichever worker is free: both
