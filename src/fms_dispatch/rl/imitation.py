"""Warm start for PPO: demonstrations from search or rules, cloned into the policy before PPO fine-tuning.

PPO from scratch learns slowly on two CPU cores; a policy that starts from good behaviour only has to improve
it. Two experts make the demonstrations (action sequences through the shop net):

* ``"search"`` — per training instance, a search over decision sequences: start from the best of the
  24 rule pairs and of ``iters/4`` random runs, then repeatedly keep a prefix of the best sequence, change one decision at random and
  complete the run by replaying the best sequence where it is still legal (else a random legal action);
  keep the result when it is no worse. For small instances (BU) this finds sequences near the net's best.
* ``"search+lookahead"`` — the same search, then a second one whose runs are lookahead runs
  (:func:`lookahead_search`): a decision sequence is judged by the makespan that the lookahead
  (:mod:`~fms_dispatch.rl.lookahead`) reaches when it drives the run and its twins. The plain search optimises
  the sequence the lookahead will then change; this one optimises what is actually shipped, policy and
  lookahead together. Its demonstrations are every decision of the lookahead run, the twins' included, so a
  policy that reproduces them reproduces the whole lookahead run.
* ``"rules"`` — per training instance, the sequence of the best of the paper's 24 rule pairs;
* ``"rules+nearest"`` — the same over all 36 pairs, i.e. also with the ``nearest`` vehicle rule. On the large
  benchmark the best pairs nearly all send the nearest vehicle, and a policy cloned from the 24 pairs (which
  never do) keeps choosing vehicles badly: replacing only its vehicle choices by ``nearest`` improves it by
  5–10 % (docs/benchmarks.md §4).

:func:`clone` then trains the policy (cross-entropy on the masked logits) and the value head (return-to-go of
the env's reward along the demonstration; none for ``search+lookahead``, whose twin states have no return in
the env) on the recorded ``(observation, mask, action)`` triples. The
result is an ordinary MaskablePPO model; PPO continues from it.
"""

from __future__ import annotations

import random
from typing import Any, Callable, Sequence

import numpy as np

from fms_sim.instance import Instance
from fms_sim.shop import Shop

__all__ = ["EXPERTS", "RULE_EXPERTS", "best_rule_pair", "rule_trajectory", "search_trajectory",
           "SequencePolicy", "lookahead_search", "lookahead_demonstration", "demonstrations",
           "pair_demonstrations", "clone", "dagger", "dagger_round", "dagger_rounds", "concat_demos"]

#: the warm-start experts (``warm_start.expert`` of a training config)
EXPERTS = ("search", "search+lookahead", "rules", "rules+nearest")
#: the experts that are rule pairs: they can label any state, which DAgger needs
RULE_EXPERTS = ("rules", "rules+nearest")


def _run(inst: Instance, choose) -> tuple[int, list[int]]:
    shop = Shop(inst)
    acts: list[int] = []
    while not shop.done:
        a = choose(shop)
        shop.act(a)
        acts.append(a)
    return shop.makespan, acts


def best_rule_pair(inst: Instance, include_nearest: bool = False) -> tuple[str, int, list[int]]:
    """(name, makespan, actions) of the best of the 24 rule pairs (36 with ``include_nearest``; first pair on
    ties)."""
    from fms_dispatch.rules import all_rule_pairs, parse_rule_name

    best: tuple[str, int, list[int]] | None = None
    for name in all_rule_pairs(include_nearest):
        ms, acts = _run(inst, parse_rule_name(name))
        if best is None or ms < best[1]:
            best = (name, ms, acts)
    assert best is not None
    return best


def rule_trajectory(inst: Instance, include_nearest: bool = False) -> tuple[int, list[int]]:
    """(makespan, actions) of :func:`best_rule_pair`."""
    _, ms, acts = best_rule_pair(inst, include_nearest)
    return ms, acts


