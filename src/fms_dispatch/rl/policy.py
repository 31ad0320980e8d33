"""The agent's network and its deterministic use at inference.

:class:`EntityPolicy` is a MaskablePPO actor-critic that reads the flat, padded observation of
:class:`~fms_dispatch.rl.envs.FastShopEnv` as *sets* of entities (jobs, machines, tools, AGVs, transporters):
one small network embeds every row of a block with shared weights, masked means of the embeddings form the
context, and each job / AGV / transporter slot gets its logit from its own embedding plus the context. The
weights do not depend on the slot, so a model trained on 15-30 job instances scores job 80 of a 100-job
instance the same way, and empty padded slots cost nothing but zeros (the action mask forbids them). The
parameter count is a few tens of thousands, so shipped models stay far below 10 MB. ``arch="mlp"`` in a
model's config uses sb3's plain MLP policy instead.

:func:`actor_from_policy` turns a trained policy's actor into numpy (:mod:`fms_dispatch.rl.actors`), which is
what :class:`~fms_dispatch.rl.agent.Agent` decides with at inference.
"""

from __future__ import annotations

from typing import Any

import torch
from gymnasium import spaces
from sb3_contrib.common.maskable.policies import MaskableActorCriticPolicy
from torch import nn

from .actors import Actor, Layers, NumpyEntityActor, NumpyMlpActor

__all__ = ["EntityPolicy", "EntityNet", "entity_actor", "actor_from_policy"]


def _mlp(n_in: int, hidden: int, n_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(n_in, hidden), nn.Tanh(), nn.Linear(hidden, n_out), nn.Tanh())


