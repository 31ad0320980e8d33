"""The bench scripts refuse bad input with one line and exit code 2 (``checks.run_main``, argparse), before any
work; and the fixes a smoke run of every script asked for (a sweep of bench/ on its smallest inputs)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def bench(*argv: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(REPO / "bench" / argv[0]), *argv[1:]], capture_output=True, text=True,
                          timeout=timeout, cwd=REPO)


@pytest.mark.parametrize("argv, needle", [
    (("cpsat_bu.py", "11"), "job sets are 1..10, got 11"),  # it asked for instance EX112
    (("cpsat_bu.py", "1", "--workers", "0"), "--workers: must be >= 1"),
    (("decide_speed.py", "--instances", "EX12", "--baseline", "no-such-revision"),
     "--baseline no-such-revision: fatal: invalid reference"),  # a traceback of git worktree add
    (("decide_speed.py", "--instances", "EX99", "--repeat", "1"), "unknown built-in instance 'EX99'"),  # two lines, rc 1
    (("decide_speed.py", "--repeat", "0"), "--repeat: must be >= 1"),
    (("replan_tabu.py", "--seeds", "0"), "--seeds: must be >= 1"),  # ZeroDivisionError after the CP-SAT plans
    (("ppo_headroom.py", "--seeds", "0"), "--seeds: must be >= 1"),
    (("heldout.py", "--limit", "1", "--write-metrics"), "cannot be combined with --only or --limit"),  # it cut 50 to 1
    (("validation.py", "--models", "ppo", "--lookahead-guide"), "--lookahead-guide chooses the lookahead"),
    (("rl_eval.py", "sl", "--per-group", "11"), "--per-group: a group has 10 instances"),  # after 14 s of rules
    (("plan_live.py", "--skip", "10"), "--skip must be 0..9"),  # an empty table, exit 0
    (("guide_replan.py", "--drifts", "abc"), "--drifts: expected a number or none, got 'abc'"),
    (("guide_effort.py", "--efforts", "8+foo"), "bad effort '8+foo'"),  # exit 1
    (("sim_cost.py", "--share", "2"), "--share must be in [0, 1)"),  # exit 1
    (("make_replay_data.py", "--only", "nomatch*"), "--only 'nomatch*' matches no file"),  # exit 0, nothing said
    (("guide_replan.py", "--replan-margins", "0.01"), "give --replan-tabu too"),  # ignored
    (("heldout.py", "--models", "ppo:no-such-model", "--limit", "1"), "no model named 'no-such-model'"),  # after CP-SAT
    (("validation.py", "--models", "ppo:guided+lookahead-guide"), "give model names without a lookahead"),
])
def test_bad_input_is_one_line_and_exit_2(argv: tuple[str, ...], needle: str) -> None:
    res = bench(*argv)
    assert res.returncode == 2, res.stdout + res.stderr
    lines = res.stderr.strip().splitlines()
    assert needle in lines[-1] and "Traceback" not in res.stderr, res.stderr  # (argparse prints its usage first)
    assert len(lines) == 1 or lines[0].startswith("usage:"), res.stderr
    assert not res.stdout.strip() or argv[0] == "decide_speed.py"  # no work was done (decide_speed: its header)


def test_sl_summary_names_a_file_it_cannot_read(tmp_path: Path) -> None:
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"rows": [{"shop": "ho00"}]}))  # a traceback: KeyError 'variant'
    res = bench("sl_summary.py", str(other))
    assert res.returncode == 2 and f"{other} is not the output of fms bench sl" in res.stderr
    other.write_text("not json")
    res = bench("sl_summary.py", str(other))
    assert res.returncode == 2 and f"{other} is not JSON" in res.stderr


def test_validation_runs_the_default_model_with_its_guide_lookahead(tmp_path: Path) -> None:
    """``--models ppo`` (no model name) with ``--lookahead-guide`` failed on ``spec.split(':')[1]``; the summary is
    written into a folder that did not exist (it failed after the work)."""
    pytest.importorskip("sb3_contrib")
    out = tmp_path / "new" / "v.json"
    res = bench("validation.py", "--models", "ppo", "--shops", "gen:10x5x5*1@216", "--lookahead", "--lookahead-guide",
                "--json", str(out), timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr
    (row,) = json.loads(out.read_text())["rows"]
    assert row["ppo"] > 0 and row["ppo+la"] > 0 and row["ppo"] <= row["list"] * 1.5


def test_replan_says_when_the_run_ended_before_its_re_plan() -> None:
    """It printed '0 re-plans' and '69 states answered while a re-plan ran' side by side."""
    pytest.importorskip("sb3_contrib")
    res = bench("replan.py", "--instance", "EX12", "--at", "10", "--jobs", "1", "--budget", "0.5", timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "0 re-plans" not in res.stdout or "one more still running when the run ended" in res.stdout, res.stdout


def _row(inst: str, method: str, makespan: int, time_limit: float | None = None, variant: str = "agvs") -> dict:
    return {"benchmark": "sl", "instance": inst, "variant": variant, "method": method, "time_limit": time_limit,
            "seed": 0, "makespan": makespan, "valid": True, "lower_bound": 90 if method == "cpsat" else None,
            "wall_time": 1.0}


def test_sl_summary_titles_cp_sat_with_the_limit_of_its_runs(tmp_path: Path) -> None:
    rows = [_row("sl00", "cpsat", 100, 60.0), _row("sl00", "ppo", 110), _row("sl00", "rule:SPT+first", 120)]
    path = tmp_path / "bench_sl.json"
    path.write_text(json.dumps({"rows": rows}))
    res = bench("sl_summary.py", str(path))
    assert res.returncode == 0, res.stderr
    assert "| CP-SAT (60 s) |" in res.stdout and "10 s" not in res.stdout  # it said "CP-SAT (10 s)" whatever ran


def test_decisions_summary_reads_cp_sat_at_its_own_limit(tmp_path: Path) -> None:
    rows = [_row("sl00", m, v) for m, v in (("rules:paper", 130), ("rules:full", 121), ("list", 125))]
    rows += [_row("sl00", "cpsat", 110, 10.0), _row("sl00", "cpsat", 100, 60.0)]  # the 60-s run came later
    (tmp_path / "bench_cache.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    res = bench("decisions.py", "--summary", "--results-dir", str(tmp_path))
    assert res.returncode == 0, res.stderr
    line = next(x for x in res.stdout.splitlines() if x.startswith("| sl group 0"))
    assert "| +10.0 % |" in line and "cpsat 10 s" in line  # rules:full against the 10-s run, not the 60-s one
    assert "1 cached CP-SAT runs with a limit other than 10 s left out" in res.stdout


def test_full_ppo_sl_takes_cp_sat_at_the_goals_limit(tmp_path: Path) -> None:
    cache = tmp_path / "bench_cache.jsonl"
    cache.write_text("".join(json.dumps(r) + "\n" for r in (_row("sl00", "cpsat", 110, 10.0),
                                                            _row("sl00", "cpsat", 100, 60.0))))
    code = ("import sys; sys.path.insert(0, 'bench'); from full_ppo_sl import references; "
            f"print(references({str(cache)!r}))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "{('sl00', 'agvs', 'cpsat'): 110}"
    assert "1 cached CP-SAT runs with a limit other than 10 s left out" in res.stderr
