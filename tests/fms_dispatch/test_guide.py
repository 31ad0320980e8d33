"""The list schedule's guide: plan orders read from states, the guide follower, guided observations and models."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
import torch

from fms_sim.benchmarks import builtin
from fms_sim.full_shop import FullShop
from fms_sim.replay import replay
from fms_sim.validate import validate
from fms_dispatch.exact import greedy_schedule
from fms_dispatch.full_rules import run_full
from fms_dispatch.rl.actors import load_actor, save_actor
from fms_dispatch.rl.envs import FastShopEnv, obs_layout, obs_size, padding_for
from fms_dispatch.rl.guide import GuideFollower, PlanGuide, guide_plan
from fms_dispatch.rl.plan_expert import plan_dagger_round, plan_demonstrations
from fms_dispatch.rl.policy import EntityPolicy, actor_from_policy


@pytest.mark.parametrize("name,exact", [("EX12", True), ("sl00", True), ("ra01", False), ("sl10", False)])
def test_the_guide_follower_acts_out_the_list_schedule(name, exact):
    # reading the plan's orders from each state (no memory of the run) is the replay of the list schedule, but
    # for the replay's empty pre-positioning trips, which a policy does not make (ra01: 111 against 110)
    inst = builtin(name)
    plan = min((greedy_schedule(inst, rule=r) for r in ("est", "ect")), key=lambda p: p.makespan)
    assert guide_plan(FullShop(inst)).makespan == plan.makespan
    s = run_full(inst, GuideFollower())
    assert validate(inst, s) == []
    assert replay(inst, plan).makespan == plan.makespan
    if exact:
        assert s.makespan == plan.makespan
    else:
        assert plan.makespan < s.makespan <= plan.makespan * 1.01


def test_the_guide_reads_any_state_the_same_way():
    # the heads are a function of the state: a copy of the shop reads what the shop reads, and a guide made
    # afresh for the same plan reads the same, wherever the run stands
    inst = builtin("sl00")
    shop = FullShop(inst)
    plan = guide_plan(shop)
    follower = GuideFollower(PlanGuide(inst, plan))
    seen = 0
    while not shop.done:
        if len(shop.legal_actions()) > 1 and seen % 97 == 0:
            twin = copy.deepcopy(shop)
            a = follower.guide.features(shop, [], 100, 20, 10, 5)
            b = PlanGuide(inst, plan).features(twin, [], 100, 20, 10, 5)
            assert all(np.array_equal(x, y) for x, y in zip(a, b))
            assert GuideFollower(PlanGuide(inst, plan))(twin) == follower(shop)
        seen += 1
        shop.act(follower(shop))
    assert shop.makespan == plan.makespan


def test_a_guide_read_from_states_in_turn_reads_each_as_a_fresh_guide_does():
    # a guide keeps the last heads and ranks it read with the state they came from; reading two runs' states in
    # turn (a shop and a copy left behind at an earlier state) must give what a guide made afresh reads in each
    inst = builtin("sl00")
    shop = FullShop(inst)
    plan = guide_plan(shop)
    guide = PlanGuide(inst, plan)
    follower = GuideFollower(PlanGuide(inst, plan))
    env = FastShopEnv(inst, decisions="full", max_jobs=100, max_machines=20, max_tools=20, max_agvs=10, max_tts=5)
    env.attach(shop)  # for the legal tool take-ups
    behind = copy.deepcopy(shop)
    checked = 0
    while not shop.done:
        legal = shop.legal_actions()
        if len(legal) > 1:
            tools = env.legal_of_kind(legal, "tool").tolist()
            for state, tl in ((shop, tools), (behind, []), (shop, tools)):
                a = guide.features(state, tl, 100, 20, 10, 5)
                b = PlanGuide(inst, plan).features(state, tl, 100, 20, 10, 5)
                assert all(np.array_equal(x, y) for x, y in zip(a, b))
            checked += 1
            if checked % 50 == 0:
                behind = copy.deepcopy(shop)
        shop.act(follower(shop))
    assert checked > 500 and shop.makespan == plan.makespan


@pytest.mark.parametrize("steps", [27, 29])  # a state that can be snapshot, and one with a vehicle choice pending
def test_a_started_shop_gets_a_residual_plan(steps):
    from fms_sim.snapshot import can_snapshot

    inst = builtin("ra01")
    shop = FullShop(inst)
    for _ in range(steps):
        shop.act(shop.legal_actions()[0])
    assert can_snapshot(shop) == (steps == 27)
    before = (shop.now, list(shop.started))
    plan = guide_plan(shop)
    assert (shop.now, list(shop.started)) == before  # the shop itself is not moved
    assert plan.meta.get("residual") is not None  # planned from the state, not from time 0
    assert {(r.job, r.op) for r in plan.operations} == {
        (j, k) for j in range(inst.n_jobs) for k in range(shop.started[j], len(inst.jobs[j]))}


def test_guided_observations_have_the_layout_the_network_reads(tmp_path):
    from sb3_contrib import MaskablePPO
    from stable_baselines3.common.vec_env import DummyVecEnv

    inst = builtin("sl00")
    pad = padding_for("large", [inst])
    env = FastShopEnv(inst, decisions="full", guide="list", **pad)
    lay = obs_layout(pad, "full", "list")
    plain = obs_size(obs_layout(pad, "full"))
    assert env.observation_space.shape[0] == obs_size(lay) == plain + 100 * 6 + 20 + 10 + 5
    model = MaskablePPO(EntityPolicy, DummyVecEnv([lambda: env]), device="cpu", seed=3, n_steps=64, batch_size=32,
                        policy_kwargs={"layout": lay, "hidden": 16})
    small = builtin("ra01")
    demos, ms = plan_demonstrations([small], pad, "shaped", "guide", guide="list")
    assert ms[small.name] == run_full(small, GuideFollower()).makespan
    assert demos["obs"].shape[1] == obs_size(lay)
    actor = actor_from_policy(model.policy)
    loaded, _ = load_actor(save_actor(actor, tmp_path / "a.actor.npz", "sha"))
    with torch.no_grad():
        ref = model.policy.mlp_extractor.forward_actor(torch.as_tensor(demos["obs"])).numpy()
    for i in range(0, len(demos["obs"]), 7):
        m = demos["mask"][i]
        assert np.allclose(loaded.logits(demos["obs"][i], m)[m], ref[i][m], atol=1e-4)
    # the guide's columns carry the plan: at every demonstrated decision some offered action heads its order
    # or a planned vehicle is marked (the follower's choice is readable from the observation)
    g0 = obs_size(obs_layout(pad, "full"))
    jobs = demos["obs"][:, g0:g0 + 100 * 6].reshape(-1, 100, 6)
    assert jobs[:, :, 0].sum() > 0 and jobs[:, :, 4].max() <= 1.0 and np.abs(jobs[:, :, 5]).max() <= 1.0


def test_guides_are_checked():
    inst = builtin("EX12")
    with pytest.raises(ValueError, match="set decisions to full"):
        FastShopEnv(inst, guide="list")
    with pytest.raises(ValueError, match="unknown guide"):
        FastShopEnv(inst, decisions="full", guide="cpsat")
    with pytest.raises(ValueError, match="set decisions to full"):
        obs_layout(padding_for("bu", [inst]), "paper", "list")


def test_a_guided_model_trains_from_the_follower_and_decides(tmp_path):
    from fms_dispatch.rl import ppo_solver
    from fms_dispatch.rl.agent import Agent
    from fms_dispatch.rl.models import load_agent
    from fms_dispatch.rl.train import expand_instances, train

    out = tmp_path / "guided"
    cfg = {"train": ["gen:8x4x3*3@7"], "eval": ["gen:8x4x3*1@8"], "decisions": "full", "guide": "list",
           "steps": 64, "n_envs": 1, "vec_env": "dummy", "hidden": 16, "eval_freq": 64, "save_freq": 64,
           "warm_start": {"expert": "guide", "epochs": 20, "dagger": 1, "dagger_epochs": 5},
           "ppo": {"n_steps": 64, "batch_size": 32}}
    m = train(cfg, out, progress=False)
    saved = json.loads((out / "config.json").read_text())
    assert saved["guide"] == "list" and m["ppo_steps"] >= 64
    follower = m["warm_start"]["expert_makespan"]
    acted = {i.name: run_full(i, GuideFollower()).makespan for i in expand_instances(["gen:8x4x3*3@7"])}
    assert follower == acted  # the expert is the list schedule acted out by the follower
    agent = load_agent(str(out))
    assert agent.guide == "list" and not agent.uses_torch
    (inst,) = expand_instances(["gen:8x4x3*1@9"])
    for lookahead in (False, True):
        s = ppo_solver(f"ppo:{out}")(inst, lookahead=lookahead)
        assert validate(inst, s) == [] and s.meta["decisions"] == "full"
    # weights and config must agree on the guide
    with pytest.raises(ValueError, match="trained with a plan guide"):
        Agent(out / "best_model.zip", agent.padding, decisions="full")


def test_the_guide_expert_needs_a_guided_observation(tmp_path):
    from fms_dispatch.rl.train import train

    base = {"train": ["gen:8x4x3*1@7"], "steps": 0, "n_envs": 1, "vec_env": "dummy", "decisions": "full"}
    with pytest.raises(ValueError, match="set guide to list"):
        train({**base, "warm_start": {"expert": "guide"}}, tmp_path / "a", progress=False)
    with pytest.raises(ValueError, match="set decisions to full"):
        train({**base, "decisions": "paper", "guide": "list", "warm_start": {"expert": "rules"}}, tmp_path / "b",
              progress=False)


def test_dagger_labels_of_the_follower_on_the_policys_states():
    from sb3_contrib import MaskablePPO
    from stable_baselines3.common.vec_env import DummyVecEnv

    inst = builtin("ra01")
    pad = padding_for(None, [inst])
    env = FastShopEnv(inst, decisions="full", guide="list", **pad)
    model = MaskablePPO(EntityPolicy, DummyVecEnv([lambda: env]), device="cpu", seed=1, n_steps=64, batch_size=32,
                        policy_kwargs={"layout": obs_layout(pad, "full", "list"), "hidden": 16})
    plans: dict = {}
    demos, _ = plan_demonstrations([inst], pad, "shaped", "guide", plans=plans, guide="list")
    rows, ms, _ = plan_dagger_round(model, [inst], plans, pad, "shaped", guide="list", follow=True)
    assert len(rows["obs"]) > 0 and rows["obs"].shape[1] == demos["obs"].shape[1]
    assert all(rows["mask"][i][rows["action"][i]] for i in range(len(rows["obs"])))  # labels are legal


def test_a_run_at_its_start_never_inherits_a_plan_made_from_another_runs_state():
    # an agent keeps its tables between runs; a guide planned from a live run's state (after an order arrived)
    # must not steer a later run of the same jobs from its start
    from fms_dispatch.rl.envs import FastShopEnv

    inst = builtin("ra01")
    pad = padding_for(None, [inst])
    live = FullShop(inst)
    for _ in range(27):
        live.act(live.legal_actions()[0])
    env = FastShopEnv(inst, decisions="full", guide="list", **pad)
    env.attach(live)
    residual = env._guide()
    assert residual.origin == live.now > 0
    fresh = FastShopEnv(inst, decisions="full", guide="list", **pad)
    fresh.attach(FullShop(inst))
    fresh.adopt_tables(env)
    assert fresh._guide().origin is None  # planned from scratch
    assert env._guide() is residual  # the live run keeps its own
    twin = copy.deepcopy(live)
    twin.act(twin.legal_actions()[0])
    again = FastShopEnv(inst, decisions="full", guide="list", **pad)
    again.attach(twin)
    again.adopt_tables(env)
    assert again._guide() is residual  # a twin of the live run shares its guide
    # an instance with other jobs (a live order adds one) gets its own guide
    import dataclasses

    bigger = dataclasses.replace(inst, jobs=inst.jobs + (inst.jobs[0],))
    other = FastShopEnv(bigger, decisions="full", guide="list", **padding_for(None, [bigger]))
    other.attach(FullShop(bigger))
    other.adopt_tables(env)
    assert other._guide() is not residual and other._guide().instance is bigger


@pytest.mark.parametrize("name", ["ra01", "sl00"])
def test_the_guides_empty_trips_bring_the_guided_model_to_its_plan(name):
    # the guided model's plain run lacks the plan's empty trips (ra01: 111 against 110); with them at its idle
    # stops it reaches the plan
    from fms_dispatch.rl.guide import PlanEffort
    from fms_dispatch.solvers import solve

    inst = builtin(name)
    plan = guide_plan(FullShop(inst))  # the plain list schedule: no restarts
    plain = solve(inst, "ppo:guided", guide_effort=PlanEffort())
    moved = solve(inst, "ppo:guided+lookahead-guide", guide_effort=PlanEffort())
    assert validate(inst, moved) == [] and moved.meta["solver"] == "ppo:guided+lookahead-guide"
    assert moved.makespan == plan.makespan <= plain.makespan
    assert (name == "ra01") == (plain.makespan > plan.makespan)


def test_lookahead_guide_needs_a_guided_model(capsys):
    from fms_dispatch.cli import main
    from fms_dispatch.solvers import solve

    with pytest.raises(ValueError, match="has no plan guide"):
        solve(builtin("EX12"), "ppo:bu+lookahead-guide")  # bu: the paper's net, no guide
    assert main(["solve", "ra01", "--solver", "ppo", "--lookahead-guide", "-q"]) == 0
    assert main(["solve", "ra01", "--solver", "rules", "--lookahead-guide", "-q"]) == 2


def test_the_cli_sets_the_guides_search(capsys, tmp_path):
    from fms_dispatch.cli import main

    out = tmp_path / "s.json"
    assert main(["solve", "EX104", "--solver", "ppo", "--guide-restarts", "64", "--guide-budget", "0", "-q",
                 "--out", str(out)]) == 0
    meta = json.loads(out.read_text())["meta"]
    # rules, tabu search and polish: the defaults
    assert meta["guide_effort"] == {"restarts": 64, "budget": None, "seed": 0, "rules": False, "exact": 0.0,
                                    "tabu": 0.0025}
    assert main(["solve", "EX104", "--solver", "ppo", "--guide-rules", "--guide-exact", "0.1", "--guide-tabu", "0",
                 "-q", "--out", str(out)]) == 0
    meta = json.loads(out.read_text())["meta"]["guide_effort"]
    assert meta["rules"] is True and meta["exact"] == 0.1 and meta["tabu"] == 0.0
    capsys.readouterr()
    assert main(["solve", "EX104", "--solver", "rules", "--guide-restarts", "4", "-q"]) == 2
    assert "apply to the ppo solver only" in capsys.readouterr().err
    # each bad value named by its own option
    assert main(["solve", "EX104", "--solver", "ppo", "--guide-restarts", "-3", "-q"]) == 2
    assert capsys.readouterr().err.startswith("fms: error: --guide-restarts: plan restarts must be")
    assert main(["solve", "EX104", "--solver", "ppo", "--guide-exact", "-1", "-q"]) == 2
    assert capsys.readouterr().err.startswith("fms: error: --guide-exact: ")
    assert main(["solve", "EX104", "--solver", "ppo", "--guide-tabu", "-0.1", "-q"]) == 2
    assert capsys.readouterr().err.startswith("fms: error: --guide-tabu: plan tabu search must be")
    assert main(["solve", "EX104", "--solver", "list", "--guide-tabu", "0", "-q"]) == 2
    assert "--guide-tabu" in capsys.readouterr().err
    assert main(["solve", "EX104", "--solver", "ppo:bu", "--guide-restarts", "4", "-q"]) == 2
    assert "no plan guide" in capsys.readouterr().err


# ---------------------------------------------------------------------- the plan's search effort
def test_restarts_improve_the_list_plan_reproducibly():
    from fms_dispatch.exact import restart_list_plan

    inst = builtin("EX104")
    plan = min((greedy_schedule(inst, rule=r) for r in ("est", "ect")), key=lambda p: p.makespan)
    better = restart_list_plan(inst, plan, tries=64, seed=3)
    assert validate(inst, better) == []
    assert better.makespan < plan.makespan  # 199 -> 177 on this shop
    assert restart_list_plan(inst, plan, tries=64, seed=3).makespan == better.makespan  # no time limit: reproducible
    # more tries continue the same sequence of restarts: never worse
    assert restart_list_plan(inst, plan, tries=256, seed=3).makespan <= better.makespan
    assert restart_list_plan(inst, plan, tries=0) is plan
    assert restart_list_plan(inst, plan, tries=64, budget=0.0) is plan
    with pytest.raises(ValueError, match="tries"):
        restart_list_plan(inst, plan, tries=-1)
    with pytest.raises(ValueError, match="budget"):
        restart_list_plan(inst, plan, tries=1, budget=-1.0)


def test_plan_effort_is_validated():
    from fms_dispatch.rl.guide import DEFAULT_EFFORT, PlanEffort, effort_from

    assert PlanEffort() == PlanEffort(0, None, 0, False)
    assert DEFAULT_EFFORT.restarts > 0 and DEFAULT_EFFORT.budget is not None and DEFAULT_EFFORT.tabu > 0
    assert effort_from() == DEFAULT_EFFORT
    assert effort_from(restarts=5, budget=0, rules=True) == PlanEffort(5, None, DEFAULT_EFFORT.seed, True,
                                                                       DEFAULT_EFFORT.exact, DEFAULT_EFFORT.tabu)
    assert effort_from(exact=0.5).exact == 0.5 and effort_from(tabu=0).tabu == 0.0
    with pytest.raises(ValueError, match="restarts"):
        effort_from(restarts=-2)
    for bad in (dict(restarts=-1), dict(restarts=1.5), dict(budget=-0.1), dict(budget=float("nan")),
                dict(exact=-0.5), dict(exact=float("nan")), dict(tabu=-0.001), dict(tabu=float("nan")),
                # a string was a TypeError at the first comparison, inf a search that never ended
                dict(budget="1"), dict(budget=float("inf")), dict(seed="a"), dict(rules="yes"), dict(restarts=True),
                dict(exact=float("inf"))):
        with pytest.raises(ValueError, match="plan"):
            PlanEffort(**bad)
    # numpy's numbers were refused; they are kept as Python's (budget=False was taken as no limit)
    got = effort_from(np.int64(3), np.float32(0.5), np.bool_(True), np.float64(0), np.float64(0.001))
    assert got == PlanEffort(3, 0.5, DEFAULT_EFFORT.seed, True, 0.0, 0.001)
    assert [type(v) for v in got.as_dict().values()] == [int, float, int, bool, float, float]
    with pytest.raises(ValueError, match="plan budget must be a finite number of seconds >= 0 .*got False"):
        effort_from(budget=False)


def test_a_searched_plan_guides_from_scratch_and_from_a_state():
    from fms_dispatch.rl.guide import PlanEffort

    inst = builtin("ra01")
    effort = PlanEffort(restarts=48, seed=1)
    plain, searched = guide_plan(FullShop(inst)), guide_plan(FullShop(inst), effort)
    assert validate(inst, searched) == [] and searched.makespan <= plain.makespan
    assert PlanGuide.for_shop(FullShop(inst), effort).effort == effort
    shop = FullShop(inst)
    for _ in range(27):
        shop.act(shop.legal_actions()[0])
    residual = guide_plan(shop, effort)
    assert residual.meta.get("residual") is not None
    assert residual.makespan <= guide_plan(shop).makespan
    assert {(r.job, r.op) for r in residual.operations} == {
        (j, k) for j in range(inst.n_jobs) for k in range(shop.started[j], len(inst.jobs[j]))}


def test_the_guided_model_follows_a_searched_plan():
    # the guide's features only say what heads the plan's orders: the model trained on plain list schedules
    # follows a better plan as well, and an env never reuses a plan searched with another effort
    from fms_dispatch.rl import ppo_solver
    from fms_dispatch.rl.guide import PlanEffort

    inst = builtin("EX104")
    solve = ppo_solver("ppo:guided")
    plain = solve(inst, guide_effort=PlanEffort())
    searched = solve(inst, guide_effort=PlanEffort(restarts=64))
    again = solve(inst, guide_effort=PlanEffort())
    for s in (plain, searched, again):
        assert validate(inst, s) == []
    plan = guide_plan(FullShop(inst), PlanEffort(restarts=64))
    assert searched.makespan < plain.makespan
    assert searched.makespan <= plan.makespan * 1.02
    assert again.makespan == plain.makespan  # the searched plan of the run before is not reused
    assert searched.meta["guide_effort"] == {"restarts": 64, "budget": None, "seed": 0, "rules": False, "exact": 0.0,
                                             "tabu": 0.0}
    assert solve(inst).meta["guide_effort"]["restarts"] > 0  # the default searches
    with pytest.raises(ValueError, match="no plan guide"):
        ppo_solver("ppo:bu")(inst, guide_effort=PlanEffort(restarts=4))
    with pytest.raises(TypeError, match="PlanEffort"):
        solve(inst, guide_effort=64)


def test_the_rule_pairs_schedules_compete_for_the_plan():
    # on EX44 (long travel times) the list schedule and its restarts stay at 163, a paper-net rule pair reaches
    # 153: with ``rules`` the guide takes it, and the guided model acts it out
    from fms_dispatch.rl import ppo_solver
    from fms_dispatch.rl.guide import PlanEffort
    from fms_dispatch.rules import all_rule_pairs, parse_rule_name
    from fms_sim.shop import run_policy

    inst = builtin("EX44")
    best_pair = min(run_policy(inst, parse_rule_name(n)).makespan for n in all_rule_pairs(True))
    listed = guide_plan(FullShop(inst), PlanEffort(restarts=64))
    ruled = guide_plan(FullShop(inst), PlanEffort(restarts=64, rules=True))
    assert validate(inst, ruled) == []
    assert ruled.makespan <= best_pair < listed.makespan
    s = ppo_solver("ppo:guided")(inst, guide_effort=PlanEffort(restarts=64, rules=True), lookahead="guide")
    assert validate(inst, s) == [] and s.makespan <= best_pair
    # a run seen after its start plans from its state: the rules, which run from time 0, are not tried there
    shop = FullShop(inst)
    for _ in range(6):
        shop.act(shop.legal_actions()[0])
    assert guide_plan(shop, PlanEffort(rules=True)).makespan == guide_plan(shop).makespan
    # a zero budget leaves the plain list schedule
    assert guide_plan(FullShop(inst), PlanEffort(restarts=64, budget=0.0, rules=True)).makespan == \
        guide_plan(FullShop(inst)).makespan


def test_cp_sat_polishes_the_plan_of_a_small_shop():
    # EX44 (long travel times): the list search and the rule pairs stop at 153, CP-SAT's full model from that
    # hint finds better within a second (the optimum is 121); the guided model acts the polished plan out
    from fms_dispatch.rl import ppo_solver
    from fms_dispatch.exact import fits_full_model
    from fms_dispatch.rl.guide import PlanEffort

    inst = builtin("EX44")
    searched = guide_plan(FullShop(inst), PlanEffort(restarts=64, rules=True))
    polished = guide_plan(FullShop(inst), PlanEffort(restarts=64, rules=True, exact=1.0))
    assert validate(inst, polished) == []
    assert polished.makespan < searched.makespan
    assert polished.meta["solver"] == "cpsat" and polished.makespan >= 121
    s = ppo_solver("ppo:guided")(inst, guide_effort=PlanEffort(restarts=64, rules=True, exact=1.0),
                                 lookahead="guide")
    assert validate(inst, s) == [] and s.makespan < searched.makespan
    # the polish gets no more than what the budget leaves: none at all here
    assert guide_plan(FullShop(inst), PlanEffort(restarts=64, budget=0.0, rules=True, exact=1.0)).makespan == \
        guide_plan(FullShop(inst)).makespan
    # a run seen after its start plans from its state (a residual plan): no polish there
    shop = FullShop(inst)
    for _ in range(6):
        shop.act(shop.legal_actions()[0])
    residual = guide_plan(shop, PlanEffort(exact=1.0))
    assert residual.meta.get("residual") is not None and residual.meta["solver"] == "greedy"
    # shops beyond CP-SAT's full model are not polished
    assert fits_full_model(inst) and not fits_full_model(builtin("sl00"))
    big = builtin("sl00")
    assert guide_plan(FullShop(big), PlanEffort(exact=5.0)).meta["solver"] == "greedy"


def test_the_tabu_search_improves_the_guides_plan():
    # EX44: the list search stops above the optimum 121; the tabu search over the plan's orders goes further, and
    # the guided model acts its plan out (with its empty trips)
    from fms_dispatch.rl import ppo_solver
    from fms_dispatch.rl.guide import PlanEffort

    inst = builtin("EX44")
    searched = guide_plan(FullShop(inst), PlanEffort(restarts=32))
    tabu = guide_plan(FullShop(inst), PlanEffort(restarts=32, tabu=0.02))
    assert validate(inst, tabu) == [] and tabu.meta["solver"] == "tabu"
    assert 121 <= tabu.makespan < searched.makespan
    s = ppo_solver("ppo:guided")(inst, guide_effort=PlanEffort(restarts=32, tabu=0.02), lookahead="guide")
    assert validate(inst, s) == [] and s.makespan < searched.makespan
    # it gets no more than what the budget leaves: none at all here
    assert guide_plan(FullShop(inst), PlanEffort(restarts=32, budget=0.0, tabu=1.0)).makespan == \
        guide_plan(FullShop(inst)).makespan
    # a residual plan (a run seen after its start) is searched by it too, from the state, and ends no later
    shop = FullShop(inst)
    for _ in range(6):
        shop.act(shop.legal_actions()[0])
    listed = guide_plan(shop)
    residual = guide_plan(shop, PlanEffort(tabu=0.05))
    assert residual.meta["solver"] == "tabu" and residual.meta["residual"] == listed.meta["residual"] == shop.now
    assert residual.makespan < listed.makespan
    # with tools too: ra01 within the default effort's budget
    ra = builtin("ra01")
    plan = guide_plan(FullShop(ra), PlanEffort(restarts=0, budget=1.0, tabu=0.01))
    assert validate(ra, plan) == [] and plan.makespan <= guide_plan(FullShop(ra)).makespan


def test_polish_plan_keeps_or_improves_a_whole_plan():
    from fms_dispatch.exact import FULL_MODEL_MAX_TASKS, n_transport_tasks, polish_plan

    inst = builtin("EX104")
    plan = greedy_schedule(inst)
    better = polish_plan(inst, plan, time_limit=1.0)
    assert validate(inst, better) == [] and better.makespan < plan.makespan
    assert better.meta["polished"] == "greedy"
    assert polish_plan(inst, plan, time_limit=0) is plan
    big = builtin("sl00")
    assert n_transport_tasks(big) > FULL_MODEL_MAX_TASKS
    big_plan = greedy_schedule(big)
    assert polish_plan(big, big_plan, time_limit=5.0) is big_plan  # beyond the full model: untouched, at once
    with pytest.raises(ValueError, match="time_limit"):
        polish_plan(inst, plan, time_limit=-1)
    with pytest.raises(ValueError, match="workers"):
        polish_plan(inst, plan, time_limit=1, workers=0)
    shop = FullShop(inst)
    for _ in range(6):
        shop.act(shop.legal_actions()[0])
    with pytest.raises(ValueError, match="residual"):
        polish_plan(inst, guide_plan(shop), time_limit=1)


def test_a_plain_job_shop_is_planned_from_scratch_and_polished():
    # without AGVs the first parts stand at their machines from time 0 without a decision: the run has not
    # started, so the guide plans from scratch (and may polish), and the snapshot check needs no AGV places
    from fms_dispatch.rl import ppo_solver
    from fms_dispatch.rl.guide import PlanEffort, at_start
    from fms_sim.snapshot import can_snapshot

    inst = builtin("EX12").without_agvs().without_tools()
    shop = FullShop(inst)
    assert any(shop.job_started_ops) and at_start(shop) and can_snapshot(shop)
    plan = guide_plan(shop, PlanEffort(restarts=8, exact=1.0))
    assert "residual" not in plan.meta and validate(inst, plan) == []
    assert plan.makespan <= guide_plan(FullShop(inst)).makespan
    shop.act(shop.legal_actions()[0])
    assert not at_start(shop) and guide_plan(shop).meta.get("residual") is not None
    s = ppo_solver("ppo:guided")(builtin("ta01"))  # the default search on Taillard's plain job shop
    assert validate(builtin("ta01"), s) == [] and s.makespan >= 1231


def test_a_guided_model_re_plans_its_guide_from_a_disrupted_state():
    """``Agent.replan_guide``: when a machine breaks down the guide is planned again from the shop's state (a
    residual plan) and adopted where it ends the margin earlier than the plan in force continued from that state
    (else the plan in force stays); the model then reads the new plan, and the run stays valid in its scenario."""
    from fms_dispatch.rl.guide import REPLAN_MARGIN, PlanEffort, effort_from, retimed_plan
    from fms_dispatch.rl.models import load_agent
    from fms_sim.disruptions import Breakdown, Scenario

    inst = builtin("ra01")
    sc = Scenario((Breakdown(machine=2, start=20, duration=40),), (), 0.1, 5)
    agent = load_agent("guided-dagger")
    agent.use_guide_effort(effort_from(tabu=0.0))
    agent.forget()
    shop = FullShop(inst, scenario=sc)
    res = None
    while not shop.done:
        if res is None and shop.now >= 20:
            old = agent.guide_of(shop)
            assert old.origin is None  # planned at the start
            kept = retimed_plan(shop, old.plan)
            fresh = guide_plan(shop, agent.guide_effort)
            assert kept.meta["residual"] == fresh.meta["residual"] >= 20
            # a margin the new plan cannot beat keeps the plan in force
            res = agent.replan_guide(shop, margin=0.99)
            assert (res.adopted, res.before, res.after) == (False, kept.makespan, fresh.makespan)
            assert agent.guide_of(shop) is old
            res = agent.replan_guide(shop)
            assert res.adopted == (fresh.makespan < kept.makespan * (1 - REPLAN_MARGIN)) and res.adopted  # 126 < 135
            new = agent.guide_of(shop)
            assert new is not old and new.origin >= 20 and new.plan.makespan == fresh.makespan  # the model reads it
            assert agent.replan_guide(shop, margin=None).adopted  # None: adopted whatever it promises
            # a re-plan may be searched with another effort than the model's (here the plain list schedule): the
            # guide then reads that plan, labelled with the model's own effort (what its guide is searched with)
            plain = guide_plan(shop, PlanEffort())
            res = agent.replan_guide(shop, margin=None, effort=PlanEffort())
            assert res.adopted and res.after == plain.makespan != fresh.makespan
            assert agent.guide_of(shop).plan.makespan == plain.makespan
            assert agent.guide_of(shop).effort == agent.guide_effort
        shop.act(agent.act(shop))
    assert res is not None and validate(inst, shop.schedule(), sc) == []
    with pytest.raises(ValueError, match="no plan guide"):
        load_agent("full").replan_guide(FullShop(inst))
    with pytest.raises(ValueError, match="margin"):
        agent.replan_guide(FullShop(inst, scenario=sc), margin=-0.1)


def test_a_guide_plans_from_the_state_when_something_is_down_from_time_0():
    """A breakdown or outage that begins at time 0 is in the shop's state only: the guide's plans there (the first
    one and the re-plan the breakdown triggers) start from that state, so none promises what the shop cannot do.
    They were planned from scratch: with every machine of EX12 down for its first 100 time units the re-plan at time
    0 promised the nominal 82 and was adopted (the run took 178; and 148 instead of 116 with AGV 0 out for 80)."""
    from fms_dispatch.rl.guide import at_start, effort_from, plans_from_scratch
    from fms_dispatch.solvers import solve
    from fms_sim.disruptions import Breakdown, Outage, Scenario

    inst = builtin("EX12")
    longest = max(sum(op.duration for op in job) for job in inst.jobs)
    everything_down = Scenario(tuple(Breakdown(machine=m, start=0, duration=100)
                                     for m in range(1, inst.n_machines + 1)), (), 0.0, 0)
    assert plans_from_scratch(FullShop(inst)) and plans_from_scratch(FullShop(inst, scenario=Scenario((), (), 0.2, 1)))
    shop = FullShop(inst, scenario=everything_down)
    assert at_start(shop) and not plans_from_scratch(shop)
    plan = guide_plan(shop, effort_from(restarts=8, tabu=0.0, budget=0))
    assert plan.meta["residual"] == 0 and plan.makespan >= 100 + longest
    later = Scenario((Breakdown(machine=1, start=5, duration=10),), (), 0.0, 0)
    assert plans_from_scratch(FullShop(inst, scenario=later))  # nothing down yet: the nominal shop at its start
    sched = solve(inst, "ppo", scenario=everything_down, guide_effort=effort_from(tabu=0.0))
    assert validate(inst, sched, everything_down) == []
    promised = [(e["before"], e["after"]) for e in sched.meta["replans"]]
    assert promised and all(min(p) >= 100 + longest for p in promised), promised
    out = Scenario((), (Outage(kind="agv", vehicle=0, start=0, duration=80),), 0.0, 0)
    sched = solve(inst, "ppo", scenario=out, guide_effort=effort_from(tabu=0.0))
    assert validate(inst, sched, out) == []
    first = sched.meta["replans"][0]
    assert (first["reason"], first["time"]) == ("outage", 0)
    # the plan from the state promises what a list schedule from that state does, not the nominal optimum 82
    from fms_dispatch.rl.guide import _state
    from fms_dispatch.exact import greedy_schedule

    start = FullShop(inst, scenario=out)
    floor = min(greedy_schedule(inst, rule=r, origin=_state(start)).makespan for r in ("est", "ect"))
    assert first["after"] > 82 and sched.makespan <= floor
    # a model's guide at time 0 is kept while the shop is there, and serves only a run with the same things down:
    # not the nominal start, nor another scenario's (one agent runs many scenarios of a shop in the benches)
    from fms_dispatch.rl.models import load_agent

    agent = load_agent("guided-dagger")
    agent.use_guide_effort(effort_from(restarts=8, tabu=0.0, budget=0))
    for sc in (everything_down, out, None, everything_down):
        shop = FullShop(inst, scenario=sc)
        guide = agent.guide_of(shop)
        assert agent.guide_of(shop) is guide and agent.guide_of(copy.deepcopy(shop)) is guide
        alone = guide_plan(FullShop(inst, scenario=sc), agent.guide_effort)
        assert guide.origin == alone.meta.get("residual") and guide.plan.makespan == alone.makespan
        assert (guide.origin is None) == (sc is None)


def test_a_guide_planned_at_a_start_that_cannot_be_snapshot_serves_that_start():
    # at time 0 with a tool-use choice pending (no snapshot) the plan starts from the next state that can be one
    # (origin 4 here); it was taken as not fitting the start, so the model re-planned at every decision there
    from fms_dispatch.rl.guide import PlanGuide, at_start, effort_from
    from fms_sim.disruptions import Breakdown, Scenario
    from fms_sim.snapshot import can_snapshot

    inst = builtin("ra01").without_agvs()
    sc = Scenario((Breakdown(machine=1, start=0, duration=30),), (), 0.0, 0)
    shop = FullShop(inst, scenario=sc)
    labels = shop.action_labels()
    shop.act(next(a for a in shop.legal_actions() if labels[a].startswith("tool:")))
    assert at_start(shop) and not can_snapshot(shop)
    guide = PlanGuide.for_shop(shop, effort_from(restarts=2, tabu=0.0, budget=0))
    assert guide.origin is not None and guide.origin > 0 and guide.fits_start(shop)
    other = FullShop(inst, scenario=Scenario((Breakdown(machine=2, start=0, duration=30),), (), 0.0, 0))
    assert not guide.fits_start(other) and not guide.fits_start(FullShop(inst))


def test_the_guide_replanner_answers_each_breakdown_once_per_run():
    """``GuideReplanner`` (breakdowns only: ``drift=None``) re-plans once per breakdown begun: not again on another
    shop object of the same run (a twin, a rebuilt replay), again in a new run (a shop at its start); refused for a
    model without a guide or with a drift that is not positive."""
    import copy

    from fms_dispatch.rl.agent import GuideReplanner
    from fms_dispatch.rl.guide import effort_from
    from fms_dispatch.rl.models import load_agent
    from fms_sim.disruptions import Breakdown, Scenario

    inst = builtin("ra01")
    sc = Scenario((Breakdown(machine=2, start=20, duration=40), Breakdown(machine=3, start=60, duration=10)),
                  (), 0.1, 5)
    agent = load_agent("guided-dagger")
    agent.use_guide_effort(effort_from(tabu=0.0))
    rp = GuideReplanner(agent, drift=None)
    for run in range(2):
        agent.forget()
        shop = FullShop(inst, scenario=sc)
        while not shop.done:
            n = len(rp.events)
            a = rp(shop)
            if len(rp.events) > n:  # a twin of this state re-plans nothing again
                assert rp.check(copy.deepcopy(shop)) is None
            shop.act(a)
        assert validate(inst, shop.schedule(), sc) == []
        assert [(e["reason"], e["time"] >= b.start) for e, b in zip(rp.events[2 * run:], sc.breakdowns)] == [
            ("breakdown", True)] * 2
    same = [{k: v for k, v in e.items() if k != "wall_time"} for e in rp.events]
    assert len(same) == 4 and same[:2] == same[2:]  # the second run as the first
    assert all(e["budget"] == agent.guide_effort.budget == 1.0 for e in rp.events)
    # re-plans searched with another effort than the model's (here without a time limit) say so
    other = GuideReplanner(agent, drift=None, effort=effort_from(tabu=0.0, budget=0))
    agent.forget()
    shop = FullShop(inst, scenario=sc)
    while not shop.done:
        shop.act(other(shop))
    assert [e["reason"] for e in other.events] == ["breakdown"] * 2 and all(e["budget"] is None for e in other.events)
    with pytest.raises(ValueError, match="no plan guide"):
        GuideReplanner(load_agent("full"))
    with pytest.raises(ValueError, match="drift must be positive"):
        GuideReplanner(agent, drift=0.0)


def test_the_guide_replanners_triggers_when_its_re_plans_run_beside_the_run():
    """Live (the shop goes on while a guide re-plan runs): an outage that begins with a breakdown is re-planned under
    the outage's rule (it was folded into the breakdown's margin); a window that began and ended while a re-plan ran
    triggers nothing once it comes in (an outage over for a thousand time units was re-planned for, its plan put in
    force); one still in force triggers its own; a re-plan ended by an order's leaves what it was started for
    unanswered (an outage's rule went to the order's margin)."""
    from fms_dispatch.rl.agent import GuideReplanner
    from fms_dispatch.rl.guide import effort_from
    from fms_dispatch.rl.models import load_agent
    from fms_sim.disruptions import Breakdown, Outage, Scenario

    inst = builtin("ra01")
    agent = load_agent("guided-dagger")
    agent.use_guide_effort(effort_from(tabu=0.0))

    def at(sc, t):  # the run's shop at its first stop from time t on
        agent.forget()
        rp = GuideReplanner(agent, drift=None)
        shop = FullShop(inst, scenario=sc)
        rp.trigger(shop)
        while shop.now < t:
            shop.act(agent.act(shop))
        return rp, shop

    both = Scenario((Breakdown(2, 10, 30),), (Outage("agv", 0, 10, 30),))
    rp, shop = at(both, 10)
    assert rp.trigger(shop) == "outage" and rp._margin("outage") is None
    # began and ended while a re-plan ran: over when it comes in (kept or failed alike); one in force triggers
    sc = Scenario((Breakdown(3, 12, 30),), (Outage("agv", 1, 12, 3),))
    for outcome in ("adopt", "failed"):
        rp, shop = at(sc, 5)
        assert rp.trigger(shop) is None
        plan = agent.guide_of(shop).plan  # (as a re-plan's result: what it is does not matter here)
        while shop.now < 16:  # the outage [12, 15) is over, the breakdown [12, 42) is not
            shop.act(agent.act(shop))
        if outcome == "adopt":
            rp.adopt(shop, "late", 5, plan, plan.makespan, 0.1, 1.0, moved=True)
        else:
            rp.failed(shop, "late", 5, "timeout", 6.0, 1.0, "no plan")
        assert rp._begun(shop) - rp._answered == {("breakdown", 3, 12)}
        assert rp.trigger(shop) == "breakdown" and rp.trigger(shop) is None
    # a re-plan that failed answered what it was started for: the outage does not trigger again
    rp, shop = at(Scenario((), (Outage("agv", 0, 10, 30),)), 10)
    assert rp.trigger(shop) == "outage"
    rp.failed(shop, "outage", shop.now, "failed", 0.1, 1.0, "no plan here")
    assert rp.trigger(shop) is None


def test_the_guide_replanner_re_plans_a_late_plan_at_most_once_per_drift():
    """With ``drift`` the guide is re-planned exactly when an operation started since the last decision is later
    than the plan in force says by more than drift x its makespan, and, after a re-plan that kept the plan, the
    clock has moved on by that much since. A drift no delay reaches re-plans nothing; the runs stay valid."""
    from fms_dispatch.rl.agent import GuideReplanner
    from fms_dispatch.rl.guide import effort_from
    from fms_dispatch.rl.models import load_agent
    from fms_sim.disruptions import Scenario

    inst = builtin("ra01")
    sc = Scenario((), (), 0.4, 2)  # noise only: no breakdown
    agent = load_agent("guided-dagger")
    agent.use_guide_effort(effort_from(tabu=0.0))
    for drift in (0.05, 0.99):
        agent.forget()
        rp = GuideReplanner(agent, drift=drift)
        shop = FullShop(inst, scenario=sc)
        seen, quiet, statuses = 0, 0.0, []
        while not shop.done:
            expect = False
            if shop.rec.ops[seen:]:
                plan = agent.guide_of(shop).plan
                planned = {(r.job, r.op): r.start for r in plan.operations}
                tol = max(1.0, drift * plan.makespan)
                expect = shop.now >= quiet and any(r.start - planned[r.job, r.op] > tol for r in shop.rec.ops[seen:])
            seen = len(shop.rec.ops)
            n = len(rp.events)
            now = shop.now
            shop.act(rp(shop))
            assert (len(rp.events) > n) == expect
            if expect:
                ev = rp.events[-1]
                assert ev["reason"] == "late" and ev["time"] == now
                statuses.append(ev["status"])
                if ev["status"] == "kept":
                    quiet = now + tol
        assert validate(inst, shop.schedule(), sc) == []
        if drift == 0.99:
            assert rp.events == []
        else:
            assert statuses.index("adopted") < len(statuses) - 1  # re-plans go on after a new plan is adopted


@pytest.mark.parametrize("no_tools", [False, True])
def test_the_default_models_numpy_actor_computes_its_torch_policys_logits(no_tools):
    # the shipped default decides with its numpy actor; on a shop without tools its padded tools and transporter
    # blocks have no rows (no embedding, a zero context), as the torch policy's masked mean makes them
    from fms_dispatch.rl.agent import Agent
    from fms_dispatch.rl.guide import effort_from
    from fms_dispatch.rl.models import default_model_name, load_agent
    from fms_sim.formats import load_instance

    inst = load_instance("ra01", no_tools=no_tools)
    assert inst.has_tools != no_tools
    agent = load_agent(default_model_name(inst))
    ref = Agent(agent.path, agent.padding, torch=True, decisions=agent.decisions, guide=agent.guide)
    effort = effort_from(restarts=0, tabu=0)
    agent.use_guide_effort(effort)
    ref.use_guide_effort(effort)
    shop = FullShop(inst)
    compared = 0
    while not shop.done:
        if len(shop.legal_actions()) > 1:
            fast, mask = agent.logits(shop, fast=True)
            slow, _ = ref.logits(shop, fast=False)
            assert np.array_equal(np.isfinite(fast), mask) and np.allclose(fast[mask], slow[mask], atol=1e-4)
            compared += 1
        shop.act(agent.act(shop))
    assert compared > 20


def test_a_plain_run_that_ends_after_its_plan_names_the_plan_and_the_lookahead(capsys, tmp_path):
    """A guided run records the makespan of the plan it acted out; where a plain nominal run ends later (it leaves
    out the plan's empty trips), fms solve says so on stderr and names --lookahead-guide, whose run ends at the
    plan. Not with -q, not in a disrupted run (its plan in force is a forecast), not with the lookahead."""
    from fms_dispatch.cli import main

    out = tmp_path / "s.json"
    args = ["solve", "EX24", "--solver", "ppo", "--guide-tabu", "0", "--out", str(out)]  # a reproducible plan search
    assert main(args) == 0
    meta = json.loads(out.read_text())["meta"]
    plain, planned = json.loads(out.read_text())["makespan"], meta["guide_plan_makespan"]
    assert plain > planned  # on this shop the plain run misses two of the plan's empty trips
    err = capsys.readouterr().err
    assert f"EX24: the model's plan ends at {planned}; --lookahead-guide sends idle vehicles on the plan's empty " \
           "trips, which a plain run leaves out" in err
    assert main(args + ["--lookahead-guide"]) == 0
    again = json.loads(out.read_text())
    assert again["makespan"] == again["meta"]["guide_plan_makespan"] == planned
    assert "plan ends at" not in capsys.readouterr().err
    assert main(args + ["-q"]) == 0 and capsys.readouterr().err == ""
    assert main(args + ["--noise", "0.1", "--seed", "1"]) == 0
    noisy = json.loads(out.read_text())
    assert noisy["makespan"] > noisy["meta"]["guide_plan_makespan"]  # later than its plan, but disrupted: no hint
    assert "plan ends at" not in capsys.readouterr().err
    assert main(["solve", "EX24", "--solver", "ppo:bu", "--out", str(out), "-q"]) == 0  # no guide, no plan
    assert "guide_plan_makespan" not in json.loads(out.read_text())["meta"]


def test_an_outage_re_plans_the_guide_around_the_vehicle_out_of_service():
    # outages were no trigger: the guide kept routing carries through AGV 0 and the model waited out its window
    # (EX12: 100,134); after an outage the new plan is put in force whatever it promises (the plan in force, re-timed
    # by a list schedule free to choose other vehicles, looked as good)
    from fms_dispatch.solvers import solve
    from fms_sim.disruptions import Outage, Scenario

    inst = builtin("EX12")
    sc = Scenario(outages=(Outage("agv", 0, 14, 100_000),))
    s = solve(inst, "ppo", scenario=sc)
    assert validate(inst, s, sc) == [] and s.makespan < 1000
    assert [(e["reason"], e["status"]) for e in s.meta["replans"]][0] == ("outage", "adopted")
    kept = solve(inst, "ppo", scenario=sc, guide_replan=False)  # (the start's plan acted out: the window waited out)
    assert kept.makespan > 100_000


def test_a_reset_first_seen_after_its_start_plans_its_own_guide():
    """An episode whose first decision comes after time 0 (its only machine broken down from time 0) is observed
    after its start: its guide is a plan from its state, whatever the env ran before. The env kept the previous
    episode's plan from scratch, so the same reset gave other observations than a fresh env's."""
    from fms_dispatch.rl.envs import FastShopEnv
    from fms_dispatch.rl.guide import at_start
    from fms_sim.disruptions import Breakdown, Scenario
    from fms_sim.instance import Instance, Operation

    inst = Instance(name="g", jobs=((Operation(2, None, 14),), (Operation(2, None, 17), Operation(1, None, 1))),
                    n_machines=2)
    late = Scenario((Breakdown(machine=2, start=0, duration=5),), (), 0.0, 0)
    used = FastShopEnv(inst, guide="list", decisions="full")
    used.reset(seed=0)  # a run from its start: a plan from scratch
    assert used.plan_guide().origin is None
    obs, _ = used.reset(seed=0, options={"scenario": late})
    assert not at_start(used.shop)
    fresh = FastShopEnv(inst, guide="list", decisions="full")
    want, _ = fresh.reset(seed=0, options={"scenario": late})
    assert fresh.plan_guide().origin is not None  # a plan from the state
    assert used.plan_guide().origin == fresh.plan_guide().origin
    assert np.array_equal(obs, want)


def _assignment_run(agent, inst, assign):
    """A run of ``agent`` (its plan: the list schedule) with or without the plan's assignments: (schedule, the
    assignments taken, the states where the network was asked about an assignment and chose otherwise)."""
    from fms_sim.full_shop import make_shop
    from fms_dispatch.rl.guide import PlanEffort

    agent.forget()
    agent.use_guide_effort(PlanEffort())
    agent.plan_assigns = assign
    shop = make_shop(inst, agent.decisions)
    n0, other = agent.assigned, 0
    while not shop.done:
        legal = shop.legal_actions()
        planned = agent.plan_assignment(shop, legal) if len(legal) > 1 else None
        if planned is not None:
            logits, _ = agent.logits(shop)
            other += agent._env(shop).to_net_action(int(np.argmax(logits))) != planned
        shop.act(agent.act(shop))
    return shop.schedule(), agent.assigned - n0, other


@pytest.mark.parametrize("name,least", [("EX22", 2), ("sl00", 400)])
def test_a_guided_model_takes_its_plans_assignments_as_its_network_would(name, least):
    # the vehicle and tool-use choices the plan answers are those the network makes: the same schedule, the
    # network's arg-max equal to the plan's answer at every one, and only the run with them counts them
    from fms_dispatch.rl.models import load_agent

    inst = builtin(name)
    agent = load_agent("guided-dagger")
    try:
        plain, n_plain, _ = _assignment_run(agent, inst, False)
        fast, n_fast, other = _assignment_run(agent, inst, True)
    finally:
        agent.plan_assigns = True
        agent.use_guide_effort(None)
    assert validate(inst, fast) == [] and fast.operations == plain.operations
    assert n_plain == 0 and n_fast >= least and other == 0


def test_the_plans_assignment_is_only_a_legal_planned_carrier_or_use():
    from fms_sim.full_shop import make_shop
    from fms_dispatch.rl.guide import PlanEffort
    from fms_dispatch.rl.models import load_agent

    inst = builtin("sl00")
    agent = load_agent("guided-dagger")
    agent.forget()
    agent.use_guide_effort(PlanEffort())
    try:
        shop = make_shop(inst, "full")
        kinds_seen, moved = set(), False
        while not shop.done:
            legal = shop.legal_actions()
            kind = shop.action_kind(legal[0])[0]
            a = agent.plan_assignment(shop, legal)
            if kind not in ("agv", "tt", "use"):
                assert a is None  # a dispatch, a start, a take-up, a hold: the network decides
            elif a is not None:
                kinds_seen.add(kind)
                assert a in legal
                guide = agent.guide_of(shop)
                if kind == "use":
                    assert shop.action_kind(a)[1] == guide.use_head(guide.view(shop))
                else:
                    assert shop.action_kind(a)[1] == guide.planned_vehicle(shop, kind)
                    busy = [v for v in range(shop.n_agvs if kind == "agv" else shop.n_tts)
                            if shop.action_index(f"{kind}:{v}") not in legal]
                    if kind == "agv" and busy and not moved:  # the plan names a vehicle that is not offered now
                        req = shop.awaiting_agv()
                        saved = guide.part_carrier[req[0], req[1]]
                        guide.part_carrier[req[0], req[1]] = busy[0]
                        assert agent.plan_assignment(shop, legal) is None
                        guide.part_carrier[req[0], req[1]] = saved
                        moved = True
            shop.act(agent.act(shop))
        assert kinds_seen == {"agv", "tt", "use"} and moved
    finally:
        agent.use_guide_effort(None)
    full = load_agent("full")  # a model without a guide: no plan to assign from
    shop = make_shop(inst, "full")
    while shop.action_kind(shop.legal_actions()[0])[0] != "agv":
        shop.act(shop.legal_actions()[0])
    assert full.plan_assignment(shop) is None and not full.plan_assigns


def test_a_solve_counts_the_plans_assignments(tmp_path):
    from fms_dispatch.rl.guide import effort_from
    from fms_dispatch.solvers import solve

    sched = solve(builtin("sl00"), "ppo", guide_effort=effort_from(restarts=4, budget=0, tabu=0))
    assert validate(builtin("sl00"), sched) == [] and sched.meta["plan_assignments"] > 100
    assert "plan_assignments" not in solve(builtin("EX22"), "ppo:full").meta
