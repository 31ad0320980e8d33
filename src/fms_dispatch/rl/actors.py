"""The trained policy's actor in numpy: deterministic inference without torch.

A decision needs only the actor half of the network (the logits), and a forward pass over one state is a few
small matrix products, so at inference torch is pure overhead: importing it and loading the model takes
seconds (it dominates the start of the agent node and of ``fms solve --solver ppo``), and per call it costs
dozens of small-op dispatches. The actors here hold the weights as numpy arrays:

* :class:`NumpyEntityActor` — the entity network of :class:`~fms_dispatch.rl.policy.EntityNet` (same float32
  arithmetic as ``EntityNet.forward_actor``, but only over the rows that exist and the action blocks that
  have a legal action);
* :class:`NumpyMlpActor` — sb3's plain MLP policy (``arch="mlp"``).

:func:`save_actor` / :func:`load_actor` store an actor in an ``.npz`` file next to the model's weights
(``best_model.zip`` → ``best_model.actor.npz``) together with the SHA-256 of the weights it was exported
from, so a stale export is never used (:mod:`fms_dispatch.rl.agent` falls back to torch then). They are
built from a loaded torch policy by :func:`fms_dispatch.rl.policy.actor_from_policy`.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Union

import numpy as np

__all__ = ["Layers", "NumpyEntityActor", "NumpyMlpActor", "Actor", "save_actor", "load_actor", "actor_path",
           "file_sha256"]

#: dense layers ``x @ W + b``, each optionally followed by tanh
Layers = list[tuple[np.ndarray, np.ndarray, bool]]

_FORMAT = "fms-actor/v1"


def _run_layers(layers: Layers, x: np.ndarray) -> np.ndarray:
    for w, b, tanh in layers:
        x = x @ w + b
        if tanh:
            x = np.tanh(x)
    return x


class NumpyEntityActor:
    """The actor of a trained entity network (see the module docstring).

    ``lay`` is the observation layout (:func:`~fms_dispatch.rl.envs.obs_layout`), ``blocks`` the embedded
    entity blocks in order (``jobs``, ``machines``, then ``tools`` / ``agvs`` / ``tts`` where present),
    ``nets[block]`` each block's embedding layers and ``heads[block]`` the scoring layers of each action block
    (on the full net also ``start``, ``use`` and ``tool``, which score job and tool rows, and ``hold``, which
    scores the context).
    """

    kind = "entity"

    def __init__(self, lay: dict[str, int], blocks: list[str], hidden: int, nets: dict[str, Layers],
                 heads: dict[str, Layers]):
        self.lay = dict(lay)
        self.blocks = list(blocks)
        self.hidden = int(hidden)
        self.nets = nets
        self.heads = heads

    @staticmethod
    def _run(layers: Layers, x: np.ndarray, shared: np.ndarray) -> np.ndarray:
        """The layers on rows ``[x, shared]`` (``shared`` the same for every row), without building them:
        the first layer is split into the rows' part and the shared part."""
        w, b, tanh = layers[0]
        k = x.shape[1]
        x = x @ w[:k] + (shared @ w[k:] + b)
        if tanh:
            x = np.tanh(x)
        return _run_layers(layers[1:], x)

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
        full = bool(L.get("full"))
        if full:  # the full net's features join the rows they describe (as in EntityNet._split)
            g = np.concatenate([g, obs[i:i + L["full_g"]]])
            i += L["full_g"]
            for name, f in (("jobs", "full_job_f"), ("tools", "full_tool_f")):
                size = L[name] * L[f]
                rows[name] = np.concatenate([rows[name], obs[i:i + size].reshape(L[name], L[f])], axis=1)
                i += size
        if L.get("guide"):  # the guide's features join the rows they describe (as in EntityNet._split)
            for name, f in (("jobs", "guide_job_f"), ("tools", "guide_tool_f"), ("agvs", "guide_agv_f"),
                            ("tts", "guide_tt_f")):
                size = L[name] * L[f]
                rows[name] = np.concatenate([rows[name], obs[i:i + size].reshape(L[name], L[f])], axis=1)
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
        paper = L["jobs"] + L["agvs"] + L["tts"]
        # head -> (first action slot, slots, embedded block it scores)
        where = {"jobs": (0, L["jobs"], "jobs"), "agvs": (L["jobs"], L["agvs"], "agvs"),
                 "tts": (L["jobs"] + L["agvs"], L["tts"], "tts"), "start": (paper, L["jobs"], "jobs"),
                 "tool": (paper + L["jobs"], L["tools"], "tools"),
                 "use": (paper + L["jobs"] + L["tools"], L["jobs"], "jobs")}
        for b, head in self.heads.items():
            if b == "hold":
                lo = paper + 2 * L["jobs"] + L["tools"]
                if mask[lo]:
                    out[lo] = _run_layers(head, np.concatenate([ctx, g]))[0]
                continue
            lo, slots, src = where[b]
            if not mask[lo:lo + slots].any():
                continue
            e = emb[src]
            out[lo:lo + e.shape[0]] = self._run(head, e, ctx)[:, 0]
        out[~mask] = -np.inf
        return out


