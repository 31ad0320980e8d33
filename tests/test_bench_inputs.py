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
    # a second sweep (output paths, unknown names, values taken and run as something else)
    (("bu_all.py", "--json", "bench"), "argument --json: bench: is a folder; name a file"),  # after the whole run
    (("sim_cost.py", "--shops", "EX12", "EX99", "--repeat", "1"), "unknown built-in instance 'EX99'"),  # after EX12
    (("guide_follower.py", "EX12", "EX99"), "unknown built-in instance 'EX99'"),
    (("guide_lookahead.py", "--model", "guided", "--instances", "EX12", "EX99"), "unknown built-in instance 'EX99'"),
    (("asymmetric.py", "--skew", "2"), "argument --skew: a skew is a factor in (0, 1], got '2'"),
    (("asymmetric.py", "--model", "bu"), "model bu has no plan guide"),
    (("asymmetric.py", "--max-jobs", "4"), "no held-out shop has at most 4 jobs"),
    (("lookahead_speed.py", "--instances", "EX12,foo"), "unknown built-in instance 'foo'"),
    (("ros_speed.py", "--instances", "EX99", "--repeat", "1"), "unknown built-in instance 'EX99'"),  # rc 1, 2 lines
    (("cpsat_bu.py", "5", "--layout", "4", "--time-limit", "nan"), "time_limit must be a positive, finite number"),
    (("ppo_headroom.py", "--noise", "-0.5"), "--noise: a spread from 0 to 1, got -0.5"),  # ran nominal runs
    (("ppo_headroom.py", "--temperatures", "nan"), "--temperatures: positive, finite numbers, got nan"),
    (("replan.py", "--at", "-5"), "argument --at: must be >= 0, got -5"),  # reported an order never sent
    (("replan.py", "--instance", "EX12", "--at", "100000"), "the run ended after 56 states, before the order"),
    (("replan.py", "--instance", "EX12", "--breakdown", "500"), "the run ended at t=84, before the breakdown"),
    (("rl_eval.py", "sl", "--groups", "3-1"), "groups are 0..7 (LO <= HI), got '3-1'"),  # ran nothing, exit 0
    (("heldout.py", "--lookahead-max-jobs", "-1"), "argument --lookahead-max-jobs: must be >= 0, got -1"),
    (("arrivals.py", "--tabu", "0", "0"), "--tabu: each time once, got 0 0"),  # one column overwritten
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


def test_bench_json_goes_into_a_missing_folder_and_a_reference_keeps_its_cp_sat_limit(tmp_path: Path) -> None:
    out = tmp_path / "new" / "deeper" / "rows.json"  # a missing folder was an error after the whole run
    res = bench("guide_follower.py", "EX12", "--json", str(out))
    assert res.returncode == 0, res.stderr
    assert json.loads(out.read_text())[0]["instance"] == "EX12"
    ref = tmp_path / "ref.json"
    ref.write_text(json.dumps({"cpsat_seconds": 1.0, "models": [], "rows": []}))
    res = bench("heldout.py", "--models", "ppo", "--only", "ho00", "--reference", str(ref), "--cpsat", "30")
    assert res.returncode == 2 and "holds CP-SAT figures of 1.0 s" in res.stderr, res.stderr  # a mix, labelled 30


def test_guide_effort_compares_each_shop_with_its_own_list_schedule() -> None:
    """Two generated shops that differ only in their tool count share a name: one shop's list makespan served
    both (0.7721 for the list schedule against itself)."""
    res = bench("guide_effort.py", "--shops", "gen:5x3x3*1@216", "gen:5x3x1*1@216", "--efforts", "0")
    assert res.returncode == 0, res.stderr
    assert "plan 1.0000" in res.stdout and "guided 1.0000" in res.stdout, res.stdout


def test_sl_summary_compares_means_over_the_same_instances(tmp_path: Path) -> None:
    """PPO failed on the larger instance: its mean over the smaller one alone was compared with the rules' mean
    over both (-80 % and a 'yes')."""
    rows = []
    for inst, lb, ppo, rule in (("sl00", 100, 110, 120), ("sl01", 1000, None, 1050)):
        base = {"benchmark": "sl", "instance": inst, "variant": "agvs", "wall_time": 1.0, "reference": None}
        rows += [dict(base, method="cpsat", makespan=lb, lower_bound=lb, valid=True, time_limit=10.0),
                 dict(base, method="ppo", makespan=ppo, lower_bound=None, valid=ppo is not None),
                 dict(base, method="rule:A+first", makespan=rule, lower_bound=None, valid=True)]
    path = tmp_path / "sl.json"
    path.write_text(json.dumps({"rows": rows}))
    res = bench("sl_summary.py", str(path))
    assert res.returncode == 0, res.stderr
    row = next(line for line in res.stdout.splitlines() if line.startswith("| 0 "))
    assert "| +10.0 % | +20.0 % | yes, over 1 (-8.3 %) |" in row, row


def test_heldout_records_metrics_in_a_model_folder_without_them(tmp_path: Path) -> None:
    import importlib.util
    import shutil

    folder = tmp_path / "mbu"
    folder.mkdir()
    for name in ("config.json", "model.zip", "model.actor.npz"):
        shutil.copy(REPO / "models" / "bu" / name, folder / name)
    sys.path.insert(0, str(REPO / "bench"))
    try:
        spec = importlib.util.spec_from_file_location("heldout_bench", REPO / "bench" / "heldout.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
    finally:
        sys.path.remove(str(REPO / "bench"))
    label = f"ppo:{folder}"
    rows = [{"shop": "ho00", "cpsat": 100, "list": 110, "rule": 120, label: 105, label + "_model": str(folder)}]
    mod.write_metrics(rows, [label], "python bench/heldout.py ...")  # a missing metrics.json was an error
    entry = json.loads((folder / "metrics.json").read_text())["heldout"]
    assert entry["shops"]["ho00"] == {"cpsat": 100, "list": 110, "rule": 120, "ppo": 105}
    assert entry["mean_gap_to_cpsat_ppo"] == 5.0


def test_decide_speed_runs_a_shop_file_named_from_the_users_folder(tmp_path: Path) -> None:
    """A path was cut at its first '/' (the '/notools' suffix), and the workers ran in the repository's root."""
    from fms_sim.benchmarks import builtin

    builtin("EX12").save(tmp_path / "shop.json")
    res = subprocess.run([sys.executable, str(REPO / "bench" / "decide_speed.py"), "--instances", "shop.json",
                          str(tmp_path / "shop.json") + "/notools", "--repeat", "1"], capture_output=True, text=True,
                         timeout=300, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    shop = tmp_path / "shop.json"
    assert lines[1].startswith(f"{shop}: ") and lines[2].startswith(f"{shop}/notools: "), res.stdout


def test_asymmetric_runs_the_model_and_its_expert_on_one_way_travel(tmp_path: Path) -> None:
    """bench/asymmetric.py on its five smallest shops, the travel as it is and one-way cheap: every row has the three
    makespans, and with the travel as it is the model decides as its expert (docs/benchmarks.md §9)."""
    pytest.importorskip("sb3_contrib")
    out = tmp_path / "a.json"
    res = bench("asymmetric.py", "--max-jobs", "5", "--skew", "1", "0.5", "--json", str(out), timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr
    rows = json.loads(out.read_text())["rows"]
    assert len(rows) == 10 and all(r["follower"] > 0 and r["model"] > 0 and r["list"] > 0 for r in rows)
    assert all(r["model"] == r["follower"] for r in rows if r["skew"] == 1)
    assert "skew 0.5: model" in res.stdout
