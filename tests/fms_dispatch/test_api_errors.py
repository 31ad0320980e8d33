"""Plausible mistakes with the library API end in one clear error naming what was wrong (they reached attribute
errors deep inside: a name for an instance, a dict for a scenario or schedule, an env used before reset)."""

from __future__ import annotations

import numpy as np
import pytest

from fms_dispatch.rl.envs import FastShopEnv, padding_for
from fms_dispatch.solvers import UnknownSolver, get_solver, solve
from fms_sim.benchmarks import builtin
from fms_sim.full_shop import FullShop, make_shop
from fms_sim.replay import replay
from fms_sim.shop import Shop
from fms_sim.snapshot import nominal_copy, snapshot
from fms_sim.env import ShopEnv
from fms_sim.validate import validate


def test_a_name_or_a_dict_for_an_instance_schedule_or_scenario_is_named() -> None:
    ex12 = builtin("EX12")
    s = solve(ex12, "list")
    for call, who in ((lambda: solve("EX12", "list"), "solve"), (lambda: Shop("EX12"), "Shop"),
                      (lambda: make_shop("EX12"), "FullShop"), (lambda: validate("EX12", s), "validate")):
        with pytest.raises(TypeError, match=f"^{who} takes an Instance .fms_sim.benchmarks.builtin or "
                                            "fms_sim.formats.load_instance reads one by name., got str 'EX12'"):
            call()
    with pytest.raises(TypeError, match=r"^validate takes a Schedule .Schedule.from_dict reads one from a dict., "
                                        r"got dict \{"):
        validate(ex12, s.to_dict())
    # replay and tabu_plan name themselves (the validator's check they run first said "validate takes ...")
    with pytest.raises(TypeError, match="^replay takes a Schedule .Schedule.from_dict reads one from a dict"):
        replay(ex12, s.to_dict())
    with pytest.raises(TypeError, match="^replay takes an Instance"):
        replay("EX12", s)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="^validate takes a Schedule .Schedule.load reads one from a file., got str"):
        validate(ex12, "s.json")  # type: ignore[arg-type]
    with pytest.raises(TypeError, match=r"^scenario must be a Scenario .Scenario.from_dict reads a dict., got dict$"):
        FullShop(ex12, scenario={"noise": 0.1})
    with pytest.raises(UnknownSolver, match="^a solver is named by a string, got NoneType None"):
        get_solver(None)
    with pytest.raises(TypeError, match="the env's episode .* takes an Instance .*got str 'EX12'"):
        ShopEnv(ex12).reset(options={"instance": "EX12"})
    paper = make_shop(ex12, "paper")
    with pytest.raises(TypeError, match="^a snapshot is taken of a FullShop .the full-decision net., not a Shop$"):
        snapshot(paper)
    with pytest.raises(TypeError, match="^a nominal copy is made of a FullShop"):
        nominal_copy(paper)


def test_charts_and_rule_policies_name_their_mistakes() -> None:
    # each was an AttributeError (swapped arguments, a name for an instance, None for a rule) or a TypeError from
    # deep inside (a paper-net policy on the full net, a time limit given as a string)
    from fms_dispatch.full_rules import FullRulePolicy, run_full, solve_best_rules, solve_list
    from fms_dispatch.rules import RulePolicy
    from fms_dispatch.tabu import tabu_plan
    from fms_sim.gantt import plot_gantt

    ex12 = builtin("EX12")
    s = solve(ex12, "list")
    with pytest.raises(TypeError, match="^plot_gantt takes a Schedule .*got Instance"):
        plot_gantt(ex12, s)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="^plot_gantt's instance takes an Instance .*got str 'EX12'"):
        plot_gantt(s, "EX12")  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="^plot_gantt takes a Schedule .Schedule.from_dict reads one from a dict"):
        plot_gantt(s.to_dict())  # type: ignore[arg-type]
    for make, what in ((lambda: RulePolicy(None), "job"), (lambda: RulePolicy("MTWR", 3), "vehicle"),
                       (lambda: FullRulePolicy("MTWR", "nearest", None), "tool")):
        with pytest.raises(ValueError, match=f"^the {what} rule is named by a string .*got (None|3)$"):
            make()
    with pytest.raises(TypeError, match="^a RulePolicy decides through the paper's net"):
        run_full(ex12, RulePolicy("MTWR", "nearest"))
    with pytest.raises(TypeError, match="^choose must be a callable shop -> action, got str"):
        run_full(ex12, "MTWR")  # type: ignore[arg-type]
    assert validate(ex12, run_full(ex12, FullRulePolicy("MTWR", "nearest"))) == []
    with pytest.raises(ValueError, match="^the list order is named by a string .est, ect, .*got None"):
        solve_list(ex12, None)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="^tabu_plan takes a Schedule"):
        tabu_plan(ex12, None)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="^tabu_plan takes an Instance"):
        tabu_plan("EX12", s)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="^time_limit must be a number of seconds or None, got '1'"):
        solve_best_rules(ex12, time_limit="1")  # type: ignore[arg-type]


