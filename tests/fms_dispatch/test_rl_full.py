"""Policies on the full-decision net: the entity network's full heads, plan experts, DAgger and training."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from fms_sim.benchmarks import builtin
from fms_sim.full_shop import FullShop
from fms_sim.shop import Shop
from fms_sim.validate import validate
from fms_dispatch.rl.actors import load_actor, save_actor
from fms_dispatch.rl.envs import FastShopEnv, obs_layout, obs_size, padding_for
from fms_dispatch.full_rules import run_full
from fms_dispatch.rl.plan_expert import PlanPriorityPolicy, expert_plan, plan_dagger_round, plan_demonstrations
from fms_dispatch.rl.policy import EntityPolicy, actor_from_policy


def _model(inst, padding, hidden=32):
    from sb3_contrib import MaskablePPO
    from stable_baselines3.common.vec_env import DummyVecEnv

    env = FastShopEnv(inst, decisions="full", **padding)
    return MaskablePPO(EntityPolicy, DummyVecEnv([lambda: env]), device="cpu", seed=3, n_steps=64, batch_size=32,
                       policy_kwargs={"layout": obs_layout(padding, "full"), "hidden": hidden})


@pytest.mark.parametrize("name,padding", [("EX12", "bu"), ("ra01", None), ("ra01", "large")])
def test_full_entity_network_numpy_actor_equals_torch_and_covers_every_block(name, padding, tmp_path):
    inst = builtin(name)
    pad = padding_for(padding, [inst])
    model = _model(inst, pad)
    demos, _ = plan_demonstrations([inst], pad, "shaped", "plan:list")
    lay = obs_layout(pad, "full")
    assert demos["obs"].shape[1] == obs_size(lay) == FastShopEnv(inst, decisions="full", **pad).observation_space.shape[0]
    ext = model.policy.mlp_extractor
    assert ext.latent_dim_pi == FastShopEnv(inst, decisions="full", **pad).n_actions
    actor = actor_from_policy(model.policy)
    path = save_actor(actor, tmp_path / "a.actor.npz", "sha")
    loaded, sha = load_actor(path)
    assert sha == "sha"
    X = torch.as_tensor(demos["obs"])
    with torch.no_grad():
        ref = ext.forward_actor(X).numpy()
    kinds = set()
    env = FastShopEnv(inst, decisions="full", **pad)
    env.reset(options={"instance": inst})
    for i in range(len(X)):
        m = demos["mask"][i]
        for a in (actor, loaded):
            got = a.logits(demos["obs"][i], m)
            assert np.allclose(got[m], ref[i][m], atol=1e-4)
            assert np.all(np.isneginf(got[~m]))
        kinds.update(env.shop.action_kind(env.to_net_action(int(x)))[0] for x in np.flatnonzero(m))
    # the demonstrations exercise the full net's own decisions, not only dispatching
    assert {"start", "job"} <= kinds and ("tool" in kinds) == inst.has_tools


def test_plan_demonstrations_follow_the_plan_and_return_exact_returns():
    inst = builtin("ra01")
    pad = padding_for(None, [inst])
    plan = expert_plan(inst, "plan:cpsat:2")
    plans: dict = {}
    demos, ms = plan_demonstrations([inst], pad, "shaped", "plan:cpsat:2", plans=plans)
    assert plan.makespan == plans["ra01"].makespan  # same expert, same seed: same plan
    acted = run_full(inst, PlanPriorityPolicy(plans["ra01"]))
    assert validate(inst, acted) == [] and ms["ra01"] == acted.makespan
    # its choices follow the plan: a start goes to the buffered job planned first, a tool to the job planned first
    shop, policy, checked = FullShop(inst), PlanPriorityPolicy(plans["ra01"]), 0
    planned = {(r.job, r.op): r.start for r in plans["ra01"].operations}
    while not shop.done:
        a = policy(shop)
        kind, j = shop.action_kind(a)
        legal = [shop.action_kind(x) for x in shop.legal_actions()]
        if kind == "start":
            others = [n for k, n in legal if k == "start"]
            assert planned[j, shop.buffered_op(j)[0]] == min(planned[n, shop.buffered_op(n)[0]] for n in others)
            checked += 1
        elif kind == "use":
            t = shop.tool_choice
            assert planned[j, shop.request_of(t, j)] == min(planned[n, shop.request_of(t, n)] for k, n in legal)
            checked += 1
        shop.act(a)
    assert checked > 20 and shop.makespan == acted.makespan
    n = len(demos["obs"])
    assert n == len(demos["mask"]) == len(demos["action"]) == len(demos["ret"]) > 10
    assert all(demos["mask"][i][demos["action"][i]] and demos["mask"][i].sum() > 1 for i in range(n))
    # shaped returns telescope: the first is -(makespan - LB_0) / scale, and they never decrease
    env = FastShopEnv(inst, decisions="full", **pad)
    env.reset(options={"instance": inst})
    assert demos["ret"][0] == pytest.approx(-(ms["ra01"] - env.potential()) / env._scale, abs=1e-5)
    assert np.all(np.diff(demos["ret"]) >= -1e-6)
    mk, _ = plan_demonstrations([inst], pad, "makespan", "plan:list")
    assert np.allclose(mk["ret"], mk["ret"][0]) and mk["ret"][0] < 0
    idle, _ = plan_demonstrations([inst], pad, "idle", "plan:list")
    assert np.all(np.isnan(idle["ret"]))


class _FirstLegal:
    """A stand-in policy that always takes the lowest legal action (it leaves any plan at once)."""

    def predict(self, obs, action_masks, deterministic=True):
        return np.array(int(np.flatnonzero(action_masks)[0])), None


@pytest.mark.parametrize("name", ["EX12", "ra01"])
def test_dagger_labels_every_state_of_the_policy_with_a_legal_plan_action(name):
    inst = builtin(name)
    pad = padding_for(None, [inst])
    plans: dict = {}
    plan_demonstrations([inst], pad, "shaped", "plan:list", plans=plans)
    rows, pm, _ = plan_dagger_round(_FirstLegal(), [inst], plans, pad, "shaped")
    assert len(rows["obs"]) > 0 and all(rows["mask"][i][rows["action"][i]] for i in range(len(rows["obs"])))
    assert pm[name] > 0


def test_dagger_in_disrupted_runs_labels_the_policys_states_and_runs_the_expert_in_the_same_scenario():
    from fms_dispatch.rl.plan_expert import expert_policy
    from fms_sim.env import check_disruptions, episode_scenario

    insts = [builtin("ra01"), builtin("EX12")]
    pad = padding_for(None, insts)
    plans: dict = {}
    _, nominal = plan_demonstrations(insts, pad, "shaped", "plan:list", plans=plans)
    d = check_disruptions({"noise": 0.3, "breakdowns": 1})
    rows, pm, em = plan_dagger_round(_FirstLegal(), insts, plans, pad, "shaped", disruptions=d,
                                     rng=np.random.default_rng(5))
    assert all(rows["mask"][i][rows["action"][i]] for i in range(len(rows["obs"])))
    again, pm2, em2 = plan_dagger_round(_FirstLegal(), insts, plans, pad, "shaped", disruptions=d,
                                        rng=np.random.default_rng(5))
    assert pm2 == pm and em2 == em and np.array_equal(again["action"], rows["action"])  # seeded scenarios
    rng = np.random.default_rng(5)
    for inst in insts:  # the expert's makespan is its run in the policy's scenario, which differs from nominal
        sc = episode_scenario(inst, d, rng)
        shop = FullShop(inst, scenario=sc)
        expert = expert_policy(inst, plans[inst.name])
        while not shop.done:
            shop.act(expert(shop))
        assert em[inst.name] == shop.makespan
    assert em != nominal
    _, _, none = plan_dagger_round(_FirstLegal(), insts, plans, pad, "shaped")
    assert none == {}  # nominal rounds compare with the demonstrations' makespans


def test_dagger_from_a_trained_models_weights_in_disrupted_shops(tmp_path):
    """``init`` with a warm-start expert and DAgger rounds: no fresh clone, the rounds start from the given
    weights in disrupted runs; the model records the initial model's training shops and no PPO steps."""
    from sb3_contrib import MaskablePPO

    from fms_dispatch.rl.train import train

    base = {"eval": ["gen:6x3x3*1@8"], "decisions": "full", "guide": "list", "n_envs": 1, "vec_env": "dummy",
            "hidden": 16, "eval_freq": 64, "save_freq": 64, "ppo": {"n_steps": 64, "batch_size": 32, "n_epochs": 1}}
    first = tmp_path / "first"
    train({**base, "train": ["gen:6x3x3*2@7"], "steps": 64}, first, progress=False)
    out = tmp_path / "dagger"
    m = train({**base, "train": ["gen:6x3x3*2@9"], "steps": 0, "init": str(first),
               "disruptions": {"noise": 0.3, "breakdowns": 1},
               "warm_start": {"expert": "guide", "dagger": 1, "dagger_epochs": 1}}, out, progress=False)
    assert m["ppo_steps"] == 0 and m["warm_start"]["init"] == str(first)
    assert len(m["warm_start"]["dagger_rounds"]) == 1 and "accuracy" not in m["warm_start"]  # no fresh clone
    assert "epochs" not in m["warm_start"]
    assert set(m["training_shops"]) == {"gen6x3s7_00", "gen6x3s7_01", "gen6x3s9_00", "gen6x3s9_01"}
    src = MaskablePPO.load(str(first / "best_model.zip"), device="cpu").policy.state_dict()
    after = MaskablePPO.load(str(out / "warm_start.zip"), device="cpu").policy.state_dict()
    assert any(not torch.equal(after[k], src[k]) for k in src)  # the DAgger round trained the initial weights
    # a resume continues its own weights: the initial model need not be where it was (it had to resolve from here)
    first.rename(tmp_path / "moved")
    m2 = train({"steps": 64}, out, resume=True, progress=False)
    assert m2["ppo_steps"] == 64 and m2["training_shops"] == m["training_shops"]


