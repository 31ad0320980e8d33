"""The agent's network and its deterministic use at inference.

:class:`EntityPolicy` is a MaskablePPO actor-critic that reads the flat, padded observation of
:class:`~fms_dispatch.rl.envs.FastShopEnv` as *sets* of entities (jobs, machines, tools, AGVs, transporters):
one small network embeds every row of a block with shared weights, masked means of the embeddings form the
context, and each job / AGV / transporter slot gets its logit from its own embedding plus the context. The
weights do not depend on the slot, so a model trained on 15-30 job instances scores job 80 of a 100-job
instance the same way, and empty padded slots cost nothing but zeros (the action mask forbids them). The
parameter count is a few tens of thousands, so shipped models stay far below 10 MB. ``arch="mlp"`` in a
model's config uses sb3's plain MLP policy instead.

:class:`Agent` loads a trained model (CPU, one torch thread, no network) and chooses net actions for a live
:class:`~fms_sim.shop.Shop`: the arg-max of the masked logits (deterministic; a single legal action is taken
without a forward pass).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from sb3_contrib.common.maskable.policies import MaskableActorCriticPolicy
from torch import nn

from fms_sim.instance import Instance
from fms_sim.shop import Shop

from .envs import FastShopEnv

__all__ = ["EntityPolicy", "EntityNet", "Agent"]


def _mlp(n_in: int, hidden: int, n_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(n_in, hidden), nn.Tanh(), nn.Linear(hidden, n_out), nn.Tanh())


def _masked_mean(e: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
    """Mean of ``e`` (B, N, H) over rows where ``present`` (B, N) is 1."""
    w = present.unsqueeze(-1)
    return (e * w).sum(1) / w.sum(1).clamp(min=1.0)


class EntityNet(nn.Module):
    """Shared per-entity embeddings -> (action logits, value latent); used as the policy's mlp_extractor.

    ``layout`` gives the observation blocks (see :func:`~fms_dispatch.rl.envs.obs_layout`).
    """

    def __init__(self, layout: dict[str, int], hidden: int = 64):
        super().__init__()
        self.lay = dict(layout)
        L, h = self.lay, hidden
        g = L["n_global"]
        self.job_emb = _mlp(L["job_f"] + L["machine_f"] + g, h, h)
        self.mach_emb = _mlp(L["machine_f"] + g, h, h)
        self.blocks = ["jobs", "machines"]
        if L["tools"]:
            self.tool_emb = _mlp(L["tool_f"] + g, h, h)
            self.blocks.append("tools")
        if L["agvs"]:
            self.agv_emb = _mlp(L["agv_f"] + g, h, h)
            self.blocks.append("agvs")
        if L["tts"]:
            self.tt_emb = _mlp(L["tt_f"] + g, h, h)
            self.blocks.append("tts")
        ctx = h * len(self.blocks) + g
        self.job_head = nn.Sequential(nn.Linear(h + ctx - g, h), nn.Tanh(), nn.Linear(h, 1))
        if L["agvs"]:
            self.agv_head = nn.Sequential(nn.Linear(h + ctx - g, h), nn.Tanh(), nn.Linear(h, 1))
        if L["tts"]:
            self.tt_head = nn.Sequential(nn.Linear(h + ctx - g, h), nn.Tanh(), nn.Linear(h, 1))
        self.value = nn.Sequential(nn.Linear(ctx, h), nn.Tanh(), nn.Linear(h, h), nn.Tanh())
        self.latent_dim_pi = L["jobs"] + L["agvs"] + L["tts"]
        self.latent_dim_vf = h

    def _split(self, obs: torch.Tensor) -> dict[str, torch.Tensor]:
        L = self.lay
        B = obs.shape[0]
        out: dict[str, torch.Tensor] = {}
        i = L["n_global"]
        out["g"] = obs[:, :i]
        for name, rows, f in (("jobs", "jobs", "job_f"), ("machines", "machines", "machine_f"),
                              ("tools", "tools", "tool_f"), ("agvs", "agvs", "agv_f"), ("tts", "tts", "tt_f")):
            size = L[rows] * L[f]
            out[name] = obs[:, i:i + size].reshape(B, L[rows], L[f])
            i += size
        return out

    def _encode(self, obs: torch.Tensor) -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor]:
        L = self.lay
        x = self._split(obs)
        g = x["g"]
        B = obs.shape[0]

        def with_g(rows: torch.Tensor) -> torch.Tensor:
            return torch.cat([rows, g.unsqueeze(1).expand(B, rows.shape[1], g.shape[1])], dim=-1)

        jobs, machines = x["jobs"], x["machines"]
        # the state of each job's next machine, gathered by its index (next_machine = machine / max_machines)
        idx = torch.round(jobs[:, :, 3] * L["machines"]).long() - 1
        valid = (idx >= 0).float().unsqueeze(-1)
        idx = idx.clamp(0, L["machines"] - 1)
        nxt = torch.gather(machines, 1, idx.unsqueeze(-1).expand(B, L["jobs"], L["machine_f"])) * valid
        emb = {"jobs": self.job_emb(with_g(torch.cat([jobs, nxt], dim=-1))),
               "machines": self.mach_emb(with_g(machines))}
        if "tools" in self.blocks:
            emb["tools"] = self.tool_emb(with_g(x["tools"]))
        if "agvs" in self.blocks:
            emb["agvs"] = self.agv_emb(with_g(x["agvs"]))
        if "tts" in self.blocks:
            emb["tts"] = self.tt_emb(with_g(x["tts"]))
        pooled = [_masked_mean(emb[b], x[b][:, :, 0]) for b in self.blocks]
        ctx = torch.cat(pooled, dim=-1)
        return emb, ctx, g

    def _logits(self, emb: dict[str, torch.Tensor], ctx: torch.Tensor) -> torch.Tensor:
        def score(head: nn.Module, e: torch.Tensor) -> torch.Tensor:
            return head(torch.cat([e, ctx.unsqueeze(1).expand(e.shape[0], e.shape[1], ctx.shape[1])],
                                  dim=-1)).squeeze(-1)

        parts = [score(self.job_head, emb["jobs"])]
        if "agvs" in self.blocks:
            parts.append(score(self.agv_head, emb["agvs"]))
        if "tts" in self.blocks:
            parts.append(score(self.tt_head, emb["tts"]))
        return torch.cat(parts, dim=-1)

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        emb, ctx, g = self._encode(features)
        return self._logits(emb, ctx), self.value(torch.cat([ctx, g], dim=-1))

    def forward_actor(self, features: torch.Tensor) -> torch.Tensor:
        emb, ctx, _ = self._encode(features)
        return self._logits(emb, ctx)

    def forward_critic(self, features: torch.Tensor) -> torch.Tensor:
        _, ctx, g = self._encode(features)
        return self.value(torch.cat([ctx, g], dim=-1))


class NumpyEntityActor:
    """The actor half of a trained :class:`EntityNet` in numpy, for fast single-state inference.

    Same arithmetic as :meth:`EntityNet.forward_actor` (float32), but only over the rows that exist (padded
    rows never enter a masked mean) and only for the action blocks that have a legal action: a decision on a
    100x20 instance costs a few small matrix products instead of dozens of torch calls.
    """

    def __init__(self, net: EntityNet):
        self.lay = dict(net.lay)
        self.blocks = list(net.blocks)

        def seq(m: nn.Module) -> list[tuple[np.ndarray, np.ndarray, bool]]:
            mods = list(m)
            out = []
            for i, mod in enumerate(mods):
                if isinstance(mod, nn.Linear):
                    tanh = i + 1 < len(mods) and isinstance(mods[i + 1], nn.Tanh)
                    out.append((mod.weight.detach().numpy().T.copy(), mod.bias.detach().numpy().copy(), tanh))
            return out

        self.nets = {"jobs": seq(net.job_emb), "machines": seq(net.mach_emb)}
        for b, attr in (("tools", "tool_emb"), ("agvs", "agv_emb"), ("tts", "tt_emb")):
            if b in self.blocks:
                self.nets[b] = seq(getattr(net, attr))
        self.heads = {"jobs": seq(net.job_head)}
        if "agvs" in self.blocks:
            self.heads["agvs"] = seq(net.agv_head)
        if "tts" in self.blocks:
            self.heads["tts"] = seq(net.tt_head)
        self.hidden = net.latent_dim_vf

    @staticmethod
    def _run(layers: list[tuple[np.ndarray, np.ndarray, bool]], x: np.ndarray, shared: np.ndarray) -> np.ndarray:
        """The layers on rows ``[x, shared]`` (``shared`` the same for every row), without building them:
        the first layer is split into the rows' part and the shared part."""
        w, b, tanh = layers[0]
        k = x.shape[1]
        x = x @ w[:k] + (shared @ w[k:] + b)
        if tanh:
            x = np.tanh(x)
        for w, b, tanh in layers[1:]:
            x = x @ w + b
            if tanh:
                x = np.tanh(x)
        return x

    def logits(self, obs: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """Logits over the padded actions; -inf where ``mask`` is False."""
        L = self.lay
        g = obs[:L["n_global"]]
        i = L["n_global"]
        rows: dict[str, np.ndarray] = {}
        for name, nr, f in (("jobs", "jobs", "job_f"), ("machines", "machines", "machine_f"),
                            ("tools", "tools", "tool_f"), ("agvs", "agvs", "agv_f"), ("tts", "tts", "tt_f")):
            size = L[nr] * L[f]
            rows[name] = obs[i:i + size].reshape(L[nr], L[f])
            i += size
        # rows that exist: the 'present' feature is 1 exactly for them, and they come first
        n = {b: int(rows[b][:, 0].sum()) if L[b] else 0 for b in rows}
        jobs = rows["jobs"][:n["jobs"]]
        idx = np.rint(jobs[:, 3] * L["machines"]).astype(np.int64) - 1
        valid = (idx >= 0).astype(np.float32)[:, None]
        nxt = rows["machines"][np.clip(idx, 0, L["machines"] - 1)] * valid
        h = self.hidden

        def embed(b: str, x: np.ndarray) -> np.ndarray:
            return self._run(self.nets[b], x, g)

        emb = {"jobs": embed("jobs", np.concatenate([jobs, nxt], axis=1))}
        for b in self.blocks[1:]:
            emb[b] = embed(b, rows[b][:n[b]])
        ctx = np.concatenate([emb[b].mean(axis=0) if emb[b].shape[0] else np.zeros(h, np.float32)
                              for b in self.blocks])
        out = np.full(mask.shape[0], -np.inf)
        start = {"jobs": 0, "agvs": L["jobs"], "tts": L["jobs"] + L["agvs"]}
        for b, head in self.heads.items():
            lo = start[b]
            if not mask[lo:lo + L[b]].any():
                continue
            e = emb[b]
            out[lo:lo + e.shape[0]] = self._run(head, e, ctx)[:, 0]
        out[~mask] = -np.inf
        return out


class NumpyMlpActor:
    """The actor of sb3's plain MLP policy (``arch="mlp"``) in numpy: policy_net layers, then action_net."""

    def __init__(self, policy: MaskableActorCriticPolicy):
        layers: list[tuple[np.ndarray, np.ndarray, bool]] = []
        mods = list(policy.mlp_extractor.policy_net) + [policy.action_net]
        for i, mod in enumerate(mods):
            if isinstance(mod, nn.Linear):
                act = i + 1 < len(mods) and not isinstance(mods[i + 1], nn.Linear)
                layers.append((mod.weight.detach().numpy().T.copy(), mod.bias.detach().numpy().copy(), act))
            elif not isinstance(mod, nn.Tanh):
                raise ValueError(f"unsupported layer {type(mod).__name__} in the MLP policy")
        self.layers = layers

    def logits(self, obs: np.ndarray, mask: np.ndarray) -> np.ndarray:
        x = obs
        for w, b, tanh in self.layers:
            x = x @ w + b
            if tanh:
                x = np.tanh(x)
        out = x.astype(np.float64)
        out[~mask] = -np.inf
        return out


class EntityPolicy(MaskableActorCriticPolicy):
    """MaskablePPO policy over :class:`EntityNet`; its logits are the action distribution directly."""

    def __init__(self, observation_space: spaces.Space, action_space: spaces.Space, lr_schedule: Any,
                 layout: dict[str, int] | None = None, hidden: int = 64, **kwargs: Any):
        if layout is None:
            raise ValueError("EntityPolicy needs the observation layout (policy_kwargs['layout'])")
        self._layout, self._hidden = dict(layout), int(hidden)
        kwargs.setdefault("ortho_init", False)
        super().__init__(observation_space, action_space, lr_schedule, **kwargs)
        # the extractor already yields one logit per action slot: no extra linear layer (it would tie slots)
        self.action_net = nn.Identity()
        self.optimizer = self.optimizer_class(self.parameters(), lr=lr_schedule(1), **self.optimizer_kwargs)

    def _build_mlp_extractor(self) -> None:
        self.mlp_extractor = EntityNet(self._layout, self._hidden)

    def _get_constructor_parameters(self) -> dict[str, Any]:
        data = super()._get_constructor_parameters()
        data.update(layout=self._layout, hidden=self._hidden)
        return data


class Agent:
    """A trained model ready to dispatch: ``agent.act(shop) -> net action`` (deterministic)."""

    def __init__(self, model_path: str | Path, padding: dict[str, int], name: str = ""):
        from sb3_contrib import MaskablePPO

        torch.set_num_threads(1)
        path = Path(model_path)
        if not path.is_file():
            raise ValueError(f"model file {path} does not exist")
        self.name = name or path.parent.name
        self.path = path
        self.model = MaskablePPO.load(str(path), device="cpu")
        self.policy = self.model.policy
        self.policy.set_training_mode(False)
        self.padding = dict(padding)
        ext = self.policy.mlp_extractor
        self._fast: NumpyEntityActor | NumpyMlpActor | None = None
        if isinstance(ext, EntityNet):
            self._fast = NumpyEntityActor(ext)
        elif isinstance(self.policy.mlp_extractor.policy_net, nn.Sequential) and all(
                isinstance(m, (nn.Linear, nn.Tanh)) for m in self.policy.mlp_extractor.policy_net):
            self._fast = NumpyMlpActor(self.policy)
        self._envs: dict[int, FastShopEnv] = {}
        self._last: FastShopEnv | None = None

    def fits(self, inst: Instance) -> bool:
        """Whether ``inst`` fits this model's padded layout."""
        p = self.padding
        return (inst.n_jobs <= p["max_jobs"] and inst.n_machines <= p["max_machines"]
                and (inst.n_tools if inst.has_tools else 0) <= p["max_tools"]
                and (inst.n_agvs if inst.has_agvs else 0) <= p["max_agvs"]
                and (inst.n_tool_transporters if inst.has_tools else 0) <= p["max_tts"])

    def _env(self, shop: Shop) -> FastShopEnv:
        env = self._envs.get(id(shop))
        if env is None or env.shop is not shop:
            if not self.fits(shop.instance):
                raise ValueError(f"instance {shop.instance.name} does not fit model {self.name} "
                                 f"(max {self.padding})")
            env = FastShopEnv(shop.instance, **self.padding)
            env.attach(shop)
            if self._last is not None:
                env.adopt_tables(self._last)  # twins share the real shop's instance tables
            if len(self._envs) >= 4:  # the live shop and a twin or two; drop stale ones
                self._envs.clear()
            self._envs[id(shop)] = env
        elif env.instance is not shop.instance:
            env.attach(shop)
        self._last = env
        return env

    def logits(self, shop: Shop, fast: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Masked-out logits are -inf; returns (logits over padded actions, mask).

        ``fast`` uses the numpy actor where the model has one (entity policy); else torch.
        """
        env = self._env(shop)
        obs, mask = env.observe()
        if fast and self._fast is not None:
            return self._fast.logits(obs, mask), mask
        with torch.no_grad():
            x = torch.as_tensor(obs, dtype=torch.float32).unsqueeze(0)
            feats = self.policy.extract_features(x, self.policy.pi_features_extractor)
            latent = self.policy.mlp_extractor.forward_actor(feats)
            out = self.policy.action_net(latent)[0].numpy().astype(np.float64)
        out[~mask] = -np.inf
        return out, mask

    def act(self, shop: Shop) -> int:
        """The net action the policy picks now (arg-max of the masked logits, lowest index on ties)."""
        legal = shop.legal_actions()
        if len(legal) == 1:
            return legal[0]
        env = self._env(shop)
        logits, _ = self.logits(shop)
        a = env.to_net_action(int(np.argmax(logits)))
        if a is None or a not in legal:  # cannot happen with a correct mask; never hand out an illegal action
            raise RuntimeError(f"policy chose a masked action at time {shop.now}")
        return a
