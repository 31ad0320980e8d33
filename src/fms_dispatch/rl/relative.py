"""Returns relative to a reference policy's run of the same episode (a variance reduction for PPO fine-tuning).

In a disrupted shop most of an episode's return is the luck of its scenario (how long the noise made the
operations, when a machine broke down), not the quality of the decisions, and PPO's samples of a near-deterministic
clone differ from it in a few decisions only; the policy gradient drowns in that noise. :class:`RelativeReturn`
wraps a shaped-reward :class:`~fms_dispatch.rl.envs.FastShopEnv` so that an episode's return is
``(B - makespan) / scale``, where ``B`` is the makespan of a reference policy (the weights a fine-tuning run
started from) run deterministically on the same instance in the same scenario: the shaped rewards as usual, and at
the end ``(B - LB_0) / scale`` (their sum is ``-(makespan - LB_0) / scale``). A return above 0 means a better run
than the reference on that very episode; the reference itself scores 0, so an evaluation on fixed scenarios
ranks weights by how much they beat it.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym

__all__ = ["RelativeReturn"]


class RelativeReturn(gym.Wrapper):
    """See the module docstring. ``reference``: an :class:`~fms_dispatch.rl.agent.Agent` (it plans with its own
    guide effort: set it as the env's). The reference makespan of each (instance, scenario) is cached, so fixed
    evaluation scenarios cost one reference run each."""

    def __init__(self, env: gym.Env, reference: Any):
        super().__init__(env)
        if getattr(env.unwrapped, "reward_mode", None) != "shaped":
            raise ValueError("a relative return needs the shaped reward")
        self.reference = reference
        self._cache: dict[tuple, int] = {}
        self._bonus = 0.0

    def _reference_makespan(self) -> int:
        from fms_sim.full_shop import make_shop

        from .lookahead import run_agent

        base = self.env.unwrapped
        inst, sc = base.instance, base.shop.scenario
        key = (inst.name, inst.jobs, None if sc is None else repr(sc.to_dict()))
        got = self._cache.get(key)
        if got is None:
            self.reference.forget()  # plan this episode's shop afresh (a twin would adopt the last plan)
            got = run_agent(make_shop(inst, base.decisions, sc), self.reference.act).makespan
            if len(self._cache) > 10_000:
                self._cache.clear()
            self._cache[key] = got
        return got

    def reset(self, **kwargs: Any):
        obs, info = self.env.reset(**kwargs)
        base = self.env.unwrapped
        ref = info["reference_makespan"] = self._reference_makespan()
        self._bonus = (ref - base._lb0) / base._scale
        return obs, info

    def step(self, action: Any):
        obs, reward, terminated, truncated, info = self.env.step(action)
        if terminated and "makespan" in info:
            reward += self._bonus
        return obs, reward, terminated, truncated, info

    def action_masks(self) -> Any:
        return self.env.unwrapped.action_masks()