def test_train_on_the_full_net_with_a_plan_expert_dagger_and_ppo(tmp_path, capsys):
    from fms_dispatch.rl import ppo_solver
    from fms_dispatch.rl.lookahead import run_agent
    from fms_dispatch.rl.models import load_agent
    from fms_dispatch.rl.train import expand_instances, train

    out = tmp_path / "full"
    cfg = {"train": ["gen:8x4x3*3@7"], "eval": ["gen:8x4x3*1@8"], "decisions": "full", "steps": 128,
           "n_envs": 1, "vec_env": "dummy", "hidden": 16, "eval_freq": 64, "save_freq": 64,
           "warm_start": {"expert": "plan:list", "epochs": 5, "dagger": 1, "dagger_epochs": 2},
           "ppo": {"n_steps": 64, "batch_size": 32}}
    m = train(cfg, out, progress=False)
    saved = json.loads((out / "config.json").read_text())
    assert saved["decisions"] == "full" and m["training"]["timesteps"] >= 128
    assert m["ppo_steps"] == m["training"]["timesteps"] and m["training_shops"] == [f"gen8x4s7_{k:02d}" for k in range(3)]
    assert (out / "warm_start.zip").is_file() and (out / "warm_start.actor.npz").is_file()  # the clone before PPO
    assert len(m["warm_start"]["dagger_rounds"]) == 1 and set(m["warm_start"]["expert_makespan"]) == {
        f"gen8x4s7_{k:02d}" for k in range(3)}
    agent = load_agent(str(out))
    assert agent.decisions == "full" and not agent.uses_torch  # the numpy export covers the full heads
    (inst,) = expand_instances(["gen:8x4x3*1@9"])
    plain = ppo_solver(f"ppo:{out}")(inst)
    assert plain.meta["decisions"] == "full" and validate(inst, plain) == []
    ahead = ppo_solver(f"ppo:{out}")(inst, lookahead=True)
    assert validate(inst, ahead) == [] and ahead.makespan <= plain.makespan  # verified moves only
    # the agent never decides through the wrong net
    with pytest.raises(ValueError, match="full net, not through a Shop"):
        run_agent(Shop(inst), agent.act)


