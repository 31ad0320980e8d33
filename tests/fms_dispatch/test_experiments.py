"""``fms experiment``: each study in ``--quick`` mode writes its CSV/JSON/PNG with valid schedules."""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import pytest

from fms_dispatch.experiments import (ABLATION_COLUMNS, DYNAMIC_COLUMNS, GENERALIZATION_COLUMNS,
                                      add_experiment_parser, lower_bound, partition_jobs, run_ablation,
                                      run_dynamic, run_generalization)
from fms_sim.benchmarks import builtin
from fms_sim.instance import Instance, Operation

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _outputs(folder: Path, name: str, columns: tuple[str, ...]) -> tuple[list[dict[str, str]], dict]:
    """Read the three files of an experiment and check their shape."""
    paths = {ext: folder / f"experiment_{name}.{ext}" for ext in ("csv", "json", "png")}
    for p in paths.values():
        assert p.is_file() and p.stat().st_size > 0, p
    assert paths["png"].read_bytes()[:8] == PNG_MAGIC
    with paths["csv"].open() as fh:
        reader = csv.DictReader(fh)
        assert tuple(reader.fieldnames or ()) == columns
        rows = list(reader)
    doc = json.loads(paths["json"].read_text())
    assert doc["experiment"] == name and doc["quick"] is True
    assert len(doc["rows"]) == len(rows)
    return rows, doc


def test_partition_and_lower_bound() -> None:
    assert partition_jobs(15) == [[0, 1], [2], [3, 4], [5], [6, 7], [8], [9, 10], [11], [12, 13], [14]]
    assert partition_jobs(3, 4) == [[0], [1], [2], []]
    for bad in ((3, 0), (3, -2), (0, 4), (3, 2.0), (3, True)):  # parts=0 was an IndexError
        with pytest.raises(ValueError, match="must be an integer >= 1"):
            partition_jobs(*bad)
    inst = Instance(name="t", jobs=((Operation(1, None, 5), Operation(2, None, 4)), (Operation(1, None, 7),)),
                    n_machines=2)
    assert lower_bound(inst) == 12  # machine 1: 5 + 7
    ta = builtin("ta01")  # the larger of the busiest machine's load and the longest job's work
    load = max(sum(o.duration for job in ta.jobs for o in job if o.machine == m) for m in range(1, ta.n_machines + 1))
    assert lower_bound(ta) == max(load, max(sum(o.duration for o in job) for job in ta.jobs))
    assert lower_bound(ta) <= ta.meta["optimal_makespan"]


