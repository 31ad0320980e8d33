"""bench/decide_speed.py --parts rebuilds the observation as the env builds it (its base, then the guide's features)
to time each part; it checks that it still does, so a change to the env that the bench does not follow stops it.
This runs it on EX104 (the default model) and ra01 (with tools), alone and against a baseline revision, and checks
the split it reports; and --solve's report of whole solves."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("sb3_contrib")

REPO = Path(__file__).resolve().parents[1]


def test_decide_speed_parts_splits_the_run_and_follows_the_env(tmp_path: Path) -> None:
    out = tmp_path / "parts.json"
    res = subprocess.run([sys.executable, str(REPO / "bench" / "decide_speed.py"), "--parts", "--instances", "EX104",
                          "ra01", "--repeat", "1", "--json", str(out)], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr
    rows = json.loads(out.read_text())["rows"]
    assert [r["instance"] for r in rows] == ["EX104", "ra01"]
    for r in rows:
        assert r["model"] == "guided-dagger" and r["decisions"] > 20 and r["makespan"] > 0
        assert all(r[part] > 0 for part in ("net", "observation", "guide", "actor"))
    # against a baseline (here the checkout's own commit, in a temporary worktree): both replays, each part's ratio
    res = subprocess.run([sys.executable, str(REPO / "bench" / "decide_speed.py"), "--parts", "--instances", "EX104",
                          "--repeat", "1", "--baseline", "HEAD", "--json", str(out)], capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr
    (row,) = json.loads(out.read_text())["rows"]
    assert set(row["baseline"]) == {"net", "observation", "guide", "actor"} and all(row["baseline"].values())
    assert "baseline: net " in res.stdout
    res = subprocess.run([sys.executable, str(REPO / "bench" / "decide_speed.py"), "--parts", "--solve"],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode != 0 and "give one of --parts and --solve" in res.stderr


def test_decide_speed_solve_reports_the_plan_searchs_share(tmp_path: Path) -> None:
    """--solve times whole solves as fms solve does, and says how much of each was the plan search at the start."""
    out = tmp_path / "solve.json"
    res = subprocess.run([sys.executable, str(REPO / "bench" / "decide_speed.py"), "--solve", "--instances", "EX104",
                          "--repeat", "2", "--json", str(out)], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr
    (row,) = json.loads(out.read_text())["rows"]
    assert len(row["seconds"]) == len(row["search_seconds"]) == 2
    assert all(0 < s < t for s, t in zip(row["search_seconds"], row["seconds"]))
    if "search_beside" in row:  # the search ran on the other core (fms_dispatch.rl.beside): what came of each
        assert len(row["search_beside"]) == 2 and set(row["search_beside"]) <= {"kept", "restarted"}
        assert "s beside the run; the run went on in " in res.stdout
    else:
        assert "s of it the plan search" in res.stdout