def test_full_net_training_refuses_experts_of_the_other_net(tmp_path):
    from fms_dispatch.rl.train import train

    base = {"train": ["gen:8x4x3*1@7"], "steps": 0, "n_envs": 1, "vec_env": "dummy"}
    with pytest.raises(ValueError, match="on the full net use a plan expert"):
        train({**base, "decisions": "full", "warm_start": {"expert": "rules"}}, tmp_path / "a", progress=False)
    with pytest.raises(ValueError, match="set decisions to full"):
        train({**base, "warm_start": {"expert": "plan:list"}}, tmp_path / "b", progress=False)
    with pytest.raises(ValueError, match="unknown decisions"):
        train({**base, "decisions": "fifo", "warm_start": {"expert": "plan:list"}}, tmp_path / "c", progress=False)


def test_ppo_fine_tuning_from_a_trained_model_in_disrupted_shops(tmp_path):
    """``init`` starts PPO from another model's weights (kept as warm_start.zip, the baseline PPO must beat);
    ``disruptions`` trains in disrupted shops and evaluates each evaluation shop in a fixed scenario;
    ``guide_effort`` searches the guided plans."""
    from sb3_contrib import MaskablePPO

    from fms_dispatch.rl.train import expand_instances, evaluate_model, train
    from fms_sim.env import episode_scenario

    base = {"train": ["gen:6x3x3*2@7"], "eval": ["gen:6x3x3*1@8"], "decisions": "full", "guide": "list",
            "n_envs": 1, "vec_env": "dummy", "hidden": 16, "eval_freq": 64, "save_freq": 64,
            "ppo": {"n_steps": 64, "batch_size": 32, "n_epochs": 1}}
    first = tmp_path / "first"
    train({**base, "steps": 64}, first, progress=False)
    out = tmp_path / "tuned"
    disruptions = {"noise": 0.3, "breakdowns": 1}
    m = train({**base, "steps": 128, "init": str(first), "disruptions": disruptions,
               "guide_effort": {"restarts": 2}}, out, progress=False)
    assert m["warm_start"]["init"] == str(first) and m["ppo_steps"] == m["training"]["timesteps"] >= 128
    start = MaskablePPO.load(str(out / "warm_start.zip"), device="cpu").policy.state_dict()
    src = MaskablePPO.load(str(first / "best_model.zip"), device="cpu").policy.state_dict()
    assert all(torch.equal(start[k], src[k]) for k in src)  # PPO started from the given weights
    saved = json.loads((out / "config.json").read_text())
    assert saved["disruptions"] == disruptions and saved["init"] == str(first)
    # the evaluation makespans are those of the fixed scenarios (validated against them)
    (inst,) = expand_instances(["gen:6x3x3*1@8"])
    pad = padding_for("auto", expand_instances(base["train"] + base["eval"]))
    from fms_dispatch.rl.guide import PlanEffort

    again = evaluate_model(out / m["training"]["weights"], pad, [inst], decisions="full", guide="list",
                           guide_effort=PlanEffort(restarts=2), disruptions=disruptions)
    assert again == m["training"]["eval_makespan"]
    fixed = episode_scenario(inst, {"noise": 0.3, "breakdowns": 1, "fixed": True, "seed": 0})
    assert fixed.noise == 0.3 and len(fixed.breakdowns) == 1


