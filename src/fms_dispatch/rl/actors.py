"""The trained policy's actor in numpy: deterministic inference without torch.

A decision needs only the actor half of the network (the logits), and a forward pass over one state is a few
small matrix products, so at inference torch is pure overhead: importing it and loading the model takes
seconds (it dominates the start of the agent node and of ``fms solve --solver ppo``), and per call it costs
dozens of small-op dispatches. The actors here hold the weights as numpy arrays:

* :class:`NumpyEntityActor` — the entity network of :class:`~fms_dispatch.rl.policy.EntityNet` (the float32
  arithmetic of ``EntityNet.forward_actor``, but only over the rows that exist and the action blocks that have a
  legal action);
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
from typing import Any, Union

import numpy as np

__all__ = ["Layers", "NumpyEntityActor", "NumpyMlpActor", "Actor", "save_actor", "load_actor", "actor_path",
           "file_sha256"]

#: dense layers ``x @ W + b``, each optionally followed by tanh
Layers = list[tuple[np.ndarray, np.ndarray, bool]]

_FORMAT = "fms-actor/v1"


def _run_layers(layers: Layers, x: np.ndarray) -> np.ndarray:
    """``layers`` on ``x``: each layer's product (a new array, so ``x`` is left as it is), its bias and tanh applied
    in place (the arithmetic of ``x @ w + b`` without an array per step)."""
    for w, b, tanh in layers:
        x = x @ w
        x += b
        if tanh:
            np.tanh(x, out=x)
    return x


class NumpyEntityActor:
    """The actor of a trained entity network (see the module docstring).

    ``lay`` is the observation layout (:func:`~fms_dispatch.rl.envs.obs_layout`), ``blocks`` the embedded
    entity blocks in order (``jobs``, ``machines``, then ``tools`` / ``agvs`` / ``tts`` where present),
    ``nets[block]`` each block's embedding layers and ``heads[block]`` the scoring layers of each action block
    (on the full net also ``start``, ``use`` and ``tool``, which score job and tool rows, and ``hold``, which
    scores the context).

    A decision costs a fraction of a millisecond, and about half of the actor's share is numpy's cost per call
    rather than arithmetic, so :meth:`logits` is built to make few calls: what does not depend on the state is
    precomputed (:meth:`_prepare`), the small blocks are embedded in one batched pass (:meth:`_embed_small`),
    the job rows are gathered with one index (:meth:`_embed_jobs`), and the heads to score are found in one pass
    over the mask, their context parts computed in one product (:meth:`_plan`). Each number is computed as before
    these savings (each product's dot products and each sum in the same order), so the logits are the same to the
    last bit, and so are a model's decisions and the figures measured with it: scoring only a head's legal rows
    or taking a mean as a product with ones would round differently (a few 1e-6), which flipped near ties of the
    paper-net and ``full`` models (sl70 without tools: ``large`` 7263 instead of 7045). Only weights are kept
    between calls (the plans): every array :meth:`logits` returns or works on is its own.
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
        # the global features: one slice, or (on the full net, two parts) one gather
        self._g_idx = (slice(0, L["n_global"]) if len(self._g) == 1
                       else np.concatenate([np.arange(i, i + f) for i, f in self._g]))
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
        # every action illegal: each call's logits start as a copy (faster than filling an array)
        self._illegal = np.full(self._hold + 1 if L.get("full") else paper, -np.inf)
        self._prepare_jobs()
        self._prepare_heads()
        self._prepare_small()

    def _prepare_jobs(self) -> None:
        """One index gathers the job rows from the flat observation, their base, full-net and guide features side
        by side (one call where slicing each part and joining them took five); the machine of each job's next
        operation joins its row as in ``EntityNet._encode``."""
        L = self.lay
        cols = [i + np.arange(L["jobs"])[:, None] * f + np.arange(f)[None, :] for i, f in self._parts["jobs"]]
        self._jobs_idx = np.concatenate(cols, axis=1) if cols else np.zeros((L["jobs"], 0), np.intp)

    def _prepare_heads(self) -> None:
        """Split the first layer of every head that scores rows into the rows' part and the context's, so that the
        context parts of all the heads a decision needs are one product (:meth:`_plan`; each column the same dot
        product as on its own). The ``hold`` head scores the context and the global features joined, as the network
        does (split, its sum would round otherwise). The heads are kept in the order of their action slots, which
        ``np.logical_or.reduceat`` over the mask at :attr:`_starts` reads in one call: a head is needed where its slots
        hold a legal action. A head with no slots (a shop layout without tools) is never needed."""
        # (first slot, name, rows' weights (None: hold), context weights, bias, tanh, rest (hold: all))
        heads: list[tuple[Any, ...]] = []
        for b, layers in self.heads.items():
            w, bias, tanh = layers[0]
            if b == "hold":
                heads.append((self._hold, b, None, None, None, None, layers))
                continue
            lo, slots, src = self._where[b]
            if slots:
                k = self.nets[src][-1][0].shape[1]  # [row embedding, context]
                heads.append((lo, b, w[:k], w[k:], bias, tanh, layers[1:]))
        heads.sort(key=lambda x: x[0])
        self._heads = heads
        self._starts = np.array([x[0] for x in heads], np.intp)
        self._plans: dict[bytes, tuple] = {}

    def _plan(self, need: np.ndarray) -> tuple:
        """What a decision whose needed heads are ``need`` (one flag per head of :attr:`_heads`) computes: the
        context weights and biases of those heads side by side (one product) and per head where its columns lie.
        Built once per set of needed heads (at most two to the number of heads, a handful in a run); the ``hold``
        head, if needed, is a step of its own."""
        key = need.tobytes()
        plan = self._plans.get(key)
        if plan is None:
            used = [x for x, n in zip(self._heads, need) if n]
            rows = [x for x in used if x[2] is not None]
            c_w = np.concatenate([x[3] for x in rows], axis=1) if rows else None
            c_b = np.concatenate([x[4] for x in rows]) if rows else None
            steps: list[tuple[Any, ...]] = []
            col = 0
            for lo, b, wr, wc, _, tanh, rest in used:
                if wr is None:
                    steps.append((lo, True, None, None, None, None, rest))
                    continue
                cols = slice(col, col + wc.shape[1])
                col += wc.shape[1]
                steps.append((lo, False, self._where[b][2], wr, cols, tanh, rest))
            plan = self._plans[key] = (c_w, c_b, steps)
        return plan

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
        self._small: dict[str, Any] | None = None
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
        # the blocks' parts of the global product and of the context: a slice where the blocks follow each other
        # (always: jobs first, then the small blocks), else an index
        sel = (slice(k[0] * h, (k[-1] + 1) * h) if k == list(range(k[0], k[0] + len(k)))
               else np.concatenate([np.arange(j * h, (j + 1) * h) for j in k]))
        self._small = {
            "blocks": small, "pos": {b: s for s, b in enumerate(small)}, "sel": sel, "idx": idx, "real": real,
            "w1": w1, "w2": np.stack([self.nets[b][1][0] for b in small]).astype(np.float32),
            "b2": np.stack([self.nets[b][1][1] for b in small]).astype(np.float32)[:, None, :],
        }

    def _embed_small(self, obs: np.ndarray, gw: np.ndarray, ctx: np.ndarray) -> tuple[np.ndarray, list[int]]:
        """Embed the stacked small blocks (:meth:`_prepare_small`) in one pass, their means into their parts of
        ``ctx``; returns the embeddings (blocks, rows, hidden) and each block's number of rows. A row exists exactly
        where its 'present' feature (its block's first) is 1, and the rows that exist come first."""
        S = self._small
        assert S is not None  # (only called where the blocks are stacked)
        x = obs[S["idx"]]  # (blocks, rows, features)
        present = x[:, :, 0] * S["real"]
        n = present.sum(axis=1)
        counts = [int(x) for x in n.tolist()]
        top = max(counts)  # the rows past every block's last are left out (only a few machines: a BU shop)
        x, present = x[:, :top], present[:, :top]
        e = x @ S["w1"]
        e += gw[S["sel"]].reshape(len(n), 1, -1)
        np.tanh(e, out=e)
        e = e @ S["w2"]
        e += S["b2"]
        np.tanh(e, out=e)
        mean = (present / np.maximum(n, 1)[:, None])[:, None, :] @ e  # (blocks, 1, hidden)
        ctx[S["sel"]] = mean.reshape(-1)
        return e, counts

    def _embed_jobs(self, obs: np.ndarray, gw: np.ndarray, ctx: np.ndarray) -> np.ndarray:
        """The embeddings of the job rows that exist (:meth:`_prepare_jobs`), their mean into the jobs' part of
        ``ctx``. A job's row is joined by the row of the machine of its next operation (a job's 4th feature: that
        machine's number over the machines' count, 0 for none), zeros for none."""
        L, h = self.lay, self.hidden
        i, f = self._parts["jobs"][0]
        nj = int(np.count_nonzero(obs[i:i + L["jobs"] * f:f]))
        mi, mf = self._parts["machines"][0]
        m = L["machines"]
        machines = np.zeros((m + 1, mf), np.float32)  # row 0: no next machine
        machines[1:] = obs[mi:mi + m * mf].reshape(m, mf)
        nxt = np.rint(obs[i + 3:i + nj * f:f] * m).astype(np.intp)
        # (take is faster than indexing; taking into the parts of one array is slower than joining them)
        x = np.concatenate((obs.take(self._jobs_idx[:nj]), machines.take(nxt, axis=0)), axis=1)
        k = self.blocks.index("jobs")
        layers = self.nets["jobs"]
        e = x @ self._row_w["jobs"]
        e += gw[k * h:(k + 1) * h]
        if layers[0][2]:
            np.tanh(e, out=e)
        e = _run_layers(layers[1:], e)
        if nj:
            ctx[k * h:(k + 1) * h] = e.sum(axis=0) * np.float32(1.0 / nj)
        return e

    def _rows(self, obs: np.ndarray, b: str, n: int) -> np.ndarray:
        """The first ``n`` rows of block ``b``: its base, full-net and guide features side by side."""
        ps = self._parts[b]
        if len(ps) == 1:
            i, f = ps[0]
            return obs[i:i + n * f].reshape(n, f)
        return np.concatenate([obs[i:i + n * f].reshape(n, f) for i, f in ps], axis=1)

    def logits(self, obs: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """Logits over the padded actions; -inf where ``mask`` is False."""
        L, h = self.lay, self.hidden
        g = obs[self._g_idx]
        gw = g @ self._g_w  # every block's first layer, global part
        gw += self._g_b
        ctx = np.zeros(h * len(self.blocks), np.float32)
        emb = {"jobs": self._embed_jobs(obs, gw, ctx)}
        S = self._small
        if S is not None:
            small, n_small = self._embed_small(obs, gw, ctx)
        for k, b in enumerate(self.blocks):
            if b in emb or (S is not None and b in S["pos"]):
                continue
            i, f = self._parts[b][0]
            n = int(np.count_nonzero(obs[i:i + L[b] * f:f])) if L[b] else 0
            if not n:  # no rows (a shop without tools): no embedding, its context stays 0
                emb[b] = np.zeros((0, self.nets[b][-1][0].shape[1]), np.float32)
                continue
            layers = self.nets[b]
            e = self._rows(obs, b, n) @ self._row_w[b]
            e += gw[k * h:(k + 1) * h]
            if layers[0][2]:
                np.tanh(e, out=e)
            emb[b] = e = _run_layers(layers[1:], e)
            ctx[k * h:(k + 1) * h] = e.sum(axis=0) * np.float32(1.0 / e.shape[0])
        out = self._illegal.copy() if mask.shape == self._illegal.shape else np.full(mask.shape[0], -np.inf)
        if not len(self._starts):
            return out
        c_w, c_b, steps = self._plan(np.logical_or.reduceat(mask, self._starts))
        if c_w is not None:
            c = ctx @ c_w  # every needed head's first layer, context part
            c += c_b
        for lo, hold, src, wr, cols, tanh, rest in steps:
            if hold:
                out[lo] = _run_layers(rest, np.concatenate([ctx, g]))[0]
                continue
            e = emb.get(src)
            if e is None:  # a batched small block: its rows that exist
                assert S is not None
                s = S["pos"][src]
                e = small[s, :n_small[s]]
            z = e @ wr
            z += c[cols]
            if tanh:
                np.tanh(z, out=z)
            out[lo:lo + z.shape[0]] = _run_layers(rest, z)[:, 0]
        np.putmask(out, ~mask, -np.inf)
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
