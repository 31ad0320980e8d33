"""The Gymnasium environment: API checks, masks, padding, rewards, invalid actions."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env

import fms_sim  # noqa: F401  (registers fms/Shop-v0)
from fms_sim import Schedule, validate
from fms_sim.benchmarks import builtin
from fms_sim.env import ShopEnv
from fms_sim.petri import InvalidAction


def rollout(env, rng, seed=0):
    obs, info = env.reset(seed=seed)
    total, done = 0.0, False
    while not done:
        mask = env.action_masks()
        assert np.array_equal(mask, info["action_mask"]) and mask.any()
        assert env.observation_space.contains(obs)
        a = int(rng.choice(np.flatnonzero(mask)))
        obs, r, done, trunc, info = env.step(a)
        total += r
    return total, info


@pytest.mark.parametrize("name", ["EX12", "ra01"])
def test_gymnasium_check_env(name):
    env = ShopEnv(builtin(name))
    gym_check_env(env, skip_render_check=True)


def test_sb3_check_env():
    sb3 = pytest.importorskip("stable_baselines3.common.env_checker")
    sb3.check_env(ShopEnv(builtin("ra01"), reward="idle"), warn=True)


def test_registered_with_gym_make():
    env = gym.make("fms/Shop-v0", instances=builtin("EX12"))
    obs, info = env.reset(seed=3)
    assert obs.shape == env.observation_space.shape


def test_episode_yields_valid_schedule_and_shaped_reward_telescopes():
    inst = builtin("ra01")
    env = ShopEnv(inst, reward="shaped")
    total, info = rollout(env, np.random.default_rng(1))
    s = env.shop.schedule()
    assert validate(inst, s) == [] and info["makespan"] == s.makespan
    lb0 = env._lb0
    assert total == pytest.approx(-(s.makespan - lb0) / env._scale, rel=1e-6)


def test_sparse_makespan_reward():
    inst = builtin("EX12")
    env = ShopEnv(inst, reward="makespan")
    total, info = rollout(env, np.random.default_rng(2))
    assert total == pytest.approx(-info["makespan"] / env._scale)


def test_idle_reward_is_minus_idle_fraction_per_step():
    inst = builtin("EX12")
    env = ShopEnv(inst, reward="idle")
    env.reset(seed=0)
    a = int(np.flatnonzero(env.action_masks())[0])
    _, r, done, _, _ = env.step(a)
    assert not done and r == pytest.approx(-env.shop.idle_machines() / inst.n_machines)
    assert -1.0 <= r <= 0.0


def test_padding_one_policy_shape_serves_smaller_instances():
    big, small = builtin("sl00"), builtin("ra01")
    env = ShopEnv([big, small], max_jobs=20, max_machines=20, max_tools=20, max_agvs=10, max_tts=5)
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=0, options={"instance": small})
    mask = env.action_masks()
    assert mask.shape == (35,)
    assert not mask[small.n_jobs:20].any()                  # padded job slots are masked
    assert not mask[20 + small.n_agvs:30].any() and not mask[30 + 1:].any()
    while not env.shop.done:
        env.step(int(rng.choice(np.flatnonzero(env.action_masks()))))
    assert validate(small, env.shop.schedule()) == []
    obs2, _ = env.reset(seed=0, options={"instance": big})
    assert obs.shape == obs2.shape


def test_too_large_instance_is_rejected():
    with pytest.raises(ValueError, match="more than this env's maximum"):
        ShopEnv(builtin("sl00"), max_jobs=10)


def test_invalid_action_raises_or_ends_with_penalty():
    env = ShopEnv(builtin("EX12"), invalid_action="raise")
    env.reset(seed=0)
    bad = int(np.flatnonzero(~env.action_masks())[0])
    with pytest.raises(InvalidAction, match="not allowed"):
        env.step(bad)
    env2 = ShopEnv(builtin("EX12"), invalid_action="penalty", invalid_penalty=-5)
    env2.reset(seed=0)
    _, r, done, _, info = env2.step(bad)
    assert done and r == -5 and info["invalid_action"]


def test_unknown_reward_rejected():
    with pytest.raises(ValueError, match="unknown reward"):
        ShopEnv(builtin("EX12"), reward="bogus")


def test_reset_seed_reproducible_instance_draw():
    insts = [builtin(n) for n in ("EX12", "EX22", "EX32")]
    env = ShopEnv(insts)
    names = [env.reset(seed=s)[1] and env.instance.name for s in range(5)]
    again = [env.reset(seed=s)[1] and env.instance.name for s in range(5)]
    assert names == again