def search_trajectory(inst: Instance, iters: int = 2000, seed: int = 0, keep: float = 0.85) -> tuple[int, list[int]]:
    """(makespan, actions) found by the local search described in the module docstring."""
    rng = random.Random(seed)
    best_ms, best = rule_trajectory(inst)
    # a quarter of the budget on random runs (a broad start), the rest on local moves
    for _ in range(iters // 4):
        ms, acts = _run(inst, lambda shop: rng.choice(shop.legal_actions()))
        if ms < best_ms:
            best_ms, best = ms, acts
    for _ in range(iters - iters // 4):
        i = rng.randrange(len(best))
        shop = Shop(inst)
        acts: list[int] = []
        for a in best[:i]:
            shop.act(a)
            acts.append(a)
        t = i
        first = True
        while not shop.done:
            legal = shop.legal_actions()
            if first:
                others = [a for a in legal if a != best[i]] or legal
                a = rng.choice(others)
                first = False
            elif t < len(best) and best[t] in legal and rng.random() < keep:
                a = best[t]
            else:
                a = rng.choice(legal)
            shop.act(a)
            acts.append(a)
            t += 1
        if shop.makespan <= best_ms:
            best_ms, best = shop.makespan, acts
    return best_ms, best


class SequencePolicy:
    """A decision sequence used as a policy (``policy(shop) -> net action``).

    Decision ``t`` of a run (counted by the net: ``shop.net.acted``) takes ``actions[t]`` where it is legal;
    otherwise the legal action picked by a fixed hash of ``(salt, t)``. The choice depends on the state only,
    never on a random stream, so a twin of the lookahead that reaches a state makes the choice the run itself
    would make there: a lookahead run of a sequence policy is reproducible, which the search and the
    demonstrations rely on.
    """

    def __init__(self, actions: Sequence[int], salt: int = 0) -> None:
        self.actions = [int(a) for a in actions]
        self.salt = int(salt)

    def __call__(self, shop: Shop) -> int:
        t = shop.net.acted
        legal = shop.legal_actions()
        if t < len(self.actions) and self.actions[t] in legal:
            return self.actions[t]
        return legal[(self.salt * 1_000_003 + t * 7_919) % len(legal)]


def _lookahead_run(inst: Instance, policy: Callable[[Shop], int]) -> tuple[int, list[tuple[list[int], int]]]:
    """(makespan, the run's own decisions as (legal actions, action)) of a lookahead run of ``policy``."""
    from .lookahead import run_with_lookahead

    decisions: list[tuple[list[int], int]] = []
    sched = run_with_lookahead(Shop(inst), policy, decisions=decisions)
    return sched.makespan, decisions


def _inserted(actions: Sequence[int], i: int, x: int) -> list[int] | None:
    """``actions`` with the first later ``x`` (after position ``i``) taken out and put in at ``i``; None
    where ``x`` does not come later (the insertion move of :func:`lookahead_search`)."""
    later = next((t for t in range(i + 1, len(actions)) if actions[t] == x), None)
    if later is None:
        return None
    out = list(actions)
    out.insert(i, out.pop(later))
    return out


def lookahead_search(inst: Instance, iters: int = 2000, seed: int = 0, keep: float = 0.85, history: int = 50,
                     start: Sequence[int] | None = None, insert: float = 0.0,
                     restarts: int = 1) -> tuple[int, SequencePolicy]:
    """(lookahead makespan, policy): a late-acceptance local search over :class:`SequencePolicy`, each
    candidate judged by a whole lookahead run (:func:`~fms_dispatch.rl.lookahead.run_with_lookahead`).

    It starts from ``start`` (default: :func:`search_trajectory` with the same ``iters`` and ``seed``). A
    candidate takes the current run's decisions and moves one decision ``i`` (with two or more legal actions)
    to another legal action ``x``, then frees each later decision with probability ``1 - keep`` (freed
    decisions fall to the policy's hashed choice, with a new salt per candidate). The move is a *change*
    (``x`` overwrites decision ``i``) or, with probability ``insert``, an *insertion*: when ``x`` is chosen
    again later in the run, that later decision is taken out and ``x`` is put in front of decision ``i``, so
    the job moved forward does not also displace the job it replaced. Late acceptance (Burke & Bykov) keeps a
    candidate that is no worse than the current run or than the current run ``history`` iterations ago: plain
    hill climbing stalls on the plateaus of equal makespans that the lookahead's verification creates.

    ``restarts`` > 1 runs the search that many times (``iters`` each), every restart from the best run so far
    with a fresh acceptance history: a late-acceptance walk drifts away from its best on long plateaus, and
    restarting there spends the budget around the best run. The best candidate seen is returned.
    """
    rng = random.Random(seed)
    if start is None:
        _, start = search_trajectory(inst, iters=iters, seed=seed)
    best = SequencePolicy(start)
    best_ms, best_decisions = _lookahead_run(inst, best)
    for _ in range(max(1, restarts)):
        cur_ms, decisions = best_ms, best_decisions  # the current run: its makespan and decisions
        past = [cur_ms] * max(1, history)
        for it in range(iters):
            free = [t for t, (legal, _) in enumerate(decisions) if len(legal) > 1]
            if not free:
                break
            i = rng.choice(free)
            legal, chosen = decisions[i]
            actions = [a for _, a in decisions]
            x = rng.choice([a for a in legal if a != chosen])
            moved = _inserted(actions, i, x) if insert > 0 and rng.random() < insert else None
            if moved is None:
                actions[i] = x
            else:
                actions = moved
            for t in range(i + 1, len(actions)):
                if rng.random() > keep:
                    actions[t] = -1
            cand = SequencePolicy(actions, salt=rng.randrange(1 << 30))
            ms, cand_decisions = _lookahead_run(inst, cand)
            slot = it % len(past)
            if ms <= cur_ms or ms <= past[slot]:
                cur_ms, decisions = ms, cand_decisions
                if ms < best_ms:
                    best, best_ms, best_decisions = cand, ms, cand_decisions
            past[slot] = cur_ms
    return best_ms, best


def lookahead_demonstration(inst: Instance, policy: Callable[[Shop], int], padding: dict[str, int],
                            reward: str = "shaped") -> tuple[int, dict[str, np.ndarray], int]:
    """(makespan, demonstrations, conflicts) of a lookahead run of ``policy``: one row per distinct observation
    at which ``policy`` chose among two or more actions, in the run or in any of its twins. A policy that
    matches every row makes the same lookahead run. ``conflicts`` counts observations seen again with another
    action (the observation does not tell those states apart; 0 in practice). ``ret`` is NaN: twin states
    have no return in the env."""
    from .envs import FastShopEnv
    from .lookahead import run_with_lookahead

    env = FastShopEnv(inst, reward=reward, invalid_action="raise", **padding)
    rows: dict[bytes, tuple[np.ndarray, np.ndarray, int]] = {}
    conflicts = 0

    def recording(shop: Shop) -> int:
        nonlocal conflicts
        a = policy(shop)
        if env.shop is not shop:
            env.attach(shop)
        obs, mask = env.observe()
        if mask.sum() > 1:
            pa = env.from_net_action(a)
            row = rows.setdefault(obs.tobytes(), (obs.copy(), mask.copy(), pa))
            conflicts += row[2] != pa
        return a

    sched = run_with_lookahead(Shop(inst), recording)
    obs, masks, actions = zip(*rows.values()) if rows else ((), (), ())
    return sched.makespan, _as_demos(list(obs), list(masks), list(actions), [np.nan] * len(rows)), conflicts


def _lookahead_searched(inst: Instance, iters: int, seed: int, insert: float,
                        restarts: int) -> tuple[int, SequencePolicy]:
    """:func:`lookahead_search` with the start searched from ``seed`` (top-level, for a process pool)."""
    return lookahead_search(inst, iters=iters, seed=seed, insert=insert, restarts=restarts)


def demonstrations(instances: Sequence[Instance], padding: dict[str, int], reward: str, expert: str,
                   iters: int = 2000, seed: int = 0,
                   progress: Callable[[str], None] | None = None,
                   pairs: dict[str, str] | None = None, insert: float = 0.0, restarts: int = 1,
                   starts: int = 1, workers: int = 1) -> tuple[dict[str, np.ndarray], dict[str, int]]:
    """Replay each instance's expert sequence through the env; returns arrays and the expert makespans.
    ``progress`` (e.g. ``print``) gets a line per instance: the experts take seconds to minutes each.
    For the rule experts, ``pairs`` (if given) receives each instance's best pair (for :func:`dagger_round`).

    Arrays: ``obs`` (N, D), ``mask`` (N, A), ``action`` (N,), ``ret`` (N,) return-to-go (undiscounted; NaN
    where unknown). Decisions with one legal action are replayed but not recorded (nothing to learn). For
    ``search+lookahead`` the makespans are the lookahead's, the rows come from
    :func:`lookahead_demonstration`, ``insert`` and ``restarts`` go to :func:`lookahead_search`, each
    instance is searched ``starts`` times from independent starts (seeds) and the best run is kept (the
    search's result varies by a few units from seed to seed), and ``workers`` > 1 runs that many searches at
    once in separate processes (they take a minute or more each and are independent; the result does not
    depend on ``workers``).
    """
    obs, masks, actions, rets = [], [], [], []
    makespans: dict[str, int] = {}
    if expert == "search+lookahead":
        starts = max(1, starts)
        # start k of instance n searches from seed + n + 1000 k (start 0: seed + n, as the other experts)
        args = [(inst, iters, seed + n + 1000 * k, insert, restarts)
                for n, inst in enumerate(instances) for k in range(starts)]
        if workers > 1 and len(args) > 1:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            # spawn, not fork: the parent may hold torch's thread pools, which do not survive a fork
            pool = ProcessPoolExecutor(min(workers, len(args)),
                                       mp_context=multiprocessing.get_context("spawn"))
            results = pool.map(_lookahead_searched, *zip(*args))
        else:
            pool = None
            results = (_lookahead_searched(*a) for a in args)
        try:
            for n, inst in enumerate(instances):
                found = [next(results) for _ in range(starts)]
                ms, policy = min(found, key=lambda r: r[0])  # the first of the best starts
                la_ms, part, conflicts = lookahead_demonstration(inst, policy, padding, reward)
                assert la_ms == ms, (la_ms, ms)
                for rows, key in ((obs, "obs"), (masks, "mask"), (actions, "action"), (rets, "ret")):
                    rows.extend(part[key])
                makespans[inst.name] = ms
                if progress is not None:
                    each = f" (starts: {', '.join(str(r[0]) for r in found)})" if len(found) > 1 else ""
                    progress(f"  demonstrations: {n + 1}/{len(instances)} instances ({inst.name}: expert "
                             f"makespan {ms} with lookahead{each}, {len(obs)} decisions recorded, {conflicts} "
                             f"conflicting)")
        finally:
            if pool is not None:
                pool.shutdown(cancel_futures=True)
        return _as_demos(obs, masks, actions, rets), makespans
    for n, inst in enumerate(instances):
        if expert == "search":
            ms, seq = search_trajectory(inst, iters=iters, seed=seed + n)
        elif expert in RULE_EXPERTS:
            name, ms, seq = best_rule_pair(inst, include_nearest=expert == "rules+nearest")
            if pairs is not None:
                pairs[inst.name] = name
        else:
            raise ValueError(f"unknown expert {expert!r}; choose from {', '.join(EXPERTS)}")
        makespans[inst.name] = ms
        _replay(inst, seq, ms, padding, reward, (obs, masks, actions, rets))
        if progress is not None:
            progress(f"  demonstrations: {n + 1}/{len(instances)} instances ({inst.name}: expert makespan {ms}, "
                     f"{len(obs)} decisions recorded)")
    return _as_demos(obs, masks, actions, rets), makespans


def _replay(inst: Instance, seq: Sequence[int], makespan: int, padding: dict[str, int], reward: str,
            rows: tuple[list, list, list, list]) -> None:
    """Replay the net actions ``seq`` through the env and append the decisions with a choice to ``rows``
    (observations, masks, env actions, returns-to-go); the run must end at ``makespan``."""
    from .envs import FastShopEnv

    obs, masks, actions, rets = rows
    env = FastShopEnv(inst, reward=reward, invalid_action="raise", **padding)
    o, _ = env.reset(options={"instance": inst})
    steps: list[tuple[int | None, float]] = []  # (recorded row or None, reward of the step)
    for a in seq:
        mask = env.action_masks()
        pa = env.from_net_action(a)
        row = None
        if mask.sum() > 1:
            obs.append(o)
            masks.append(mask)
            actions.append(pa)
            row = len(obs) - 1
        o, r, _, _, _ = env.step(pa)
        steps.append((row, float(r)))
    rets.extend(_returns_to_go(steps))
    assert env.shop.done and env.shop.makespan == makespan


def pair_demonstrations(instances: Sequence[Instance], pair: str, padding: dict[str, int], reward: str,
                        progress: Callable[[str], None] | None = None
                        ) -> tuple[dict[str, np.ndarray], dict[str, int]]:
    """Demonstrations of one rule pair (e.g. ``"MTWR+nearest"``) on every instance, as :func:`demonstrations`
    returns them.

    Why: the ``rules`` experts label each instance with *its* best pair, chosen with a hindsight the policy
    does not have. On 100-job shops the best pair changes from instance to instance while the states look
    alike, so those labels contradict each other and the clone ends between the pairs, worse than any one
    of them (docs/benchmarks.md §4). The labels of one pair are consistent.
    """
    from fms_dispatch.rules import parse_rule_name

    choose = parse_rule_name(pair)
    obs: list = []
    masks: list = []
    actions: list = []
    rets: list = []
    makespans: dict[str, int] = {}
    for n, inst in enumerate(instances):
        ms, seq = _run(inst, choose)
        makespans[inst.name] = ms
        _replay(inst, seq, ms, padding, reward, (obs, masks, actions, rets))
        if progress is not None:
            progress(f"  {pair} demonstrations: {n + 1}/{len(instances)} instances ({inst.name}: makespan {ms}, "
                     f"{len(obs)} decisions recorded)")
    return _as_demos(obs, masks, actions, rets), makespans


def _returns_to_go(steps: list[tuple[int | None, float]]) -> list[float]:
    """Return-to-go (the rewards from that decision on) of the recorded rows of ``steps``, in row order."""
    total = 0.0
    rtg: dict[int, float] = {}
    for row, r in reversed(steps):
        total += r
        if row is not None:
            rtg[row] = total
    return [rtg[i] for i in sorted(rtg)]


def _as_demos(obs: list, masks: list, actions: list, rets: list) -> dict[str, np.ndarray]:
    """The arrays of a demonstration set (see :func:`demonstrations`) from its rows."""
    return {"obs": np.asarray(obs, dtype=np.float32), "mask": np.asarray(masks, dtype=bool),
            "action": np.asarray(actions, dtype=np.int64), "ret": np.asarray(rets, dtype=np.float32)}


def concat_demos(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The rows of ``a`` followed by those of ``b``."""
    return {k: np.concatenate([a[k], b[k]]) for k in a}


def dagger_round(model: Any, instances: Sequence[Instance], pairs: dict[str, str], padding: dict[str, int],
                 reward: str, progress: Callable[[str], None] | None = None
                 ) -> tuple[dict[str, np.ndarray], dict[str, int]]:
    """One DAgger round (Ross et al., 2011): run the current policy (deterministic) on each instance and label
    every state it visits with the action of that instance's expert rule pair (``pairs``, from
    :func:`demonstrations`). Returns the labelled rows (as :func:`demonstrations`, ``ret`` being the policy's
    own return-to-go) and the policy's makespans.

    Why: a cloned policy only ever saw the expert's states. Once it deviates it reaches states with no
    demonstration and its errors compound; the large models cloned from the best rule pair end 1-5 % above
    their expert. Labelling the policy's own states teaches it to recover.
    """
    from fms_dispatch.rules import parse_rule_name

    from .envs import FastShopEnv

    obs, masks, actions, rets = [], [], [], []
    makespans: dict[str, int] = {}
    for n, inst in enumerate(instances):
        if inst.name not in pairs:
            raise ValueError(f"no expert rule pair for {inst.name}")
        expert = parse_rule_name(pairs[inst.name])
        env = FastShopEnv(inst, reward=reward, invalid_action="raise", **padding)
        o, _ = env.reset(options={"instance": inst})
        steps: list[tuple[int | None, float]] = []
        done = False
        while not done:
            mask = env.action_masks()
            row = None
            if mask.sum() > 1:
                obs.append(o)
                masks.append(mask)
                actions.append(env.from_net_action(expert(env.shop)))
                row = len(obs) - 1
                a = int(model.predict(o, action_masks=mask, deterministic=True)[0])
            else:
                a = int(np.flatnonzero(mask)[0])
            o, r, done, _, _ = env.step(a)
            steps.append((row, float(r)))
        rets.extend(_returns_to_go(steps))
        makespans[inst.name] = env.shop.makespan
        if progress is not None:
            progress(f"  dagger: {n + 1}/{len(instances)} instances ({inst.name}: policy makespan "
                     f"{env.shop.makespan}, {len(obs)} states labelled)")
    return _as_demos(obs, masks, actions, rets), makespans


def dagger_rounds(model: Any, demos: dict[str, np.ndarray],
                  label_round: Callable[[], tuple[Any, ...]], expert_ms: dict[str, int],
                  rounds: int, epochs: int = 10, lr: float = 1e-3, seed: int = 0,
                  progress: Callable[[str], None] | None = None, experts: str = "experts"
                  ) -> tuple[dict[str, np.ndarray], list[dict[str, Any]]]:
    """``rounds`` DAgger rounds after :func:`clone`: each runs ``label_round()`` (the current policy's states
    with the expert's labels, the policy's makespans and optionally the expert's makespans of this round's runs,
    which replace ``expert_ms``'s: a disrupted round's scenarios), adds the rows to ``demos`` and clones the
    aggregate for ``epochs`` more epochs. Returns the aggregate and per round the policy's mean makespan *before* that
    round's cloning (relative to the experts' makespans ``expert_ms``; ``experts`` names them in the progress
    lines) and the cloning figures."""
    history: list[dict[str, Any]] = []
    for r in range(rounds):
        got = label_round()
        new, policy_ms = got[0], got[1]
        ref = dict(expert_ms, **(got[2] if len(got) > 2 else {}))
        demos = concat_demos(demos, new)
        ratio = float(np.mean([policy_ms[k] / ref[k] for k in policy_ms]))
        if progress is not None:
            progress(f"  dagger round {r + 1}/{rounds}: policy makespan {100 * (ratio - 1):+.2f} % against the "
                     f"{experts}; cloning {len(demos['obs'])} states")
        bc = clone(model, demos, epochs=epochs, lr=lr, seed=seed + r + 1, progress=progress)
        history.append(dict(round=r + 1, policy_vs_expert=round(ratio, 4), **bc))
    return demos, history


def dagger(model: Any, demos: dict[str, np.ndarray], pairs: dict[str, str], expert_ms: dict[str, int],
           instances: Sequence[Instance],
           padding: dict[str, int], reward: str, rounds: int, epochs: int = 10, lr: float = 1e-3, seed: int = 0,
           progress: Callable[[str], None] | None = None) -> tuple[dict[str, np.ndarray], list[dict[str, Any]]]:
    """:func:`dagger_rounds` with the rule-pair labels of :func:`dagger_round` on ``instances``."""
    return dagger_rounds(model, demos,
                         lambda: dagger_round(model, instances, pairs, padding, reward, progress=progress),
                         expert_ms, rounds, epochs=epochs, lr=lr, seed=seed, progress=progress)


def clone(model: Any, demos: dict[str, np.ndarray], epochs: int = 300, lr: float = 1e-3, batch_size: int = 256,
          seed: int = 0, progress: Callable[[str], None] | None = None) -> dict[str, float]:
    """Behaviour cloning of ``demos`` into ``model.policy`` (policy cross-entropy + value MSE);
    ``progress`` gets the mean loss about every 10 % of the epochs."""
    import torch

    policy = model.policy
    policy.set_training_mode(True)
    gen = torch.Generator().manual_seed(seed)
    X = torch.as_tensor(demos["obs"])
    M = torch.as_tensor(demos["mask"])
    Y = torch.as_tensor(demos["action"])
    R = torch.as_tensor(demos["ret"])
    opt = torch.optim.Adam(policy.parameters(), lr=lr)
    n = X.shape[0]
    every = max(1, epochs // 10)
    for epoch in range(epochs):
        perm = torch.randperm(n, generator=gen)
        total = 0.0
        for i in range(0, n, batch_size):
            idx = perm[i:i + batch_size]
            values, log_prob, _ = policy.evaluate_actions(X[idx], Y[idx], action_masks=M[idx])
            known = ~torch.isnan(R[idx])  # rows without a return train the policy only
            loss = -log_prob.mean()
            if bool(known.any()):
                loss = loss + 0.5 * ((values.squeeze(-1)[known] - R[idx][known]) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(policy.parameters(), 1.0)
            opt.step()
            total += float(loss.detach()) * len(idx)
        if progress is not None and ((epoch + 1) % every == 0 or epoch + 1 == epochs):
            progress(f"  cloning: epoch {epoch + 1}/{epochs}, loss {total / max(1, n):.4f}")
    policy.set_training_mode(False)
    hits, nll = 0, 0.0
    with torch.no_grad():  # in batches: the entity network over 100k+ padded states at once needs many GB
        for i in range(0, n, 4096):
            sl = slice(i, i + 4096)
            dist = policy.get_distribution(X[sl], action_masks=M[sl].numpy())  # one forward pass for both
            hits += int((dist.distribution.probs.argmax(dim=-1) == Y[sl]).sum())
            nll -= float(dist.log_prob(Y[sl]).sum())
    return {"samples": int(n), "accuracy": round(hits / max(1, n), 4), "nll": round(nll / max(1, n), 4)}