def test_dynamic_quick(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    doc = run_dynamic(quick=True, results_dir=tmp_path)
    rows, saved = _outputs(tmp_path, "dynamic", DYNAMIC_COLUMNS)
    assert saved["instance"] == "sl00" and saved["model"] == "guided-dagger" and saved["partitions"] == 10
    inst = builtin("sl00")
    assert saved["lower_bound"] == lower_bound(inst)
    assert [int(r["partition"]) for r in rows] == list(range(10))
    assert [int(r["jobs_so_far"]) for r in rows] == [2, 3, 5, 6, 8, 9, 11, 12, 14, 15]
    assert all(r["sos_valid"] == "True" for r in rows)
    for r in rows:  # jobs never enter before their arrival unless flagged early
        assert float(r["entered_at"]) >= float(r["arrival"]) or r["early"] == "True"
    times = [float(r["sos_time_cum"]) for r in rows]
    assert times == sorted(times) and times[-1] >= 10 * 0.2 * 0.9
    rl = [float(r["rl_time_cum"]) for r in rows]
    assert rl == sorted(rl)
    s = doc["summary"]
    assert s["rl_final_makespan"] == int(rows[-1]["rl_makespan"])  # the deterministic projection is exact
    assert s["sos_final_makespan"] == int(rows[-1]["sos_makespan"])
    assert "| partition |" in capsys.readouterr().out


def test_ablation_quick(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import tempfile

    scratch = tmp_path / "tmp"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    doc = run_ablation(quick=True, results_dir=tmp_path, steps=64, echo=False)
    assert not list(scratch.glob("SB3-*"))  # sb3's default logger left an empty folder there per run
    rows, _ = _outputs(tmp_path, "ablation", ABLATION_COLUMNS)
    by = {(r["study"], r["variant"]) for r in rows}
    assert by == {("reward_shaping", "shaped"), ("reward_shaping", "sparse"), ("lookahead", "off"),
                  ("lookahead", "on"), ("masking", "masked"), ("masking", "unmasked")}
    shaping = [r for r in rows if r["study"] == "reward_shaping"]
    assert sorted(r["instance"] for r in shaping) == ["sl40", "sl40", "sl41", "sl41"]
    assert all(r["valid"] == "True" and int(r["makespan"]) > 0 for r in shaping)
    look = [r for r in rows if r["study"] == "lookahead"]
    assert sorted(r["instance"] for r in look) == ["EX12", "EX12", "EX22", "EX22"]
    assert all(r["valid"] == "True" for r in look)
    off = {r["instance"]: int(r["makespan"]) for r in look if r["variant"] == "off"}
    from fms_dispatch.rl import ppo_solver

    assert off["EX12"] == ppo_solver("ppo:bu")(builtin("EX12")).makespan
    curve = [r for r in rows if r["study"] == "masking"]
    masked = [r for r in curve if r["variant"] == "masked"]
    unmasked = [r for r in curve if r["variant"] == "unmasked"]
    assert len(masked) >= 2 and len(unmasked) >= 2
    assert all(int(r["invalid_episodes"]) == 0 for r in masked)  # masks never let an invalid action through
    assert sum(int(r["invalid_episodes"]) for r in unmasked) > 0
    steps = [int(r["timesteps"]) for r in masked]
    assert steps == sorted(steps)
    assert set(doc["summary"]) == {"reward_shaping", "lookahead", "masking"}


def test_ablation_only_lookahead(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    doc = run_ablation(quick=True, results_dir=tmp_path, studies=["lookahead"])
    out = capsys.readouterr().out  # the printed table names the study's model and its lookahead
    assert f"| lookahead (bu: verified twin) | off | mean makespan {doc['summary']['lookahead']['off']} |" in out
    rows, _ = _outputs(tmp_path, "ablation", ABLATION_COLUMNS)
    assert {r["study"] for r in rows} == {"lookahead"} and len(rows) == 4
    assert list(doc["summary"]) == ["lookahead"] and doc["studies"] == ["lookahead"]
    with pytest.raises(ValueError, match="unknown ablation study 'typo'"):
        run_ablation(quick=True, results_dir=tmp_path, studies=["typo"], echo=False)


def test_generalization_quick(tmp_path: Path) -> None:
    doc = run_generalization(quick=True, results_dir=tmp_path, steps=32, echo=False)
    rows, _ = _outputs(tmp_path, "generalization", GENERALIZATION_COLUMNS)
    assert [(r["group"], r["agent"], r["instance"]) for r in rows] == [
        ("0", "general (large)", "sl09"), ("0", "specialized", "sl09")]
    assert all(r["valid"] == "True" and int(r["makespan"]) > 0 for r in rows)
    from fms_dispatch.rl import ppo_solver

    assert int(rows[0]["makespan"]) == ppo_solver("ppo:large")(builtin("sl09")).makespan
    assert doc["summary"]["0"]["specialized"] == float(rows[1]["makespan"])


def test_the_experiments_on_the_full_net(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The paper's experiments side by side on the full net: the shipped default model (guided) for inference by
    default, another full-net model by --model, full-net training for the trained agents; every schedule is
    validated inside the experiments."""
    from fms_dispatch.rl import guide, ppo_solver
    from fms_dispatch.rl.models import default_model_name, load_agent

    # the default plan search stops on the clock (its tabu search); a search without it is reproducible, so the
    # experiments' runs can be compared with the solver's
    monkeypatch.setattr(guide, "DEFAULT_EFFORT", guide.PlanEffort(restarts=8, tabu=0.0))
    default = default_model_name(builtin("EX12"))
    doc = run_ablation(quick=True, results_dir=tmp_path / "a", steps=64, studies=["lookahead", "masking"],
                       echo=False, decisions="full")
    assert doc["decisions"] == "full" and doc["lookahead"] == {
        "model": default, "mode": "plan's empty trips",
        "plan": "searched in the off run, acted out again in the on run"}
    look = [r for r in doc["rows"] if r["study"] == "lookahead"]
    assert sorted((r["instance"], r["variant"]) for r in look) == [("EX12", "off"), ("EX12", "on"), ("EX22", "off"),
                                                                   ("EX22", "on")]
    assert all(r["valid"] for r in look)
    off = {r["instance"]: r["makespan"] for r in look if r["variant"] == "off"}
    assert off["EX12"] == ppo_solver(f"ppo:{default}")(builtin("EX12")).makespan
    on = {r["instance"]: r["makespan"] for r in look if r["variant"] == "on"}
    assert on["EX22"] == ppo_solver(f"ppo:{default}")(builtin("EX22"), lookahead="guide").makespan
    curve = [r for r in doc["rows"] if r["study"] == "masking"]
    assert all(r["invalid_episodes"] == 0 for r in curve if r["variant"] == "masked")
    assert sum(r["invalid_episodes"] for r in curve if r["variant"] == "unmasked") > 0
    doc = run_ablation(quick=True, results_dir=tmp_path / "a2", studies=["lookahead"], echo=False, decisions="full",
                       model="full")
    assert doc["lookahead"] == {"model": "full", "mode": "verified twin", "plan": None}
    look = {(r["instance"], r["variant"]): r["makespan"] for r in doc["rows"]}
    assert look[("EX12", "off")] == ppo_solver("ppo:full")(builtin("EX12")).makespan
    assert all(look[(i, "on")] <= look[(i, "off")] for i in ("EX12", "EX22"))  # verified moves only

    # two groups: the model runs again after a specialist has trained
    doc = run_generalization(quick=True, results_dir=tmp_path / "g", steps=32, echo=False, decisions="full",
                             groups=[0, 1])
    assert doc["general_model"] == default and doc["decisions"] == "full"
    assert [(r["group"], r["agent"], r["instance"]) for r in doc["rows"]] == [
        (g, a, f"sl{g}9") for g in (0, 1) for a in (f"general ({default})", "specialized")]
    for general in doc["rows"][::2]:
        assert general["valid"] and general["makespan"] == ppo_solver(f"ppo:{default}")(
            builtin(general["instance"])).makespan
    doc = run_generalization(quick=True, results_dir=tmp_path / "g2", steps=32, echo=False, decisions="full",
                             model="full")
    assert doc["general_model"] == "full" and doc["rows"][0]["agent"] == "general (full)"
    assert doc["rows"][0]["makespan"] == ppo_solver("ppo:full")(builtin("sl09")).makespan

    doc = run_dynamic(quick=True, results_dir=tmp_path / "d", model="full", echo=False)
    assert doc["model"] == "full" and doc["decisions"] == "full"
    static = doc["summary"]["rl_static_makespan"]
    assert static == ppo_solver("ppo:full")(builtin("sl00")).makespan
    with pytest.raises(ValueError, match="full net, not through a Shop"):  # the model never runs on the wrong net
        from fms_sim.shop import Shop

        load_agent("full").act(Shop(builtin("EX12")))
    with pytest.raises(ValueError, match="unknown decisions 'both'"):
        run_ablation(quick=True, results_dir=tmp_path, studies=["lookahead"], echo=False, decisions="both")
    with pytest.raises(ValueError, match="unknown decisions"):
        run_generalization(quick=True, results_dir=tmp_path, echo=False, decisions="both")


def test_a_study_model_of_the_other_net_is_refused_before_any_work(tmp_path: Path) -> None:
    """--model names a model of the net the study runs on; one of the other net is refused at once (before the
    ablation trains anything), naming the option that fits it; an unknown model names the shipped ones."""
    with pytest.raises(ValueError, match="model full decides through the full net, but this study runs on the "
                                         "paper net; run it with --decisions full"):
        run_ablation(quick=True, results_dir=tmp_path / "a", echo=False, model="full")
    with pytest.raises(ValueError, match="model bu decides through the paper net.*--decisions paper"):
        run_generalization(quick=True, results_dir=tmp_path / "g", echo=False, decisions="full", model="bu")
    with pytest.raises(ValueError, match="no model named 'nope'"):
        run_generalization(quick=True, results_dir=tmp_path / "g", echo=False, model="nope")
    assert not any(tmp_path.iterdir())
    from fms_dispatch.cli import main

    assert main(["experiment", "ablation", "--quick", "--model", "full", "--results-dir", str(tmp_path / "c")]) == 2
    assert not any(tmp_path.iterdir())


def test_dynamic_with_fewer_jobs_than_partitions_keeps_their_arrival_times(tmp_path: Path) -> None:
    # empty partitions were dropped and the rest renumbered: they arrived earlier than p * delta
    inst = builtin("EX12")
    assert inst.n_jobs < 10
    doc = run_dynamic(quick=True, results_dir=tmp_path, instance="EX12", sos_time=0.05, echo=False)
    slots = [p for p, g in enumerate(partition_jobs(inst.n_jobs)) if g]
    assert [r["partition"] for r in doc["rows"]] == slots and len(slots) == inst.n_jobs
    assert [r["arrival"] for r in doc["rows"]] == [round(p * doc["delta"], 2) for p in slots]
    assert slots != list(range(len(slots)))  # some partitions are empty: the case that was renumbered
    assert all(r["sos_valid"] for r in doc["rows"])


def test_a_results_dir_that_is_a_file_is_refused_before_any_work(tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    from fms_dispatch.cli import main

    (tmp_path / "f").write_text("")
    for where in (tmp_path / "f", tmp_path / "f" / "sub"):
        assert main(["experiment", "ablation", "--quick", "--studies", "lookahead", "--results-dir", str(where)]) == 2
        err = capsys.readouterr()
        assert "is a file; name a folder" in err.err and "lookahead [" not in err.out  # nothing was run


def test_bad_options(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="size group 9"):
        run_generalization(quick=True, results_dir=tmp_path, groups=[9], echo=False)
    with pytest.raises(ValueError, match="--sos-time"):
        run_dynamic(quick=True, results_dir=tmp_path, sos_time=0, echo=False)
    with pytest.raises(ValueError, match="--steps"):
        run_ablation(quick=True, results_dir=tmp_path, steps=-5, echo=False)
    from fms_dispatch.cli import main

    # on the command line a 0 is refused too, not read as "the default"
    for args in (["ablation", "--steps", "0"], ["disruptions", "--seeds", "0"], ["dynamic", "--sos-time", "0"]):
        assert main(["experiment", *args, "--quick", "--results-dir", str(tmp_path)]) == 2, args
    assert not any(tmp_path.iterdir())


def test_parser() -> None:
    p = argparse.ArgumentParser()
    add_experiment_parser(p.add_subparsers(dest="cmd"))
    a = p.parse_args(["experiment", "dynamic", "--quick", "--results-dir", "r", "--seed", "3", "--sos-time", "0.5"])
    assert (a.experiment, a.quick, a.results_dir, a.seed, a.sos_time) == ("dynamic", True, "r", 3, 0.5)
    a = p.parse_args(["experiment", "generalization", "--groups", "0", "2", "--steps", "100"])
    assert (a.groups, a.steps, a.quick, a.results_dir) == ([0, 2], 100, False, "results")
    a = p.parse_args(["experiment", "ablation", "--studies", "lookahead", "masking"])
    assert a.studies == ["lookahead", "masking"] and a.steps is None
    a = p.parse_args(["experiment", "disruptions", "--seeds", "1", "--lookahead-max-ops", "300", "--instances", "sl00"])
    assert (a.seeds, a.lookahead_max_ops, a.instances, a.model) == (1, 300, ["sl00"], None)
    assert p.parse_args(["experiment", "disruptions"]).lookahead_max_ops == 100
    assert p.parse_args(["experiment", "ablation"]).decisions == "paper"
    assert p.parse_args(["experiment", "generalization", "--decisions", "full"]).decisions == "full"
    assert p.parse_args(["experiment", "generalization"]).model is None
    assert p.parse_args(["experiment", "ablation", "--model", "full", "--decisions", "full"]).model == "full"
    with pytest.raises(SystemExit):
        p.parse_args(["experiment", "nonsense"])


def test_disruptions_quick(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from fms_dispatch.experiments import DISRUPTION_COLUMNS, DISRUPTION_METHODS, run_disruptions

    doc = run_disruptions(quick=True, results_dir=tmp_path)
    rows, saved = _outputs(tmp_path, "disruptions", DISRUPTION_COLUMNS)
    # two instances x noise 0 / 10 % x six methods (PPO: the full-net model; default: the shipped default model)
    assert len(rows) == 2 * 2 * 6
    assert {r["instance"] for r in rows} == {"EX12", "ra01"} and {float(r["noise"]) for r in rows} == {0.0, 0.1}
    assert all(int(r["breakdowns"]) == 2 for r in rows)
    for r in rows:  # every run measured (and validated inside the experiment), with its decision latency
        assert int(r["makespan"]) > 0 and int(r["decisions"]) > 0 and float(r["latency_ms"]) > 0
    assert saved["not_measured"] == {}
    assert set(doc["summary"]) == {f"{m} noise {n:g}" for m in DISRUPTION_METHODS for n in (0.0, 0.1)}
    for key, v in doc["summary"].items():
        assert v["runs"] == 2, key  # each method's rows only (one prefixes another)
    assert set(saved["replan_beats_plan"]) == set(saved["replan_beats_ppo"]) == {"noise 0", "noise 0.1"}
    assert set(saved["replan_beats_ppo_lookahead"]) == set(saved["ppo_lookahead_beats_ppo"]) == {"noise 0", "noise 0.1"}
    assert all(v.endswith("/2") for v in saved["replan_beats_ppo_lookahead"].values())
    # PPO decides in the disrupted shop itself: its nominal run is the model's plain run of the instance
    from fms_dispatch.rl import ppo_solver
    from fms_sim.benchmarks import builtin

    ppo = [r for r in rows if r["method"] == "ppo" and r["instance"] == "EX12"]
    assert {int(r["nominal_makespan"]) for r in ppo} == {ppo_solver("ppo:full")(builtin("EX12")).makespan}
    # without disruptions the verified lookahead is never worse than the plain model (nominal runs)
    look = [r for r in rows if r["method"] == "ppo+lookahead"]
    for r in look:
        plain = next(p for p in rows if p["method"] == "ppo" and p["instance"] == r["instance"])
        assert int(r["nominal_makespan"]) <= int(plain["nominal_makespan"])
    # the default model (its plan search stops on the clock, so its makespans are not compared with another run):
    # one nominal run per instance, each disrupted run against it
    default = [r for r in rows if r["method"] == "default"]
    assert {r["instance"] for r in default} == {"EX12", "ra01"}
    for r in rows:  # the time spent before a run: a plan's or the rule choice's; a policy's is inside its run
        assert (float(r["plan_time"]) > 0) == (r["method"].split(" ")[0] in ("plan:cpsat", "plan:cpsat+replan",
                                                                               "best-rule")), r
    for r in default:
        assert len({int(d["nominal_makespan"]) for d in default if d["instance"] == r["instance"]}) == 1
        assert float(r["ratio"]) == round(int(r["makespan"]) / int(r["nominal_makespan"]), 4)
    assert set(saved["replan_beats_default"]) == set(saved["default_beats_best_rule"]) == {"noise 0", "noise 0.1"}
    for k, v in saved["replan_beats_default"].items():
        a, n = map(int, v.split("/"))
        b = int(saved["default_beats_replan"][k].split("/")[0])
        assert n == 2 and a + b <= n
    out = capsys.readouterr().out
    assert "| method | noise |" in out and "beats PPO + lookahead" in out and "beats the default model" in out


def test_disruptions_run_the_lookahead_only_up_to_its_size_limit(tmp_path: Path) -> None:
    from fms_dispatch.experiments import run_disruptions

    doc = run_disruptions(quick=True, results_dir=tmp_path, echo=False, seeds=1, lookahead_max_ops=0)
    assert "ppo+lookahead" not in {r["method"] for r in doc["rows"]}
    assert "over 0 operations" in doc["not_measured"]["ppo+lookahead"] and "EX12" in doc["not_measured"]["ppo+lookahead"]
    assert doc["replan_beats_ppo_lookahead"] == {"noise 0": "0/0", "noise 0.1": "0/0"}
    with pytest.raises(ValueError, match="--lookahead-max-ops"):
        run_disruptions(quick=True, results_dir=tmp_path, echo=False, lookahead_max_ops=-1)
    doc = run_disruptions(quick=True, results_dir=tmp_path, echo=False, instances=["ra01"], seeds=1)
    assert {r["instance"] for r in doc["rows"]} == {"ra01"}
    with pytest.raises(ValueError, match="sl99 not in this experiment"):
        run_disruptions(quick=True, results_dir=tmp_path, echo=False, instances=["sl99"])


def test_disruptions_ppo_method_takes_a_full_net_model_by_name(tmp_path: Path,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """--model puts another full-net model in the ppo method (recorded as ppo_model); a paper-net model or an
    unknown one is refused before any work (the shipped default may be absent, a model asked for may not)."""
    from fms_dispatch.cli import main
    from fms_dispatch.experiments import run_disruptions
    from fms_dispatch.rl import guide, ppo_solver

    monkeypatch.setattr(guide, "DEFAULT_EFFORT", guide.PlanEffort(restarts=8, tabu=0.0))  # a reproducible search
    doc = run_disruptions(quick=True, results_dir=tmp_path / "ok", echo=False, seeds=1, lookahead_max_ops=0,
                          instances=["EX12"], model="guided-dagger")
    assert doc["ppo_model"] == "guided-dagger"
    ppo = [r for r in doc["rows"] if r["method"] == "ppo"]
    assert len(ppo) == 2 and all(r["makespan"] > 0 for r in ppo)  # noise 0 and 10 %, validated in the experiment
    # its nominal run is the model's run of the instance, with the plan search fms solve makes
    assert ppo[0]["nominal_makespan"] == ppo_solver("ppo:guided-dagger")(builtin("EX12")).makespan
    assert run_disruptions(quick=True, results_dir=tmp_path / "d", echo=False, seeds=1, lookahead_max_ops=0,
                           instances=["EX12"])["ppo_model"] == "full"
    with pytest.raises(ValueError, match="model bu decides through the paper's net, which runs no disruptions"):
        run_disruptions(quick=True, results_dir=tmp_path / "bad", echo=False, model="bu")
    with pytest.raises(ValueError, match="no model named 'nope'"):
        run_disruptions(quick=True, results_dir=tmp_path / "bad", echo=False, model="nope")
    assert main(["experiment", "disruptions", "--quick", "--model", "bu", "--results-dir", str(tmp_path / "bad")]) == 2
    assert not (tmp_path / "bad").exists()


def test_disruptions_report_ppo_as_not_measured_without_its_model(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    from fms_dispatch.experiments import run_disruptions

    monkeypatch.setenv("FMS_MODELS_DIR", str(tmp_path / "none"))
    doc = run_disruptions(quick=True, results_dir=tmp_path, echo=False)
    assert "no model named 'full'" in doc["not_measured"]["ppo"] and "no model" in doc["not_measured"]["ppo+lookahead"]
    assert "the default model is not available" in doc["not_measured"]["default"]
    assert {r["method"].split(" ")[0] for r in doc["rows"]} == {"plan:cpsat", "plan:cpsat+replan", "best-rule"}



def test_an_interrupt_while_writing_leaves_the_last_runs_files_whole(tmp_path: Path) -> None:
    """The CSV and JSON were written in place before the chart: an interrupt while drawing left this run's tables
    beside the last run's chart (and one while writing the CSV, half a CSV). Now all three stay the last run's."""
    from fms_dispatch.experiments import _write

    def old_chart(path: Path) -> None:
        path.write_bytes(PNG_MAGIC + b"old")

    def interrupted(path: Path) -> None:
        path.write_bytes(PNG_MAGIC + b"half")
        raise KeyboardInterrupt

    _write("x", tmp_path, ("a",), [{"a": 1}], {"experiment": "x"}, old_chart)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    with pytest.raises(KeyboardInterrupt):
        _write("x", tmp_path, ("a",), [{"a": 2}, {"a": 3}], {"experiment": "x"}, interrupted)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before  # no temporaries left either


def test_dynamic_validates_its_static_reference_run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The summary's rl_static_makespan (all jobs at 0) came from a run that was never validated."""
    from fms_dispatch.rl import lookahead

    real = lookahead.run_agent

    def broken(*args, **kwargs):
        s = real(*args, **kwargs)
        s.makespan += 1  # a simulator bug the validator must catch
        return s

    monkeypatch.setattr(lookahead, "run_agent", broken)
    with pytest.raises(RuntimeError, match="infeasible schedule for EX12"):
        run_dynamic(quick=True, results_dir=tmp_path, instance="EX12", echo=False)
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("reference", ["cpsat", "rules"])
def test_disruptions_validate_the_nominal_runs_they_divide_by(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                              reference: str) -> None:
    """Every ratio divides by a nominal makespan: the CP-SAT plan's and the best rule's were taken unchecked."""
    from fms_dispatch import solvers
    from fms_dispatch.experiments import run_disruptions

    real = solvers.solve

    def broken(instance, name, **options):
        s = real(instance, name, **options)
        if name == reference:
            s.makespan += 1  # a solver bug the validator must catch
        return s

    monkeypatch.setattr(solvers, "solve", broken)
    with pytest.raises(RuntimeError, match="infeasible schedule for EX12"):
        run_disruptions(quick=True, results_dir=tmp_path, instances=["EX12"], echo=False)
    assert not any(tmp_path.iterdir())


def _interrupt_training(monkeypatch: pytest.MonkeyPatch, at: int | None) -> list[int]:
    """Make PPO's ``at``-th training (1-based; None: none) end in Ctrl-C, as a user's would; returns the list that
    counts the trainings started."""
    from sb3_contrib import MaskablePPO

    real = MaskablePPO.learn
    calls: list[int] = []

    def learn(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == at:
            raise KeyboardInterrupt  # (train keeps what was learnt and returns, marked interrupted)
        return real(self, *args, **kwargs)

    monkeypatch.setattr(MaskablePPO, "learn", learn)
    return calls


def test_generalization_keeps_finished_groups_on_an_interrupt_and_reuses_them(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """A Ctrl-C in group 1's training was swallowed (train keeps its model and returns): the run went on with a
    specialist of 0 steps in the tables. Now it stops, says what was kept, and a rerun of the same command reuses the
    finished group 0, continues group 1's training, and trains only what it lacks; other options reuse nothing."""
    with monkeypatch.context() as m:
        _interrupt_training(m, at=2)
        with pytest.raises(KeyboardInterrupt):
            run_generalization(quick=True, results_dir=tmp_path, steps=32, groups=[0, 1], echo=False)
    err = capsys.readouterr().err
    assert "generalization: interrupted in group 1 (training: 32 steps) after 1 of 2 group(s)" in err
    assert "kept: 1 finished group(s) (0)" in err and "trained 0 of 32 steps" in err
    assert "run the same command again to continue" in err
    assert not list(tmp_path.glob("experiment_generalization.*"))  # the tables were not written
    kept = list((tmp_path / "experiment_generalization_groups").glob("g0-*/group.json"))
    assert len(kept) == 1
    group0 = json.loads(kept[0].read_text())["rows"]
    assert [(r["group"], r["agent"], r["instance"], r["train_steps"]) for r in group0] == [
        (0, "specialized", "sl09", 32)]

    calls = _interrupt_training(monkeypatch, at=None)
    doc = run_generalization(quick=True, results_dir=tmp_path, steps=32, groups=[0, 1])
    err = capsys.readouterr().err
    assert len(calls) == 1 and doc["reused_groups"] == [0]  # only group 1 trained, and only what it lacked
    assert "group 0 (15x15x15) [1/2]: specialised agent and its 1 row(s) reused from" in err
    assert "group 1 (20x15x15) [2/2]: training: continues the agent interrupted after 0 of 32 steps" in err
    assert [r for r in doc["rows"] if r["agent"] == "specialized"][0] == group0[0]
    assert [(r["group"], r["agent"]) for r in doc["rows"]] == [(g, a) for g in (0, 1)
                                                               for a in ("general (large)", "specialized")]
    _outputs(tmp_path, "generalization", GENERALIZATION_COLUMNS)

    doc = run_generalization(quick=True, results_dir=tmp_path, steps=32, groups=[0, 1], echo=False)
    assert len(calls) == 1 and doc["reused_groups"] == [0, 1]  # both finished now: nothing trains
    doc = run_generalization(quick=True, results_dir=tmp_path, steps=32, groups=[0], seed=1, echo=False)
    assert len(calls) == 2 and doc["reused_groups"] == []  # another seed: its own agent
    doc = run_generalization(quick=True, results_dir=tmp_path, steps=48, groups=[0], echo=False)
    assert len(calls) == 3 and doc["reused_groups"] == []  # other steps: its own agent
    assert doc["rows"][1]["train_steps"] == 48


def test_generalization_says_each_groups_stages(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """It said one line per group, once the group was done: hours of training without a word."""
    run_generalization(quick=True, results_dir=tmp_path, steps=32)
    err = capsys.readouterr().err
    head = "generalization: group 0 (15x15x15) [1/1]: "
    stages = [line.split(head, 1)[1].split(" (")[0] for line in err.splitlines() if line.startswith(head)]
    assert stages[:3] == ["general model large on 1 instance(s)", "training: 32 steps",
                          "measuring the specialised agent on 1 instance(s)"]
    assert len(stages) == 4 and stages[3].startswith("done in ")
    assert all(line.endswith(" s in all)") for line in err.splitlines() if line.startswith(head))
    assert "PPO: 32/32 steps" in err  # PPO's own progress, as fms train says it off a terminal
    run_generalization(quick=True, results_dir=tmp_path / "q", steps=32, echo=False)
    assert capsys.readouterr().err == ""


def test_ablation_stops_on_an_interrupted_training(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A Ctrl-C while the reward-shaping agent trained was swallowed by train: the study went on and measured an
    agent cut short as if it had trained its budget."""
    calls = _interrupt_training(monkeypatch, at=1)
    with pytest.raises(KeyboardInterrupt):
        run_ablation(quick=True, results_dir=tmp_path, steps=32, studies=["reward_shaping"], echo=False)
    assert len(calls) == 1 and [p.name for p in tmp_path.iterdir()] == ["experiment_ablation_studies"]  # no tables


def test_generalization_interrupted_on_the_command_line_says_what_was_kept(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """fms ends an interrupted command with exit code 130; the experiment says before that what it kept, and the
    interrupted group's model folder holds the training to continue (it trained in a temporary folder, removed)."""
    from fms_dispatch.cli import main

    _interrupt_training(monkeypatch, at=1)
    args = ["experiment", "generalization", "--quick", "--steps", "32", "--results-dir", str(tmp_path)]
    assert main(args) == 130
    err = capsys.readouterr().err
    assert "interrupted in group 0 (training: 32 steps) after 0 of 1 group(s); kept: 0 finished group(s) (none)" in err
    assert "group 0's agent, trained 0 of 32 steps, in " in err and err.rstrip().endswith("fms: interrupted")
    model = next((tmp_path / "experiment_generalization_groups").glob("g0-*/model"))
    assert json.loads((model / "metrics.json").read_text())["training"]["interrupted"] is True
    assert (model / "model.zip").is_file()


@pytest.mark.parametrize("name", ["ablation", "generalization", "dynamic", "disruptions"])
def test_fms_experiment_refuses_a_negative_seed(name, tmp_path, capsys):
    # (training refused it only after the studies before it had run, minutes in; sos ran -1 as seed 1)
    from fms_dispatch import cli

    code = cli.main(["experiment", name, "--quick", "--seed", "-1", "--results-dir", str(tmp_path)])
    assert code == 2 and "--seed must be an integer >= 0, got -1" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_ablation_keeps_finished_variants_on_an_interrupt_and_reuses_them(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """The ablation trained its agents in a temporary folder and kept its rows in memory: a Ctrl-C in the sparse
    agent's training lost the shaped agent trained before it. Now it says what was kept, and a rerun of the same
    command reuses the finished variants, continues the sparse agent's training, measures the lookahead again and
    trains only what it lacks; other options reuse nothing."""
    with monkeypatch.context() as m:
        _interrupt_training(m, at=2)
        with pytest.raises(KeyboardInterrupt):
            run_ablation(quick=True, results_dir=tmp_path, steps=32, echo=False)
    err = capsys.readouterr().err
    assert "ablation: interrupted in reward shaping sparse (training: 32 steps) after 1 of 5 variant(s)" in err
    assert "kept: 1 finished variant(s) (reward shaping shaped)" in err and "trained 0 of 32 steps" in err
    assert "run the same command again to continue" in err
    assert not list(tmp_path.glob("experiment_ablation.*"))  # the tables were not written
    root = tmp_path / "experiment_ablation_studies"
    kept = list(root.glob("reward_shaping-shaped-*/variant.json"))
    assert len(kept) == 1
    shaped = json.loads(kept[0].read_text())["rows"]
    assert [(r["study"], r["variant"], r["instance"]) for r in shaped] == [
        ("reward_shaping", "shaped", "sl40"), ("reward_shaping", "shaped", "sl41")]

    calls = _interrupt_training(monkeypatch, at=None)
    doc = run_ablation(quick=True, results_dir=tmp_path, steps=32)
    err = capsys.readouterr().err
    assert len(calls) == 3 and doc["reused_variants"] == ["reward_shaping/shaped"]  # sparse's rest, the 2 curves
    assert "ablation: reward shaping shaped [1/5]: its 2 row(s) reused from" in err
    assert "ablation: reward shaping sparse [2/5]: training: continues the agent interrupted after 0 of 32 steps" in err
    assert "ablation: lookahead [3/5]: bu off and on, EX12 [1/2]" in err  # measured again: it trains nothing
    assert [r for r in doc["rows"] if r["variant"] == "shaped"] == shaped
    assert [(r["study"], r["variant"]) for r in doc["rows"] if r["study"] != "masking"] == [
        ("reward_shaping", v) for v in ("shaped", "shaped", "sparse", "sparse")] + [
        ("lookahead", v) for v in ("off", "on", "off", "on")]
    assert sorted(p.name.rsplit("-", 1)[0] for p in root.iterdir()) == [
        "masking-masked", "masking-unmasked", "reward_shaping-shaped", "reward_shaping-sparse"]
    _outputs(tmp_path, "ablation", ABLATION_COLUMNS)

    doc = run_ablation(quick=True, results_dir=tmp_path, steps=32, echo=False)
    assert len(calls) == 3 and doc["reused_variants"] == [  # all finished now: nothing trains
        "reward_shaping/shaped", "reward_shaping/sparse", "masking/masked", "masking/unmasked"]
    doc = run_ablation(quick=True, results_dir=tmp_path, steps=32, studies=["masking"], seed=1, echo=False)
    assert len(calls) == 5 and doc["reused_variants"] == []  # another seed: its own curves
    doc = run_ablation(quick=True, results_dir=tmp_path, steps=48, studies=["masking"], echo=False)
    assert len(calls) == 7 and doc["reused_variants"] == []  # other steps: its own curves
    doc = run_ablation(quick=True, results_dir=tmp_path, steps=32, studies=["masking"], echo=False,
                       decisions="full")
    assert len(calls) == 9 and doc["reused_variants"] == []  # the other net: its own curves


def test_ablation_interrupted_on_the_command_line_says_what_was_kept(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """fms ends an interrupted command with exit code 130; the ablation says before that what it kept (it said only
    "fms: interrupted", and the finished masked curve was lost with the interrupted unmasked one)."""
    from fms_dispatch.cli import main

    _interrupt_training(monkeypatch, at=2)
    args = ["experiment", "ablation", "--quick", "--steps", "32", "--studies", "masking", "--results-dir",
            str(tmp_path)]
    assert main(args) == 130
    err = capsys.readouterr().err
    assert ("ablation: interrupted in masking unmasked (training: 32 steps) after 1 of 2 variant(s); kept: 1 "
            "finished variant(s) (masking masked)") in err and err.rstrip().endswith("fms: interrupted")
    assert "ablation: masking masked [1/2]: training: 32 steps" in err  # each stage said as it starts
    kept = [p.parent.name.rsplit("-", 1)[0] for p in (tmp_path / "experiment_ablation_studies").glob("*/variant.json")]
    assert kept == ["masking-masked"]  # (the interrupted curve keeps no rows: it is trained again from its start)
