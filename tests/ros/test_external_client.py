"""The external client of docs/ros.md ("External clients: joining a run late"), run exactly as written there:
started while a run is under way, with nobody else asking for replays, it gets every event of the run."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

pytest.importorskip("rclpy")

from fms_sim.schedule import Schedule  # noqa: E402

from .conftest import RUN_S, STARTUP_S, NodeProcs, Observer, wait_file  # noqa: E402

DOCS = Path(__file__).resolve().parents[2] / "docs" / "ros.md"


def doc_client() -> str:
    section = DOCS.read_text().split("### External clients: joining a run late", 1)[1]
    return re.search(r"```python\n(.*?)```", section, flags=re.S).group(1)


def test_the_documented_client_joins_mid_run_and_gets_the_whole_run(nodes: NodeProcs, observer: Observer,
                                                                     tmp_path: Path) -> None:
    script = tmp_path / "follow_run.py"
    script.write_text(doc_client())
    out = tmp_path / "EX12.schedule.json"
    nodes.start("shop", "fms_sim.shop_node", instance="EX12", run_id="late", schedule_out=out)
    nodes.start("agent", "fms_dispatch.agent_node", solver="rule:SPT+least-work", delay_s=0.1)
    observer.wait_for(lambda g: any(s["seq"] >= 8 for s in g["state"]), STARTUP_S, "state 8")  # well under way
    client = nodes.start("client", [sys.executable, str(script)])
    assert client.wait(STARTUP_S + RUN_S) == 0, nodes.log("client")
    line = nodes.log("client").strip().splitlines()[-1]
    found = re.fullmatch(r"run late: joined at state (\d+); (\d+) events from run_start to run_end at time (\d+)",
                         line)
    assert found, nodes.log("client")
    joined_at, n_events, end_time = map(int, found.groups())
    sched = Schedule.load(wait_file(out, RUN_S, nodes))
    assert joined_at >= 8 and end_time == sched.makespan
    # one event per start and end of each operation and trip, plus run_start and run_end
    trips = len(sched.operations) + len(sched.agv_trips) + len(sched.tool_trips)
    assert n_events == 2 * trips + 2