def test_the_solvers_public_functions_name_their_mistakes() -> None:
    # each was an AttributeError or a TypeError from deep inside (a name for an instance, a string for a config, a
    # count or a seed rule), or ran on (a NaN budget)
    from fms_dispatch import parse_rule_name, solve_best_rules, solve_list, solve_tabu, tabu_plan
    from fms_dispatch.exact import greedy_schedule

    ex11 = builtin("EX11")
    for call, who in ((lambda: solve_list("EX11"), "solve_list"), (lambda: solve_tabu("EX11"), "solve_tabu"),
                      (lambda: solve_best_rules("EX11"), "solve_best_rules"),
                      (lambda: greedy_schedule("EX11"), "greedy_schedule")):
        with pytest.raises(TypeError, match=f"^{who} takes an Instance .*got str 'EX11'"):
            call()
    with pytest.raises(ValueError, match="a rule name is a string such as rule:MTWR.nearest, got None"):
        parse_rule_name(None)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="config must be an SOSConfig or None, got str"):
        solve(ex11, "sos", time_limit=0.5, config="x")
    with pytest.raises(ValueError, match="initial names seed policies .*got 1"):
        solve(ex11, "sos", time_limit=0.5, initial=[1])
    with pytest.raises(ValueError, match="workers must be an integer >= 1, got '2'"):
        solve(ex11, "cpsat", time_limit=1, workers="2")
    plan = greedy_schedule(ex11)
    with pytest.raises(ValueError, match="budget must be >= 0 seconds .None: no time limit., got nan"):
        tabu_plan(ex11, plan, budget=float("nan"))
    with pytest.raises(ValueError, match="needs a time budget or an iteration limit"):  # inf: no limit, as None
        tabu_plan(ex11, plan, budget=float("inf"))
    assert validate(ex11, tabu_plan(ex11, plan, budget=float("inf"), max_iters=3)) == []
    assert validate(ex11, tabu_plan(ex11, plan, budget=np.float32(0.01))) == []  # numpy numbers are numbers
    with pytest.raises(ValueError, match="time_limit must be a positive, finite number of seconds, got inf"):
        solve_tabu(ex11, time_limit=float("inf"))  # it said "tabu_plan needs a time budget", never called by name


def test_an_env_used_before_reset_or_given_the_wrong_shop_says_so() -> None:
    ex12 = builtin("EX12")
    for call in (lambda e: e.observe(), lambda e: e.potential(), lambda e: e.to_net_action(0),
                 lambda e: e.plan_guide(), lambda e: e.replan_guide()):
        with pytest.raises(RuntimeError, match=r"^no shop to observe: call reset\(\) or attach\(shop\) first$"):
            call(FastShopEnv(ex12, decisions="full", guide="list"))
    with pytest.raises(TypeError, match="^guide_effort must be a PlanEffort, got int$"):
        FastShopEnv(ex12, decisions="full", guide="list", guide_effort=3)
    with pytest.raises(ValueError, match="decisions='paper' observes a paper-net Shop, not a FullShop"):
        FastShopEnv(ex12).attach(make_shop(ex12, "full"))  # an UnboundLocalError in _obs
    with pytest.raises(ValueError, match="missing: max_machines, max_tools, max_agvs, max_tts; unknown: jobs$"):
        padding_for({"max_jobs": 10, "jobs": 3}, [ex12])


def test_an_attached_shop_can_be_stepped_from_its_state() -> None:
    """attach set neither the episode's end nor its reward's potential: step failed (no _lb), or refused a live
    shop after a finished episode ('the episode has ended'), or counted the reward from the old episode."""
    ex12 = builtin("EX12")
    env = FastShopEnv(ex12)
    env.reset(seed=0)
    while not env.step(int(np.flatnonzero(env.action_masks())[0]))[2]:
        pass
    shop = make_shop(ex12, "paper")
    for _ in range(4):
        shop.act(shop.legal_actions()[0])
    env.attach(shop)
    before = env.potential()
    _, reward, done, _, _ = env.step(int(np.flatnonzero(env.action_masks())[0]))
    assert not done and reward == pytest.approx(-(env.potential() - before) / env._scale)
    fresh = FastShopEnv(ex12)
    fresh.attach(make_shop(ex12, "paper"))  # never reset: stepping works too
    fresh.step(int(np.flatnonzero(fresh.action_masks())[0]))


def test_a_ppo_solver_names_its_mistakes() -> None:
    # ppo_solver(None) and a name for an instance were AttributeErrors
    from fms_dispatch.rl import ppo_solver

    with pytest.raises(ValueError, match="bad PPO solver name None"):
        ppo_solver(None)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="^a ppo solver takes an Instance .*got str 'EX12'"):
        ppo_solver("ppo")("EX12")


def test_a_model_given_a_missing_file_or_an_incomplete_padding_says_so(tmp_path) -> None:
    # export_actor named "nope.zip.zip" (sb3 adds ".zip"); a padding without max_machines was a KeyError
    from fms_dispatch.rl.agent import Agent, export_actor
    from fms_dispatch.rl.models import resolve_model

    with pytest.raises(ValueError, match=f"the weights {tmp_path / 'nope.zip'} are no file"):
        export_actor(tmp_path / "nope.zip")
    with pytest.raises(ValueError, match="the padding lacks max_machines, max_tools, max_agvs, max_tts"):
        Agent(resolve_model("bu").weights, {"max_jobs": 8})


def test_the_lazy_re_exports_are_listed_and_load_or_tools_only_when_used():
    # Replanner and solve_with_replanning load OR-Tools on first use; dir() did not list them
    import subprocess
    import sys

    code = ("import sys, fms_dispatch as d; assert 'ortools' not in ' '.join(sys.modules); "
            "assert {'Replanner', 'solve_with_replanning'} <= set(dir(d)); "
            "d.Replanner; assert 'ortools.sat.python.cp_model' in sys.modules; print('ok')")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and res.stdout.strip() == "ok", res.stderr
