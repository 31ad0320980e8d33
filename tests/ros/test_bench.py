"""bench/ros_speed.py runs its ``fms up`` on the ROS domain ``ROS_DOMAIN_ID`` names (it used to drop the
variable and run on a random domain whatever the environment said); without it each run gets its own."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("rclpy")

REPO = Path(__file__).resolve().parents[2]


def ros_speed(env: dict[str, str]) -> list[str]:
    """The domains of two EX12 runs, as the benchmark reports them (from fms up's own start line)."""
    res = subprocess.run([sys.executable, str(REPO / "bench" / "ros_speed.py"), "--instances", "EX12", "--repeat",
                          "2", "--solver", "first"], env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr
    header, columns, row = res.stdout.splitlines()
    assert columns.endswith("ROS domains") and row.split()[0] == "EX12"
    return row.split()[-1].split(",")


def test_ros_speed_uses_the_given_domain(ros_env: dict[str, str]) -> None:
    assert ros_speed(ros_env) == [ros_env["ROS_DOMAIN_ID"]] * 2


def test_ros_speed_without_a_domain_uses_a_random_one_per_run(ros_env: dict[str, str],
                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("ROS_DOMAIN_ID")
    domains = ros_speed(dict(os.environ))
    assert len(domains) == 2 and all(1 <= int(d) <= 101 for d in domains)


def test_ros_speed_runs_a_solver_that_re_plans(ros_env: dict[str, str]) -> None:
    """``plan:list`` makes fms up add to its start line after the domain (the shop waits for each re-plan): the
    domain was not found, and the in-process measurement gave the agent no history (an IndexError)."""
    res = subprocess.run([sys.executable, str(REPO / "bench" / "ros_speed.py"), "--instances", "EX12", "--repeat",
                          "1", "--solver", "plan:list"], env=ros_env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr
    row = res.stdout.splitlines()[-1].split()
    assert row[0] == "EX12" and row[-1] == ros_env["ROS_DOMAIN_ID"] and int(row[-2]) > 0  # (makespan, domain)
