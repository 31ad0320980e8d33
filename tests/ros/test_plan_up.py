"""fms up with a plan solver: the agent node plans at the first state and executes the plan over the topics."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("rclpy")

from fms_sim import validate  # noqa: E402
from fms_sim.benchmarks import builtin  # noqa: E402
from fms_sim.schedule import Schedule  # noqa: E402


def test_fms_up_executes_a_cpsat_plan_at_the_optimum(ros_env: dict[str, str], tmp_path: Path) -> None:
    out, db = tmp_path / "EX12.json", tmp_path / "fms.sqlite"
    res = subprocess.run([sys.executable, "-m", "fms_dispatch.up", "EX12", "--solver", "plan:cpsat:10", "--out",
                          str(out), "--db", str(db), "--run-id", "up-plan", "--domain-id", ros_env["ROS_DOMAIN_ID"],
                          "--log-dir", str(tmp_path / "logs")],
                         env=ros_env, capture_output=True, text=True, timeout=180)
    assert res.returncode == 0, res.stderr + res.stdout
    inst = builtin("EX12")
    sched = Schedule.load(out)
    assert validate(inst, sched) == [] and sched.makespan == inst.meta["optimal_makespan"] == 82
    assert sched.meta["solver"] == "plan:cpsat:10"
    assert res.stdout.startswith("EX12: makespan 82 (plan:cpsat:10 over ROS 2 topics")
    assert "did not stop cleanly" not in res.stderr  # CP-SAT leaves SIGINT to the node
    for name in ("shop", "agent", "recorder"):
        assert "Traceback" not in (tmp_path / "logs" / f"{name}.log").read_text()