def test_fine_tuning_options_are_checked(tmp_path):
    from fms_dispatch.rl.train import train

    base = {"train": ["gen:6x3x3*1@7"], "decisions": "full", "guide": "list", "steps": 64, "n_envs": 1,
            "vec_env": "dummy", "hidden": 16}
    with pytest.raises(ValueError, match="replaces the cloning of a warm-start expert"):
        train({**base, "init": str(tmp_path), "warm_start": {"expert": "guide"}}, tmp_path / "a", progress=False)
    with pytest.raises(ValueError, match="run the DAgger rounds first"):
        train({**base, "init": str(tmp_path), "baseline": "init", "warm_start": {"expert": "guide", "dagger": 1}},
              tmp_path / "a2", progress=False)
    with pytest.raises(ValueError, match="no weights"):
        train({**base, "init": str(tmp_path / "none")}, tmp_path / "b", progress=False)
    with pytest.raises(ValueError, match="bad guide_effort"):
        train({**base, "guide_effort": {"restarts": -1}}, tmp_path / "c", progress=False)
    with pytest.raises(ValueError, match="bad guide_effort"):
        train({**base, "guide_effort": {"tries": 3}}, tmp_path / "d", progress=False)
    with pytest.raises(ValueError, match="set guide to list"):
        train({**base, "guide": None, "guide_effort": {"restarts": 2}}, tmp_path / "e", progress=False)
    with pytest.raises(ValueError, match="unknown disruption keys"):
        train({**base, "disruptions": {"storms": 1}}, tmp_path / "f", progress=False)
    other = tmp_path / "other"  # weights of another layout (more jobs) do not fit
    train({**base, "train": ["gen:9x3x3*1@7"]}, other, progress=False)
    with pytest.raises(ValueError, match="another layout: its padding .*'max_jobs': 9.*, this run's .*'max_jobs': "):
        train({**base, "init": str(other)}, tmp_path / "g", progress=False)  # (what differs was not said)
    assert not (tmp_path / "g").exists()  # refused before the folder is made (it was left empty)
    (tmp_path / "g").mkdir()
    first = {p.name: p.read_bytes() for p in other.iterdir() if p.is_file()}
    # fine-tuning in place: --force removed the model in the way first (its recorded shops with it), and the config
    # named the folder's new weights as the initial ones
    with pytest.raises(ValueError, match="is the model folder being trained: fine-tune into another folder"):
        train({**base, "init": str(other)}, other, progress=False, force=True)
    assert {p.name: p.read_bytes() for p in other.iterdir() if p.is_file()} == first


