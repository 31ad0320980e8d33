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
import zipfile
import zlib
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
        self._prepare()

    def _prepare(self) -> None:
        """Precompute what every call needs (a decision costs a fraction of a millisecond, so the per-call
        bookkeeping matters): where each block's rows lie in the flat observation (its base, full-net and guide
        parts), and the embedding nets' first layers split into the rows' part and the global part, the
        global parts of all blocks stacked so that one product serves them all."""
        L = self.lay
        parts: dict[str, list[tuple[int, int]]] = {}  # block -> [(offset, features)] of its parts, in order
        i = L["n_global"]
        for name, nr, f in (("jobs", "jobs", "job_f"), ("machines", "machines", "machine_f"),
                            ("tools", "tools", "tool_f"), ("agvs", "agvs", "agv_f"), ("tts", "tts", "tt_f")):
            parts[name] = [(i, L[f])]
            i += L[nr] * L[f]
        self._g = [(0, L["n_global"])]
        if L.get("full"):  # the full net's features join the rows they describe (as in EntityNet._split)
            self._g.append((i, L["full_g"]))
            i += L["full_g"]
            for name, f in (("jobs", "full_job_f"), ("tools", "full_tool_f")):
                parts[name].append((i, L[f]))
                i += L[name] * L[f]
        if L.get("guide"):  # the guide's features join the rows they describe (as in EntityNet._split)
            for name, f in (("jobs", "guide_job_f"), ("tools", "guide_tool_f"), ("agvs", "guide_agv_f"),
                            ("tts", "guide_tt_f")):
                parts[name].append((i, L[f]))
                i += L[name] * L[f]
        self._parts = parts
        first = []
        self._row_w: dict[str, np.ndarray] = {}
        for b in self.blocks:
            w, bias, _ = self.nets[b][0]
            k = w.shape[0] - sum(f for _, f in self._g)  # the rows' features come first, then the global ones
            self._row_w[b] = w[:k]
            first.append((w[k:], bias))
        self._g_w = np.concatenate([w for w, _ in first], axis=1)
        self._g_b = np.concatenate([b for _, b in first])
        paper = L["jobs"] + L["agvs"] + L["tts"]
        # head -> (first action slot, slots, embedded block it scores)
        self._where = {"jobs": (0, L["jobs"], "jobs"), "agvs": (L["jobs"], L["agvs"], "agvs"),
                       "tts": (L["jobs"] + L["agvs"], L["tts"], "tts"), "start": (paper, L["jobs"], "jobs"),
                       "tool": (paper + L["jobs"], L["tools"], "tools"),
                       "use": (paper + L["jobs"] + L["tools"], L["jobs"], "jobs")}
        self._hold = paper + 2 * L["jobs"] + L["tools"]
        self._prepare_small()

    def _prepare_small(self) -> None:
        """Stack the blocks other than the jobs' (machines, tools, AGVs, transporters: a few dozen rows in all) so
        that one batched pass embeds them all: much of a decision's cost is numpy's cost per call, and these blocks
        took about ten calls each (docs/benchmarks.md §1: the actor 1.10× faster in sl70's run, 1.14× in sl00's).
        One index gathers each block's rows from the flat observation (its base, full-net and guide features side by
        side), padded to the widest block's features and the longest block's rows; the padding reads any feature,
        which the zero-padded first-layer weights ignore, and the padded rows are left out of the means. Only for
        embedding nets of two tanh layers of the hidden size (every entity network :mod:`fms_dispatch.rl.policy`
        builds); otherwise :attr:`_small` is None and :meth:`logits` embeds block by block."""
        L = self.lay
        small = [b for b in self.blocks if b != "jobs" and L[b]]
        self._small = None
        h = self.hidden
        if not small or any(len(self.nets[b]) != 2 or not all(t for _, _, t in self.nets[b])
                            or self.nets[b][0][0].shape[1] != h or self.nets[b][1][0].shape != (h, h) for b in small):
            return
        rows = max(L[b] for b in small)
        width = max(self._row_w[b].shape[0] for b in small)
        idx = np.zeros((len(small), rows, width), dtype=np.intp)
        real = np.zeros((len(small), rows), dtype=np.float32)  # 1 for the rows the observation has
        w1 = np.zeros((len(small), width, h), dtype=np.float32)
        for s, b in enumerate(small):
            col = 0
            for i, f in self._parts[b]:
                idx[s, :L[b], col:col + f] = i + np.arange(L[b])[:, None] * f + np.arange(f)[None, :]
                col += f
            w1[s, :col] = self._row_w[b]
            real[s, :L[b]] = 1.0
        k = [self.blocks.index(b) for b in small]
        self._small = {
            "blocks": small, "k": np.array(k), "idx": idx, "real": real, "w1": w1,
            "gsel": np.concatenate([np.arange(j * h, (j + 1) * h) for j in k]).reshape(len(small), 1, h),
            "w2": np.stack([self.nets[b][1][0] for b in small]).astype(np.float32),
            "b2": np.stack([self.nets[b][1][1] for b in small]).astype(np.float32)[:, None, :],
        }

    def _embed_small(self, obs: np.ndarray, gw: np.ndarray, ctx: np.ndarray, emb: dict[str, np.ndarray]) -> None:
        """Embed the stacked small blocks (:meth:`_prepare_small`) in one pass: each block's rows into ``emb``,
        their mean into its part of ``ctx``. A row exists exactly where its 'present' feature (its block's first) is
        1, and the rows that exist come first."""
        S = self._small
        x = obs[S["idx"]]  # (blocks, rows, features)
        present = x[:, :, 0] * S["real"]
        n = present.sum(axis=1)
        top = int(n.max())  # the rows past every block's last are left out (only a few machines: a BU shop)
        x, present = x[:, :top], present[:, :top]
        e = np.tanh(x @ S["w1"] + gw[S["gsel"]])
        e = np.tanh(e @ S["w2"] + S["b2"])
        mean = (present / np.maximum(n, 1)[:, None])[:, None, :] @ e  # (blocks, 1, hidden)
        h = self.hidden
        ctx.reshape(-1, h)[S["k"]] = mean[:, 0, :]
        for s, b in enumerate(S["blocks"]):
            emb[b] = e[s, :int(n[s])]

    def _rows(self, obs: np.ndarray, b: str, n: int) -> np.ndarray:
        """The first ``n`` rows of block ``b``: its base, full-net and guide features side by side."""
        ps = self._parts[b]
        if len(ps) == 1:
            i, f = ps[0]
            return obs[i:i + n * f].reshape(n, f)
        return np.concatenate([obs[i:i + n * f].reshape(n, f) for i, f in ps], axis=1)

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
        g = obs[:L["n_global"]] if len(self._g) == 1 else np.concatenate([obs[i:i + f] for i, f in self._g])
        h = self.hidden
        gw = g @ self._g_w + self._g_b  # every block's first layer, global part
        # rows that exist: the 'present' feature (each block's first) is 1 exactly for them, and they come first
        n = {}
        batched = self._small["blocks"] if self._small is not None else ()
        for b in self.blocks:
            if b in batched:
                continue  # counted in the batched pass
            i, f = self._parts[b][0]
            n[b] = int(np.count_nonzero(obs[i:i + L[b] * f:f])) if L[b] else 0
        nj = n["jobs"]
        i, f = self._parts["jobs"][0]
        idx = np.rint(obs[i + 3:i + nj * f:f] * L["machines"]).astype(np.int64) - 1  # next machine (0: none)
        i, f = self._parts["machines"][0]
        nxt = np.take(obs[i:i + L["machines"] * f].reshape(L["machines"], f), np.maximum(idx, 0), axis=0)
        nxt[idx < 0] = 0.0
        emb: dict[str, np.ndarray] = {}
        ctx = np.zeros(h * len(self.blocks), np.float32)
        if self._small is not None:
            self._embed_small(obs, gw, ctx, emb)
        for k, b in enumerate(self.blocks):
            if b in emb:
                continue
            if b != "jobs" and not n[b]:  # no rows (a shop without tools): no embedding, its context stays 0
                emb[b] = np.zeros((0, self.nets[b][-1][0].shape[1]), np.float32)
                continue
            if b == "jobs":  # a job's row is joined by the row of the machine of its next operation
                x = np.concatenate([obs[i:i + nj * f].reshape(nj, f) for i, f in self._parts[b]] + [nxt], axis=1)
            else:
                x = self._rows(obs, b, n[b])
            layers = self.nets[b]
            e = x @ self._row_w[b] + gw[k * h:(k + 1) * h]
            if layers[0][2]:
                e = np.tanh(e)
            e = _run_layers(layers[1:], e)
            emb[b] = e
            if e.shape[0]:
                ctx[k * h:(k + 1) * h] = e.sum(axis=0) * np.float32(1.0 / e.shape[0])
        out = np.full(mask.shape[0], -np.inf)
        for b, head in self.heads.items():
            if b == "hold":
                lo = self._hold
                if mask[lo]:
                    out[lo] = _run_layers(head, np.concatenate([ctx, g]))[0]
                continue
            lo, slots, src = self._where[b]
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
            if not isinstance(meta, dict) or meta.get("format") != _FORMAT:
                raise ValueError(f"{path} is not an actor export ({_FORMAT})")
            if meta["kind"] == "entity":
                actor: Actor = NumpyEntityActor(
                    meta["lay"], meta["blocks"], meta["hidden"],
                    {b: _unpack(f"net.{b}", t, data) for b, t in meta["nets"].items()},
                    {b: _unpack(f"head.{b}", t, data) for b, t in meta["heads"].items()})
            else:
                actor = NumpyMlpActor(_unpack("mlp", meta["layers"], data))
            sha = meta["source_sha256"]  # (read outside this guard, its absence was a KeyError)
    except (OSError, EOFError, KeyError, TypeError, AttributeError, zipfile.BadZipFile, zlib.error,
            json.JSONDecodeError, UnicodeDecodeError) as exc:  # empty, truncated or damaged (an interrupted copy)
        raise ValueError(f"cannot read the actor export {path}: {exc}") from None
    return actor, sha