class NumpyMlpActor:
    """The actor of sb3's plain MLP policy (``arch="mlp"``): the policy_net layers, then action_net."""

    kind = "mlp"

    def __init__(self, layers: Layers):
        self.layers = layers

    def logits(self, obs: np.ndarray, mask: np.ndarray) -> np.ndarray:
        out = _run_layers(self.layers, obs).astype(np.float64)
        out[~mask] = -np.inf
        return out


Actor = Union[NumpyEntityActor, NumpyMlpActor]


def actor_path(weights: str | Path) -> Path:
    """Where the numpy export of ``weights`` lives: ``best_model.zip`` → ``best_model.actor.npz``."""
    w = Path(weights)
    return w.with_name(w.stem + ".actor.npz")


def file_sha256(path: str | Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _pack(prefix: str, layers: Layers, arrays: dict[str, np.ndarray]) -> list[bool]:
    for k, (w, b, _) in enumerate(layers):
        arrays[f"{prefix}.{k}.w"] = w
        arrays[f"{prefix}.{k}.b"] = b
    return [bool(t) for _, _, t in layers]


def _unpack(prefix: str, tanh: list[bool], data) -> Layers:
    return [(data[f"{prefix}.{k}.w"], data[f"{prefix}.{k}.b"], t) for k, t in enumerate(tanh)]


def save_actor(actor: Actor, path: str | Path, source_sha256: str) -> Path:
    """Write ``actor`` to ``path`` (.npz) with the SHA-256 of the weights file it comes from."""
    arrays: dict[str, np.ndarray] = {}
    meta: dict = {"format": _FORMAT, "kind": actor.kind, "source_sha256": source_sha256}
    if isinstance(actor, NumpyEntityActor):
        meta.update(lay=actor.lay, blocks=actor.blocks, hidden=actor.hidden,
                    nets={b: _pack(f"net.{b}", ls, arrays) for b, ls in actor.nets.items()},
                    heads={b: _pack(f"head.{b}", ls, arrays) for b, ls in actor.heads.items()})
    else:
        meta["layers"] = _pack("mlp", actor.layers, arrays)
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez_compressed(tmp, **arrays)
    tmp.replace(path)
    return path


def load_actor(path: str | Path) -> tuple[Actor, str]:
    """The actor stored in ``path`` and the SHA-256 of the weights it was exported from; raises ValueError
    if the file is not an actor export."""
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(bytes(data["meta"]).decode())
            if meta.get("format") != _FORMAT:
                raise ValueError(f"{path} is not an actor export ({_FORMAT})")
            if meta["kind"] == "entity":
                actor: Actor = NumpyEntityActor(
                    meta["lay"], meta["blocks"], meta["hidden"],
                    {b: _unpack(f"net.{b}", t, data) for b, t in meta["nets"].items()},
                    {b: _unpack(f"head.{b}", t, data) for b, t in meta["heads"].items()})
            else:
                actor = NumpyMlpActor(_unpack("mlp", meta["layers"], data))
    except (OSError, KeyError, json.JSONDecodeError) as exc:
        raise ValueError(f"cannot read the actor export {path}: {exc}") from None
    return actor, meta["source_sha256"]