def test_relative_returns_score_the_reference_zero_and_fine_tuning_uses_them(tmp_path):
    """With ``baseline: init`` an episode's return is (reference makespan - makespan) / scale: the reference
    weights themselves score exactly 0 on every episode, disrupted or not."""
    from fms_dispatch.rl.agent import Agent
    from fms_dispatch.rl.envs import FastShopEnv
    from fms_dispatch.rl.guide import PlanEffort
    from fms_dispatch.rl.relative import RelativeReturn
    from fms_dispatch.rl.train import expand_instances, train

    base = {"train": ["gen:6x3x3*2@7"], "eval": ["gen:6x3x3*1@8"], "decisions": "full", "guide": "list",
            "n_envs": 1, "vec_env": "dummy", "hidden": 16, "eval_freq": 64, "save_freq": 64,
            "ppo": {"n_steps": 64, "batch_size": 32, "n_epochs": 1}}
    first = tmp_path / "first"
    train({**base, "steps": 64}, first, progress=False)
    insts = expand_instances(base["train"] + base["eval"])
    pad = padding_for("auto", insts)
    ref = Agent(first / "model.zip", pad, decisions="full", guide="list")
    ref.use_guide_effort(PlanEffort(restarts=2))
    me = Agent(first / "model.zip", pad, decisions="full", guide="list")
    me.use_guide_effort(PlanEffort(restarts=2))
    for disruptions in (None, {"noise": 0.3, "breakdowns": 1}):
        env = RelativeReturn(FastShopEnv(insts, decisions="full", guide="list", guide_effort=PlanEffort(restarts=2),
                                         disruptions=disruptions, **pad), ref)
        for seed in (1, 2):
            _, info = env.reset(seed=seed)
            total, done = 0.0, False
            while not done:
                a = env.unwrapped.from_net_action(me.act(env.unwrapped.shop))
                _, r, done, _, step_info = env.step(a)
                total += r
            assert step_info["makespan"] == info["reference_makespan"]  # the same weights, the same episode
            assert abs(total) < 1e-9
    with pytest.raises(ValueError, match="shaped reward"):
        RelativeReturn(FastShopEnv(insts, decisions="full", reward="makespan", **pad), ref)
    # in training: the initial weights are the baseline, so their evaluation reward is 0
    out = tmp_path / "tuned"
    m = train({**base, "steps": 64, "init": str(first), "baseline": "init",
               "disruptions": {"noise": 0.3, "breakdowns": 1}}, out, progress=False)
    assert m["warm_start"]["mean_reward"] == 0.0
    with pytest.raises(ValueError, match="set init"):
        train({**base, "steps": 64, "baseline": "init"}, tmp_path / "x", progress=False)
    with pytest.raises(ValueError, match="unknown baseline"):
        train({**base, "steps": 64, "init": str(first), "baseline": "rules"}, tmp_path / "y", progress=False)
