"""The Gymnasium environment: API checks, masks, padding, rewards, invalid actions."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env as gym_check_env

import fms_sim  # noqa: F401  (registers fms/Shop-v0)
from fms_sim import validate
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


def test_idle_reward_on_the_full_net_counts_the_machines_processing_nothing():
    # the full net had no idle_machines: the paper's reward crashed on the first step (and fms train with it)
    inst = builtin("ra01")
    env = ShopEnv(inst, decisions="full", reward="idle")
    env.reset(seed=0)
    rng, rewards = np.random.default_rng(1), []
    while True:
        _, r, done, _, _ = env.step(int(rng.choice(np.flatnonzero(env.action_masks()))))
        shop = env.shop
        if done:
            break
        running = {o.machine for o in shop.rec.ops if o.start <= shop.now < o.end}
        assert shop.idle_machines() == inst.n_machines - len(running)
        assert r == pytest.approx(-shop.idle_machines() / inst.n_machines)
        rewards.append(r)
    assert min(rewards) < max(rewards) <= 0.0


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
    # as after a normal end, nothing is offered: the shop's legal actions were, and step refused each
    assert not env2.action_masks().any() and not info["action_mask"].any()
    with pytest.raises(RuntimeError, match="episode has ended"):
        env2.step(bad)


@pytest.mark.parametrize("decisions", ["paper", "full"])
def test_step_after_the_end_raises_until_reset(decisions):
    # a finished episode answered a step as an invalid action (-10, as if the shop could go on)
    env = ShopEnv(builtin("EX12"), decisions=decisions, invalid_action="penalty")
    rollout(env, np.random.default_rng(0))
    with pytest.raises(RuntimeError, match="episode has ended; call reset"):
        env.step(0)
    env.reset(seed=1)
    _, _, done, _, _ = env.step(int(np.flatnonzero(env.action_masks())[0]))
    assert not done


@pytest.mark.parametrize("args, kwargs, error, msg", [
    (("EX12",), {}, TypeError, "not the name 'EX12'"),
    ((["EX12"],), {}, TypeError, "takes Instance objects, got str"),
    ((None,), {"max_jobs": 0, "max_machines": 4, "max_tools": 0, "max_agvs": 1, "max_tts": 0}, ValueError,
     "max_jobs must be an integer >= 1"),
    ((None,), {"max_jobs": 7.5}, ValueError, "max_jobs must be an integer >= 1 .*got 7.5"),
    ((None,), {"max_machines": 0}, ValueError, "max_machines must be an integer >= 1"),
    ((None,), {"max_agvs": -1}, ValueError, "max_agvs must be an integer >= 0"),
])
def test_bad_instances_and_sizes_are_refused_by_name(args, kwargs, error, msg):
    # a name was an AttributeError, max_jobs=0 was quietly replaced (and with a sampler an error from max()),
    # 7.5 a TypeError from numpy
    if args == (None,):
        args = ((lambda rng: builtin("EX12")) if kwargs.get("max_jobs") == 0 else builtin("EX12"),)
    with pytest.raises(error, match=msg):
        ShopEnv(*args, **kwargs)
    env = ShopEnv(builtin("EX12"), max_jobs=np.int64(12))
    assert env.max_jobs == 12 and type(env.max_jobs) is int


def test_unknown_reward_rejected():
    with pytest.raises(ValueError, match="unknown reward"):
        ShopEnv(builtin("EX12"), reward="bogus")


def test_reset_seed_reproducible_instance_draw():
    insts = [builtin(n) for n in ("EX12", "EX22", "EX32")]
    env = ShopEnv(insts)
    names = [env.reset(seed=s)[1] and env.instance.name for s in range(5)]
    again = [env.reset(seed=s)[1] and env.instance.name for s in range(5)]
    assert names == again


# ---------------------------------------------------------------------------------------------------------
# A slow, obviously-correct reference for the table-driven features: per job and machine, straight from the
# instance and the shop. The env's numpy version must give the same values bit for bit.
from fms_sim.env import (GLOBAL_FEATURES, JOB_FEATURES, MACHINE_FEATURES, OBS_HIGH,  # noqa: E402
                         TOOL_FEATURES)


def reference_lower_bound(self) -> int:
    s, inst = self.shop, self.instance
    now = s.now
    lb = max(now, s.makespan)
    machine_load = [0] * (inst.n_machines + 1)
    for j, ops in enumerate(inst.jobs):
        k = s.next_op(j)
        rem = 0
        for op in ops[k:]:
            machine_load[op.machine] += op.duration
            rem += op.duration
        if rem:
            lb = max(lb, now + rem)
    for m in range(1, inst.n_machines + 1):
        lb = max(lb, max(now, s.machine_busy_until[m]) + machine_load[m])
    return lb

def reference_obs(self) -> np.ndarray:
    s, inst = self.shop, self.instance
    sc = self._scale
    now = s.now
    jobs_ops = inst.jobs
    g = np.zeros(len(GLOBAL_FEATURES), dtype=np.float32)
    kinds = s.decision_kind() or ""
    g[:] = (now / sc, sum(s.job_done_ops) / self._total_ops, "job" in kinds, "agv" in kinds, "tt" in kinds,
            inst.n_jobs / self.max_jobs, inst.n_machines / self.max_machines)
    legal = set(s.legal_actions())
    req = s.awaiting_agv()
    mm = self.max_machines
    J = np.zeros((self.max_jobs, len(JOB_FEATURES)), dtype=np.float32)
    for j, ops in enumerate(jobs_ops):
        k = s.next_op(j)
        loc = s.part_location(j)
        row = J[j]
        row[0] = 1.0
        row[1] = j in legal
        row[2] = loc is not None
        if k < len(ops):
            op = ops[k]
            row[3] = op.machine / mm
            row[4] = op.duration / sc
            row[9] = (op.tool or 0) / max(1, self.max_tools)
        row[5] = sum(o.duration for o in ops[k:]) / sc
        row[6] = (len(ops) - k) / max(1, len(ops))
        row[7] = (loc if loc is not None else -1) / mm
        row[8] = (now - s.job_ready_since[j]) / sc if loc is not None else 0.0
        row[10] = req is not None and req[0] == j
    M = np.zeros((mm, len(MACHINE_FEATURES)), dtype=np.float32)
    buffers = s.p_buffer
    for m in range(1, inst.n_machines + 1):
        row = M[m - 1]
        row[0] = 1.0
        until = s.machine_busy_until[m]
        row[1] = until > now
        row[2] = max(0, until - now) / sc
        q = buffers.tokens(m)
        row[3] = len(q) / inst.n_jobs
        row[4] = sum(jobs_ops[c.colour[0]][c.colour[1]].duration for c in q) / sc
    T = np.zeros((self.max_tools, len(TOOL_FEATURES)), dtype=np.float32)
    if inst.has_tools:
        free = {c.colour[0] for c in s.p_tool_free.tokens()}
        for t in range(1, inst.n_tools + 1):
            T[t - 1] = (1.0, s.tool_loc[t] / mm, t in free)
    A = self._vehicles(self.max_agvs, s.n_agvs, s.agv_loc, s.agv_free_at, s.agv_work,
                       {c[0] for c in s.idle_agvs()}, inst.agv_travel, req[2] if req else None, now, sc, mm)
    treq = s.awaiting_transporter()
    R = self._vehicles(self.max_tts, s.n_tts, s.tt_loc, s.tt_free_at, s.tt_work,
                       {c[0] for c in s.idle_transporters()}, inst.tool_travel, treq[1] if treq else None,
                       now, sc, mm)
    obs = np.concatenate([g, J.ravel(), M.ravel(), T.ravel(), A.ravel(), R.ravel()])
    return np.clip(obs, -1.0, OBS_HIGH, out=obs)


@pytest.mark.parametrize("name, pad", [("EX12", {}), ("ra01", {}),
                                       ("ra01", dict(max_jobs=100, max_machines=20, max_tools=20, max_agvs=10,
                                                     max_tts=5))])
def test_table_features_match_the_reference(name, pad):
    inst = builtin(name)
    env = ShopEnv(inst, **pad)
    obs, _ = env.reset(seed=3)
    rng = np.random.default_rng(0)
    steps, done = 0, False
    while not done:
        assert np.array_equal(obs, reference_obs(env))
        assert env._lower_bound() == reference_lower_bound(env)
        obs, _, done, _, _ = env.step(int(rng.choice(np.flatnonzero(env.action_masks()))))
        steps += 1
    assert steps > 10


@pytest.mark.parametrize("first, then", [("EX12", "EX13"), ("EX12", "EX14"), ("EX13", "EX11")])
def test_an_env_that_ran_one_layout_observes_the_next_as_a_fresh_one(first, then):
    """The BU shops share their jobs across layouts: the tables kept for equal jobs held the previous layout's AGV
    travel times, so the full net's start estimates (and a model's decisions) depended on the shop run before."""
    a, b = builtin(first), builtin(then)
    assert a.jobs == b.jobs and a.agv_travel != b.agv_travel
    env = ShopEnv([a, b], decisions="full")
    env.reset(seed=0, options={"instance": a})
    for _ in range(8):
        env.step(int(np.flatnonzero(env.action_masks())[0]))
    fresh = ShopEnv([a, b], decisions="full")
    obs, _ = env.reset(seed=1, options={"instance": b})
    ref, _ = fresh.reset(seed=1, options={"instance": b})
    done = False
    while not done:
        assert np.array_equal(obs, ref)
        act = int(np.flatnonzero(env.action_masks())[-1])
        obs, _, done, _, _ = env.step(act)
        ref, *_ = fresh.step(act)


def test_table_features_follow_live_orders():
    from fms_sim import Operation

    env = ShopEnv(builtin("ra01"), max_jobs=8)
    env.reset(seed=0)
    for _ in range(6):
        env.step(int(np.flatnonzero(env.action_masks())[0]))
    env.shop.add_jobs([[Operation(2, 1, 5), Operation(4, 3, 7)]])
    env._total_ops = env.shop.instance.n_operations
    env.instance = env.shop.instance
    assert np.array_equal(env._obs(), reference_obs(env))
    assert env._lower_bound() == reference_lower_bound(env)


# ---------------------------------------------------------------------------------------------- full net
@pytest.mark.parametrize("name", ["EX12", "ra01"])
def test_full_decisions_pass_gymnasium_check_env(name):
    gym_check_env(ShopEnv(builtin(name), decisions="full"), skip_render_check=True)


def test_full_action_space_layout_masks_and_a_valid_episode():
    from fms_sim.env import FULL_GLOBAL_FEATURES, FULL_JOB_FEATURES, FULL_TOOL_FEATURES

    small, big = builtin("ra01"), builtin("sl00")
    env = ShopEnv([small, big], decisions="full")
    paper = ShopEnv([small, big])
    mj, ma, mr, mt = env.max_jobs, env.max_agvs, env.max_tts, env.max_tools
    assert env.n_actions == 3 * mj + ma + mr + mt + 1 == paper.n_actions + 2 * mj + mt + 1
    extra = len(FULL_GLOBAL_FEATURES) + mj * len(FULL_JOB_FEATURES) + mt * len(FULL_TOOL_FEATURES)
    assert env.observation_space.shape[0] == paper.observation_space.shape[0] + extra
    rng = np.random.default_rng(1)
    obs, info = env.reset(options={"instance": small})
    shop = env.shop
    seen = set()
    done = False
    while not done:
        mask = env.action_masks()
        legal = shop.legal_actions()
        # the env's mask is the net's, moved into the padded blocks; padded slots stay False
        assert sorted(env._to_net(int(a)) for a in np.flatnonzero(mask)) == legal
        seen.update(shop.action_kind(a)[0] for a in legal)
        a = int(rng.choice(np.flatnonzero(mask)))
        obs, _, done, _, info = env.step(a)
        assert env.observation_space.contains(obs)
    assert {"job", "agv", "tt", "start", "tool", "use", "hold"} <= seen
    assert validate(small, shop.schedule()) == []
    env.reset(options={"instance": small})
    hold = env.n_actions - 1
    assert not env.action_masks()[hold]  # nothing is in flight at time 0
    _, reward, done, _, info = env.step(hold)
    assert done and info.get("invalid_action") and reward == env.invalid_penalty


def test_unknown_decisions_rejected():
    with pytest.raises(ValueError, match="unknown decisions"):
        ShopEnv(builtin("EX12"), decisions="fifo")


def test_maskable_ppo_learns_on_the_full_action_space():
    # the full net's env works with sb3-contrib's MaskablePPO end to end (a few hundred steps, then a
    # deterministic masked episode that yields a valid schedule)
    sb3c = pytest.importorskip("sb3_contrib")
    inst = builtin("ra01")
    env = ShopEnv(inst, decisions="full")
    from stable_baselines3.common.logger import Logger

    model = sb3c.MaskablePPO("MlpPolicy", env, n_steps=64, batch_size=32, n_epochs=1, seed=0, verbose=0)
    model.set_logger(Logger(folder=None, output_formats=[]))  # sb3's default makes a folder in the temp dir
    model.learn(total_timesteps=128)
    obs, info = env.reset(options={"instance": inst})
    done = False
    while not done:
        action, _ = model.predict(obs, action_masks=env.action_masks(), deterministic=True)
        obs, _, done, _, info = env.step(int(action))
        assert not info.get("invalid_action")
    assert validate(inst, env.shop.schedule()) == []


def _start_estimate(s, j: int) -> int:
    """Reference, one job at a time: time from now until job ``j``'s next operation to start could start on its
    machine (the part there: buffered now; else free now or when its running operation ends, plus the AGV trip;
    the machine free); 0 for a finished job."""
    ops = s.instance.jobs[j]
    k = s.started[j]
    if k >= len(ops):
        return 0
    now, m = s.now, ops[k].machine
    busy = s.machine_busy_until
    travel = s.instance.agv_travel if s.instance.has_agvs else None
    if s.buffered_op(j) is not None:
        part = now
    elif s.job_done_ops[j] >= k:  # the part is free (at the L/U or a machine) or on its way
        here = s.part_location(j)
        part = now + (travel[here][m] if travel is not None and here is not None and here != m else 0)
    else:  # its previous operation still runs
        prev = ops[k - 1].machine
        part = max(now, busy[prev]) + (travel[prev][m] if travel is not None and prev != m else 0)
    return max(part, busy[m], now) - now


@pytest.mark.parametrize("name,steps", [("EX12", None), ("ra01", None), ("ra05", None), ("sl00", 600)])
def test_full_features_match_the_shops_own_per_job_answers(name, steps):
    """The full net's vectorised job and tool features equal FullShop's per-job methods (the reference) at every
    state of a random run: buffered parts, due tool requests (and their count per tool), start estimates."""
    from fms_sim.env import FULL_GLOBAL_FEATURES, FULL_JOB_FEATURES, FULL_TOOL_FEATURES

    env = ShopEnv(builtin(name), decisions="full")
    obs, _ = env.reset(seed=3)
    rng = np.random.default_rng(5)
    base = len(obs) - len(FULL_GLOBAL_FEATURES) - env.max_jobs * len(FULL_JOB_FEATURES) \
        - env.max_tools * len(FULL_TOOL_FEATURES)
    checked = due_seen = 0
    done = False
    while not done and (steps is None or checked < steps):
        s = env.shop
        J = obs[base + len(FULL_GLOBAL_FEATURES):][:env.max_jobs * len(FULL_JOB_FEATURES)].reshape(env.max_jobs, -1)
        T = obs[base + len(FULL_GLOBAL_FEATURES) + env.max_jobs * len(FULL_JOB_FEATURES):].reshape(
            env.max_tools, len(FULL_TOOL_FEATURES))
        counts = {}
        for j in range(s.instance.n_jobs):
            assert J[j, 1] == (s.buffered_op(j) is not None)
            due = s.due_tool_request(j)
            assert J[j, 5] == (due is not None)
            if due is not None:
                counts[due] = counts.get(due, 0) + 1
                due_seen += 1
            assert J[j, 6] == pytest.approx(_start_estimate(s, j) / env._scale, rel=1e-6)
        for t in range(1, s.instance.n_tools + 1 if s.instance.has_tools else 1):
            assert T[t - 1, 6] == pytest.approx(counts.get(t, 0) / s.instance.n_jobs)
        checked += 1
        mask = env.action_masks()
        obs, _, done, _, _ = env.step(int(rng.choice(np.flatnonzero(mask))))
    assert checked > 20 and (due_seen > 0) == builtin(name).has_tools


def _run_first_legal(env: ShopEnv, **reset) -> tuple[float, dict]:
    env.reset(**reset)
    total, done, info = 0.0, False, {}
    while not done:
        _, r, done, _, info = env.step(int(np.flatnonzero(env.action_masks())[0]))
        total += r
    return total, info


def test_disrupted_episodes_draw_scenarios_and_stay_valid():
    from fms_sim.disruptions import Scenario
    from fms_sim.env import episode_scenario

    inst = builtin("ra01")
    env = ShopEnv(inst, decisions="full", disruptions={"noise": 0.2, "breakdowns": 1})
    ret, info = _run_first_legal(env, seed=3)
    sc = env.shop.scenario
    assert sc is not None and sc.noise == 0.2 and len(sc.breakdowns) == 1
    sched = env.shop.schedule()
    assert validate(inst, sched, sc) == [] and info["makespan"] == sched.makespan
    nominal = ShopEnv(inst, decisions="full")
    _, nom = _run_first_legal(nominal, seed=3)
    assert nominal.shop.scenario is None and nom["makespan"] != info["makespan"]  # the noise changed the run
    # a fresh scenario per episode from the env's generator; a fixed one depends on the instance only
    env.reset()
    assert env.shop.scenario != sc
    fixed = ShopEnv(inst, decisions="full", disruptions={"noise": 0.2, "breakdowns": 1, "fixed": True})
    fixed.reset(seed=1)
    first = fixed.shop.scenario
    fixed.reset(seed=2)
    assert fixed.shop.scenario == first == episode_scenario(inst, fixed.disruptions)
    # an explicit scenario wins
    given = Scenario(noise=0.1, seed=9)
    env.reset(options={"scenario": given})
    assert env.shop.scenario == given


@pytest.mark.parametrize("bad, match", [({"noise": -1}, "noise"), ({"noise": float("inf")}, "noise"),
                                        ({"breakdowns": 1.5}, "breakdowns"),
                                        ({"jitter": 1}, "unknown disruption keys"), ("noise", "must be a dict"),
                                        ({"fixed": "no"}, "fixed must be true or false, got 'no'"),  # was True
                                        ({"seed": True}, "seed must be an integer, got True"),  # was seed 1
                                        ({"noise": float("nan")}, "noise")])
def test_bad_disruptions_are_refused(bad, match):
    with pytest.raises(ValueError, match=match):
        ShopEnv(builtin("EX12"), decisions="full", disruptions=bad)


def test_numpy_numbers_are_numbers_in_disruptions():
    # a np.int64 breakdown count was refused while a np.float64 noise passed; values come back as Python's
    got = ShopEnv(builtin("EX12"), decisions="full", disruptions={
        "breakdowns": np.int64(2), "noise": np.float32(0.25), "seed": np.int32(4), "fixed": np.bool_(True)}).disruptions
    assert got == {"noise": 0.25, "breakdowns": 2, "fixed": True, "seed": 4}
    assert [type(got[k]) for k in ("noise", "breakdowns", "fixed", "seed")] == [float, int, bool, int]


@pytest.mark.parametrize("decisions", ["paper", "full"])
def test_actions_that_are_no_integers_are_refused(decisions):
    # step took int(action): 0.9 and "0" ran action 0, though the action space holds neither
    env = ShopEnv(builtin("EX12"), decisions=decisions)
    env.reset(seed=0)
    legal = int(np.flatnonzero(env.action_masks())[0])
    for bad in (legal + 0.9, str(legal), None, float(legal)):
        with pytest.raises(InvalidAction, match="action must be an integer, got"):
            env.step(bad)
    _, _, _, _, info = env.step(np.int64(legal))  # numpy integers are integers (sb3 passes them)
    assert not info.get("invalid_action")


def test_render_mode_none_is_taken_and_options_are_checked():
    # gym.make(..., render_mode=None) was a TypeError; a misspelt reset option was ignored (another instance ran)
    env = gym.make("fms/Shop-v0", instances=builtin("EX12"), render_mode=None)
    env.reset(seed=0)
    with pytest.raises(TypeError, match="renders nothing"):
        ShopEnv(builtin("EX12"), render_mode="human")
    # sb3's make_vec_env asks for render_mode='rgb_array' and goes on without one on a TypeError (it stopped on the
    # ValueError this was)
    import warnings

    from stable_baselines3.common.env_util import make_vec_env

    with warnings.catch_warnings():  # gymnasium's warning for the render mode sb3 asks for first (then refused)
        warnings.filterwarnings("ignore", message=".*render_mode='rgb_array'", category=UserWarning)
        venv = make_vec_env("fms/Shop-v0", n_envs=2, env_kwargs={"instances": [builtin("EX12")]})
    assert venv.reset().shape[0] == 2 and venv.env_method("action_masks")[0].any()
    with pytest.raises(ValueError, match=r"unknown reset options \['instanc'\]; use instance, scenario"):
        env.reset(options={"instanc": builtin("EX11")})
    with pytest.raises(TypeError, match="options must be a dict"):
        env.reset(options=[1])
    with pytest.raises(ValueError, match="invalid_penalty must be a finite number"):
        ShopEnv(builtin("EX12"), invalid_penalty=float("nan"))


def test_disruptions_need_the_full_net():
    with pytest.raises(ValueError, match="full-decision net only"):
        ShopEnv(builtin("EX12"), disruptions={"noise": 0.1})
    assert ShopEnv(builtin("EX12"), disruptions={}).disruptions is None  # empty: none


def test_an_env_over_a_list_of_shops_pickles_before_its_first_episode() -> None:
    # its sampler was a lambda (vector envs and process pools pickle what they are given)
    import pickle

    env = ShopEnv([builtin("EX12"), builtin("EX11")])
    back = pickle.loads(pickle.dumps(env))
    obs, info = back.reset(seed=3)
    assert back.observation_space.contains(obs) and info["action_mask"].any()


@pytest.mark.parametrize("inst", [builtin("ra01").without_agvs(), builtin("ra01").without_agvs().without_tools(),
                                  builtin("ra01"), builtin("EX42")], ids=["tools", "job shop", "agvs+tools", "agvs"])
def test_a_jobs_legal_feature_is_its_dispatch_on_the_full_net(inst):
    """The full net's first actions are the jobs' dispatches only where there are AGVs: without them (tt:0, start:j
    first) the 'legal' job feature marked job 0 for a legal transporter and job j+1 for a legal start of job j."""
    env = ShopEnv(inst, decisions="full")
    obs, info = env.reset(seed=0)
    rng = np.random.default_rng(1)
    n = inst.n_jobs
    while True:
        J = obs[len(GLOBAL_FEATURES):len(GLOBAL_FEATURES) + env.max_jobs * len(JOB_FEATURES)].reshape(env.max_jobs, -1)
        jobs = [num for kind, num in map(env.shop.action_kind, env.shop.legal_actions()) if kind == "job"]
        assert np.flatnonzero(J[:n, JOB_FEATURES.index("legal")]).tolist() == sorted(jobs)
        obs, _, done, _, info = env.step(int(rng.choice(np.flatnonzero(info["action_mask"]))))
        if done:
            break


def test_a_refused_reset_leaves_the_env_as_it_was():
    # the instance was switched before the shop was made: a scenario refused for the new instance left it beside
    # the old run, and step went on observing that run through the other instance's tables
    from fms_sim.disruptions import Breakdown, Scenario, ScenarioError

    env = ShopEnv([builtin("ra01"), builtin("EX42")], decisions="full")
    env.reset(seed=0, options={"instance": builtin("ra01")})
    with pytest.raises(ScenarioError):
        env.reset(options={"instance": builtin("EX42"),
                           "scenario": Scenario((Breakdown(machine=9, start=0, duration=5),), (), 0.0, 0)})
    assert env.instance.name == env.shop.instance.name == "ra01"
    obs, *_ = env.step(int(np.flatnonzero(env.action_masks())[0]))
    assert env.observation_space.contains(obs)


def test_disruptions_on_a_shop_of_times_near_the_largest():
    # its work per machine (the breakdowns' horizon) is above MAX_TIME: every reset with breakdowns drawn past it
    # raised ScenarioError
    from fms_sim.instance import MAX_TIME, Instance, Operation

    big = MAX_TIME - 1
    inst = Instance(name="huge", jobs=tuple((Operation(1, None, big), Operation(2, None, big)) for _ in range(3)),
                    n_machines=2)
    env = ShopEnv(inst, decisions="full", disruptions={"noise": 0.1, "breakdowns": 2})
    for seed in range(10):
        obs, info = env.reset(seed=seed)
        assert env.observation_space.contains(obs)
        assert len(env.shop.scenario.breakdowns) == 2


def test_render_without_render_mode_returns_none():
    # render_mode None: gymnasium's render computes nothing; it raised NotImplementedError, through gym.make too
    env = gym.make("fms/Shop-v0", instances=builtin("EX12"))
    env.reset(seed=0)
    assert env.render() is None and env.unwrapped.render() is None
    env.close()