def _masked_mean(e: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
    """Mean of ``e`` (B, N, H) over rows where ``present`` (B, N) is 1."""
    w = present.unsqueeze(-1)
    return (e * w).sum(1) / w.sum(1).clamp(min=1.0)


class EntityNet(nn.Module):
    """Shared per-entity embeddings -> (action logits, value latent); used as the policy's mlp_extractor.

    ``layout`` gives the observation blocks (see :func:`~fms_dispatch.rl.envs.obs_layout`). On the full net
    (``layout["full"]``) the full net's extra features join their rows (global, job and tool features), and
    four more heads score the full net's decisions: machine starts and tool take-ups per job (from the job's
    embedding), tool-request choices per tool (from the tool's), and ``hold`` (from the context). A guide's
    features (``layout["guide"]``, :mod:`fms_dispatch.rl.guide`) join the job, tool, AGV and transporter rows.
    """

    def __init__(self, layout: dict[str, int], hidden: int = 64):
        super().__init__()
        self.lay = dict(layout)
        L, h = self.lay, hidden
        self.full = bool(L.get("full"))
        g = L["n_global"] + (L["full_g"] if self.full else 0)
        guide = bool(L.get("guide"))
        job_f = L["job_f"] + (L["full_job_f"] if self.full else 0) + (L["guide_job_f"] if guide else 0)
        tool_f = L["tool_f"] + (L["full_tool_f"] if self.full else 0) + (L["guide_tool_f"] if guide else 0)
        agv_f = L["agv_f"] + (L["guide_agv_f"] if guide else 0)
        tt_f = L["tt_f"] + (L["guide_tt_f"] if guide else 0)
        self.job_emb = _mlp(job_f + L["machine_f"] + g, h, h)
        self.mach_emb = _mlp(L["machine_f"] + g, h, h)
        self.blocks = ["jobs", "machines"]
        if L["tools"]:
            self.tool_emb = _mlp(tool_f + g, h, h)
            self.blocks.append("tools")
        if L["agvs"]:
            self.agv_emb = _mlp(agv_f + g, h, h)
            self.blocks.append("agvs")
        if L["tts"]:
            self.tt_emb = _mlp(tt_f + g, h, h)
            self.blocks.append("tts")
        ctx = h * len(self.blocks) + g
        self.job_head = nn.Sequential(nn.Linear(h + ctx - g, h), nn.Tanh(), nn.Linear(h, 1))
        if L["agvs"]:
            self.agv_head = nn.Sequential(nn.Linear(h + ctx - g, h), nn.Tanh(), nn.Linear(h, 1))
        if L["tts"]:
            self.tt_head = nn.Sequential(nn.Linear(h + ctx - g, h), nn.Tanh(), nn.Linear(h, 1))
        self.value = nn.Sequential(nn.Linear(ctx, h), nn.Tanh(), nn.Linear(h, h), nn.Tanh())
        self.latent_dim_pi = L["jobs"] + L["agvs"] + L["tts"]
        if self.full:
            self.start_head = nn.Sequential(nn.Linear(h + ctx - g, h), nn.Tanh(), nn.Linear(h, 1))
            self.use_head = nn.Sequential(nn.Linear(h + ctx - g, h), nn.Tanh(), nn.Linear(h, 1))
            if L["tools"]:
                self.tool_head = nn.Sequential(nn.Linear(h + ctx - g, h), nn.Tanh(), nn.Linear(h, 1))
            self.hold_head = nn.Sequential(nn.Linear(ctx, h), nn.Tanh(), nn.Linear(h, 1))
            self.latent_dim_pi += 2 * L["jobs"] + L["tools"] + 1
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
        if self.full:  # the full net's blocks follow; their features join the rows they describe
            out["g"] = torch.cat([out["g"], obs[:, i:i + L["full_g"]]], dim=-1)
            i += L["full_g"]
            for name, rows, f in (("jobs", "jobs", "full_job_f"), ("tools", "tools", "full_tool_f")):
                size = L[rows] * L[f]
                out[name] = torch.cat([out[name], obs[:, i:i + size].reshape(B, L[rows], L[f])], dim=-1)
                i += size
        if L.get("guide"):  # the guide's features join the rows they describe
            for name, f in (("jobs", "guide_job_f"), ("tools", "guide_tool_f"), ("agvs", "guide_agv_f"),
                            ("tts", "guide_tt_f")):
                size = L[name] * L[f]
                out[name] = torch.cat([out[name], obs[:, i:i + size].reshape(B, L[name], L[f])], dim=-1)
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

    def _logits(self, emb: dict[str, torch.Tensor], ctx: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        def score(head: nn.Module, e: torch.Tensor) -> torch.Tensor:
            return head(torch.cat([e, ctx.unsqueeze(1).expand(e.shape[0], e.shape[1], ctx.shape[1])],
                                  dim=-1)).squeeze(-1)

        parts = [score(self.job_head, emb["jobs"])]
        if "agvs" in self.blocks:
            parts.append(score(self.agv_head, emb["agvs"]))
        if "tts" in self.blocks:
            parts.append(score(self.tt_head, emb["tts"]))
        if self.full:  # [start per job | tool per tool | use per job | hold], the env's order
            parts.append(score(self.start_head, emb["jobs"]))
            if "tools" in self.blocks:
                parts.append(score(self.tool_head, emb["tools"]))
            parts.append(score(self.use_head, emb["jobs"]))
            parts.append(self.hold_head(torch.cat([ctx, g], dim=-1)))
        return torch.cat(parts, dim=-1)

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        emb, ctx, g = self._encode(features)
        return self._logits(emb, ctx, g), self.value(torch.cat([ctx, g], dim=-1))

    def forward_actor(self, features: torch.Tensor) -> torch.Tensor:
        emb, ctx, g = self._encode(features)
        return self._logits(emb, ctx, g)

    def forward_critic(self, features: torch.Tensor) -> torch.Tensor:
        _, ctx, g = self._encode(features)
        return self.value(torch.cat([ctx, g], dim=-1))


def _layers(m: nn.Module) -> Layers:
    """The Linear layers of a Linear/Tanh sequence as numpy ``(W, b, tanh)``."""
    mods = list(m)
    out = []
    for i, mod in enumerate(mods):
        if isinstance(mod, nn.Linear):
            tanh = i + 1 < len(mods) and isinstance(mods[i + 1], nn.Tanh)
            out.append((mod.weight.detach().numpy().T.copy(), mod.bias.detach().numpy().copy(), tanh))
        elif not isinstance(mod, nn.Tanh):
            raise ValueError(f"unsupported layer {type(mod).__name__} in the policy")
    return out


def entity_actor(net: EntityNet) -> NumpyEntityActor:
    """The numpy actor of a trained :class:`EntityNet`."""
    nets = {"jobs": _layers(net.job_emb), "machines": _layers(net.mach_emb)}
    for b, attr in (("tools", "tool_emb"), ("agvs", "agv_emb"), ("tts", "tt_emb")):
        if b in net.blocks:
            nets[b] = _layers(getattr(net, attr))
    heads = {"jobs": _layers(net.job_head)}
    if "agvs" in net.blocks:
        heads["agvs"] = _layers(net.agv_head)
    if "tts" in net.blocks:
        heads["tts"] = _layers(net.tt_head)
    if net.full:
        heads["start"] = _layers(net.start_head)
        heads["use"] = _layers(net.use_head)
        if "tools" in net.blocks:
            heads["tool"] = _layers(net.tool_head)
        heads["hold"] = _layers(net.hold_head)
    return NumpyEntityActor(net.lay, net.blocks, net.latent_dim_vf, nets, heads)


def actor_from_policy(policy: MaskableActorCriticPolicy) -> Actor | None:
    """The numpy actor of a loaded policy (entity network or plain Linear/Tanh MLP), or None if its layers
    are of another kind."""
    ext = policy.mlp_extractor
    if isinstance(ext, EntityNet):
        return entity_actor(ext)
    net = getattr(ext, "policy_net", None)
    if isinstance(net, nn.Sequential) and all(isinstance(m, (nn.Linear, nn.Tanh)) for m in net):
        return NumpyMlpActor(_layers(nn.Sequential(*net, policy.action_net)))
    return None


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
