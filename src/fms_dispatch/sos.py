"""Symbiotic organisms search (SOS) over random keys, decoded through the shop net.

SOS (Cheng & Prayogo 2014) keeps a population ("ecosystem") of organisms, each a real vector, and improves it
with three phases per organism ``i``:

* **mutualism** — with a random partner ``j``: the mutual vector ``(Xi + Xj) / 2`` and benefit factors
  ``BF1, BF2`` in {1, 2}; ``Xi' = Xi + r * (Xbest - BF1 * mutual)`` and ``Xj' = Xj + r * (Xbest - BF2 * mutual)``
  (``r`` uniform in [0, 1) per dimension);
* **commensalism** — ``Xi' = Xi + u * (Xbest - Xj)`` with ``u`` uniform in [-1, 1) per dimension;
* **parasitism** — a copy of ``Xi`` with randomly chosen dimensions redrawn replaces a random ``Xj`` if it
  is at least as good.

Replacement is greedy (a new vector replaces its parent only if its makespan is not worse; equal makespans
are accepted so the search can drift over plateaus). Reddy et al. (2021) used SOS for FMS scheduling with
AGVs; this is our own re-implementation.

Encoding (random keys in [0, 1]): one *priority key* per operation (smaller = dispatched earlier), plus, with
AGVs, one *AGV key* per operation and, with tools, one *transporter key* per operation. A vector is decoded
by running the :class:`~fms_sim.shop.Shop` net, so every decoded schedule is feasible by construction:

* job decision — the legal job whose next operation has the smallest priority key (ties: lowest job);
* AGV decision for operation ``o`` — the AGV ``floor(key * n_agvs)`` (clipped) if it is legal, else the legal
  AGV with the least empty travel to the pickup (ties: nearest index to the keyed one, then lowest index);
* transporter decision — likewise with the transporter key and the tool's location.

The initial population is seeded from dispatching rules: a rule run is recorded as keys (priority = the
order in which the rule dispatched the operations, vehicle keys = the vehicles it chose), and these keys
decode to exactly the rule's schedule, so SOS never returns anything worse than its best seed.

Budget: the search stops after ``iterations`` full SOS iterations or at the time limit. The time limit is
checked at every net decision, so a decode running at the deadline is abandoned rather than finished (one
sl70 decode takes over a second); the first evaluation always completes, so there is always a schedule.

Determinism: for a given seed the search is deterministic when it is bounded by ``iterations`` only. A time
limit makes the number of evaluations — and thus the result — depend on the machine's speed and load.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from fms_sim.instance import Instance, require_instance
from fms_sim.schedule import Schedule
from fms_sim.shop import Shop

from .progress import say
from .rules import RulePolicy, parse_rule_name

__all__ = ["SOSConfig", "KeyDecoder", "TimeUp", "solve_sos", "keys_from_policy", "DEFAULT_SEED_RULES"]

# Seed rules, roughly best first on the project's benchmarks: when a time limit cuts the seeding phase short
# on a large instance, the most promising rules have been tried.
DEFAULT_SEED_RULES: tuple[str, ...] = tuple(
    f"rule:{job}+{veh}"
    for veh in ("nearest", "first", "least-work")
    for job in ("MTWR", "LPT", "LPSR", "FIFO", "LWT", "LPS", "SPTN", "LPTN", "SPSR", "SPS", "SPT", "LTWR")
)


@dataclass(frozen=True)
class SOSConfig:
    """Tunable parameters of the search (the defaults follow the original SOS where it has one).

    ``benefit_factors`` are the values ``BF`` is drawn from in mutualism; ``parasite_rate`` is the largest
    fraction of dimensions a parasite redraws (at least one; the count is uniform in ``1..max``);
    ``seed_fraction`` is the share of the population taken from the best distinct rule seeds (the rest is
    random); ``seed_time_share`` caps the time the rule-seeding phase may use under a time limit.
    """

    population: int = 20
    benefit_factors: tuple[int, ...] = (1, 2)
    parasite_rate: float = 0.1
    seed_fraction: float = 0.5
    seed_time_share: float = 0.5
    accept_equal: bool = True

    def __post_init__(self) -> None:
        if isinstance(self.population, bool) or not isinstance(self.population, int) or self.population < 2:
            raise ValueError(f"SOS population must be an integer >= 2, got {self.population!r}")
        if not self.benefit_factors or any(not isinstance(b, (int, float)) or isinstance(b, bool)
                                           or not 0 < b < math.inf  # (NaN made NaN keys: a decode crashed)
                                           for b in self.benefit_factors):
            raise ValueError(f"SOS benefit factors must be positive, finite numbers, got {self.benefit_factors!r}")
        if not 0.0 < self.parasite_rate <= 1.0:
            raise ValueError(f"SOS parasite_rate must be in (0, 1], got {self.parasite_rate!r}")
        if not 0.0 <= self.seed_fraction <= 1.0:
            raise ValueError(f"SOS seed_fraction must be in [0, 1], got {self.seed_fraction!r}")
        if not 0.0 < self.seed_time_share <= 1.0:
            raise ValueError(f"SOS seed_time_share must be in (0, 1], got {self.seed_time_share!r}")


class TimeUp(Exception):
    """Raised inside a decode that passed its deadline; the search stops and keeps what it has."""


class KeyDecoder:
    """Maps random-key vectors of one instance to schedules by running the shop net.

    Layout of a vector (``n`` = number of operations, operation ``o`` = ``offset[j] + k``): ``[0, n)``
    priority keys, then ``[n, 2n)`` AGV keys if the instance has AGVs, then transporter keys if it has tools.
    """

    def __init__(self, instance: Instance):
        self.instance = instance
        self.offsets: list[int] = []
        n = 0
        for ops in instance.jobs:
            self.offsets.append(n)
            n += len(ops)
        self.n_ops = n
        self.n_agvs = instance.n_agvs if instance.has_agvs else 0
        self.n_tts = instance.n_tool_transporters if instance.has_tools else 0
        self.agv_base = n if self.n_agvs else -1
        self.tt_base = n * (1 + (self.n_agvs > 0)) if self.n_tts else -1
        self.dim = n * (1 + (self.n_agvs > 0) + (self.n_tts > 0))

    def op_index(self, job: int, op: int) -> int:
        return self.offsets[job] + op

    def decode(self, keys: np.ndarray, deadline: float | None = None) -> Shop:
        """Run the shop to completion under the keys; returns the finished shop (``.makespan``, ``.schedule()``).

        With a ``deadline`` (a :func:`time.perf_counter` value) the run is abandoned with :class:`TimeUp`
        once it passes, so a time limit is not overrun by a whole decode on a large instance.
        """
        if keys.shape != (self.dim,):
            raise ValueError(f"key vector has shape {keys.shape}, expected ({self.dim},)")
        inst = self.instance
        shop = Shop(inst)
        allk = keys.tolist()
        off, nj, na, nt = self.offsets, shop.n_jobs, self.n_agvs, self.n_tts
        started = shop.job_started_ops
        ab, tb = self.agv_base, self.tt_base
        agv_travel, tool_travel = inst.agv_travel, inst.tool_travel
        clock = time.perf_counter
        while not shop.done:
            if deadline is not None and clock() >= deadline:
                raise TimeUp("decoding abandoned at the time limit")
            legal = shop.legal_actions()
            first = legal[0]
            if first < nj:  # job decision (vehicle decisions are offered before jobs, never mixed)
                best, best_key = first, allk[off[first] + started[first]]
                for j in legal[1:]:
                    key = allk[off[j] + started[j]]
                    if key < best_key:
                        best, best_key = j, key
                shop.act(best)
            elif first < nj + na:  # AGV decision (taken before a simultaneous transporter decision)
                j, k, pickup, _, _ = shop.awaiting_agv()
                cands = [a - nj for a in legal if a < nj + na]
                v = _vehicle(allk[ab + off[j] + k], na, cands, shop.agv_loc, agv_travel, pickup)
                shop.act(nj + v)
            else:  # transporter decision
                _, tool_loc, j, k, _, _ = shop.awaiting_transporter()
                cands = [a - nj - na for a in legal]
                r = _vehicle(allk[tb + off[j] + k], nt, cands, shop.tt_loc, tool_travel, tool_loc)
                shop.act(nj + na + r)
        return shop


def _vehicle(key: float, n: int, cands: list[int], loc: list[int], travel: Any, target: int) -> int:
    """The keyed vehicle if legal, else the legal one with the least empty travel, nearest index to the key."""
    want = min(max(int(key * n), 0), n - 1)
    if want in cands:
        return want
    return min(cands, key=lambda v: (travel[loc[v]][target], abs(v - want), v))


def keys_from_policy(decoder: KeyDecoder, policy: Callable[[Shop], int],
                     deadline: float | None = None) -> tuple[np.ndarray, Shop]:
    """Run ``policy`` through the net and record its decisions as keys that decode to the same schedule.

    Priority key of an operation = (dispatch rank + 0.5) / n; vehicle key = (index + 0.5) / fleet size.
    Vehicle keys of operations without a vehicle decision (a part already at its machine, a tool already
    there) are 0.5. Returns the keys and the finished shop. ``deadline`` as in :meth:`KeyDecoder.decode`.
    """
    n = decoder.n_ops
    keys = np.full(decoder.dim, 0.5)
    shop = Shop(decoder.instance)
    nj, na, nt = shop.n_jobs, decoder.n_agvs, decoder.n_tts
    rank = 0
    while not shop.done:
        if deadline is not None and time.perf_counter() >= deadline:
            raise TimeUp("seeding abandoned at the time limit")
        a = policy(shop)
        if a < nj:
            keys[decoder.op_index(a, shop.next_op(a))] = (rank + 0.5) / n
            rank += 1
        elif a < nj + na:
            j, k = shop.awaiting_agv()[:2]
            keys[decoder.agv_base + decoder.op_index(j, k)] = (a - nj + 0.5) / na
        else:
            j, k = shop.awaiting_transporter()[2:4]
            keys[decoder.tt_base + decoder.op_index(j, k)] = (a - nj - na + 0.5) / nt
        shop.act(a)
    return keys, shop


def _policy_for(name: str) -> Callable[[Shop], int]:
    """A seed name -> policy: ``first`` (lowest legal action) or a rule ``rule:JOB+veh`` / ``JOB+veh``."""
    if not isinstance(name, str):  # an AttributeError from .lower()
        raise ValueError(f"initial names seed policies (strings such as rule:MTWR+first or first), got {name!r}")
    if name.lower() == "first":
        return lambda shop: shop.legal_actions()[0]
    policy: RulePolicy = parse_rule_name(name)
    return policy


def _check_args(time_limit: float | None, iterations: int | None, population: int, seed: int) -> None:
    if isinstance(population, bool) or not isinstance(population, int) or population < 2:
        raise ValueError(f"SOS population must be an integer >= 2, got {population!r}")
    if time_limit is not None:
        if isinstance(time_limit, bool) or not isinstance(time_limit, (int, float)) or math.isnan(time_limit):
            raise ValueError(f"time_limit must be a number of seconds or None, got {time_limit!r}")
        if not 0 < time_limit < math.inf:  # (inf without iterations searched for ever)
            raise ValueError(f"time_limit must be positive and finite (seconds), got {time_limit}")
    if iterations is not None and (isinstance(iterations, bool) or not isinstance(iterations, int)
                                   or iterations < 0):
        raise ValueError(f"iterations must be a non-negative integer or None, got {iterations!r}")
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise ValueError(f"seed must be an integer, got {seed!r}")


class _Search:
    """State of one SOS run: population, fitness, the best schedule, budget and progress bookkeeping."""

    def __init__(self, decoder: KeyDecoder, rng: np.random.Generator, deadline: float | None,
                 progress: bool, t0: float, bound: int = 0):
        self.decoder, self.rng, self.deadline, self.progress, self.t0 = decoder, rng, deadline, progress, t0
        self.bound = bound  # a lower bound on the makespan: once reached, nothing better exists
        self.evaluations = 0
        self.iteration = 0
        self.best_makespan: int | None = None
        self.best_keys: np.ndarray | None = None
        self.best_shop: Shop | None = None
        self.history: list[list[int]] = []
        self.last_print = t0

    @property
    def at_bound(self) -> bool:
        """Whether the best makespan found is the lower bound (proven optimal: the search can stop)."""
        return self.best_makespan is not None and self.best_makespan <= self.bound

    def out_of_time(self) -> bool:
        """True once the deadline has passed or the lower bound is reached; the first evaluation is always
        allowed."""
        if self.at_bound:
            return True
        return self.deadline is not None and self.evaluations > 0 and time.perf_counter() >= self.deadline

    def budget(self) -> float | None:
        """The deadline for the next decode: none for the first evaluation (there is always a result)."""
        return self.deadline if self.evaluations > 0 else None

    def evaluate(self, keys: np.ndarray, shop: Shop | None = None) -> int:
        """Makespan of ``keys`` (decoding them unless the finished ``shop`` is given); tracks the best.

        Raises :class:`TimeUp` if the decode passes the deadline.
        """
        if shop is None:
            shop = self.decoder.decode(keys, self.budget())
        self.evaluations += 1
        ms = shop.makespan
        if self.best_makespan is None or ms < self.best_makespan:
            self.best_makespan, self.best_keys, self.best_shop = ms, keys.copy(), shop
            self.history.append([self.evaluations, ms])
            self.report(force=True)
        else:
            self.report()
        return ms

    def report(self, force: bool = False) -> None:
        if not self.progress:
            return
        now = time.perf_counter()
        if force or now - self.last_print >= 1.0:
            self.last_print = now
            say(f"  sos: iteration {self.iteration}, evaluations {self.evaluations}, "
                f"best makespan {self.best_makespan}, {now - self.t0:.1f} s")


def solve_sos(instance: Instance, *, time_limit: float | None = 10.0, population: int | None = None,
              iterations: int | None = None, seed: int = 0, progress: bool = False,
              initial: Sequence[str] | None = None, config: SOSConfig | None = None, **_: Any) -> Schedule:
    """Symbiotic organisms search; returns the best schedule found (always feasible).

    Stops after ``iterations`` full SOS iterations or at ``time_limit`` seconds, whichever comes first (if
    both are None the time limit is 10 s). ``initial`` lists the seed policies (rule names such as
    ``"rule:MTWR+first"``, or ``"first"``); default :data:`DEFAULT_SEED_RULES`. ``config`` overrides the
    tunables; ``population`` (given) replaces its population (default: the config's, else 20). Unknown keyword
    options (``workers``) are ignored.
    ``meta``: solver, seed, population, evaluations, iterations, best_makespan_history ([evaluation,
    makespan] at improvements, at most 20 entries), best_seed ([name, makespan]), stopped ("iterations",
    "time_limit", or "lower_bound": the best makespan is :func:`fms_dispatch.exact.simple_lower_bound`, optimal).
    """
    require_instance(instance, "solve_sos")  # (a name was an AttributeError deep inside)
    if time_limit is None and iterations is None:
        time_limit = 10.0
    if config is not None and not isinstance(config, SOSConfig):  # an AttributeError (no __dict__) further down
        raise TypeError(f"config must be an SOSConfig or None, got {type(config).__name__}")
    if population is None:  # (a default of 20 here replaced every config's population)
        population = config.population if config is not None else SOSConfig.population
    _check_args(time_limit, iterations, population, seed)
    cfg = SOSConfig(**{**(config.__dict__ if config else {}), "population": population})
    if isinstance(initial, str):
        raise ValueError("initial must be a list of rule names, not a single string")
    seeds = list(DEFAULT_SEED_RULES if initial is None else initial)
    policies = [(name, _policy_for(name)) for name in seeds]  # bad names raise ValueError before any work

    t0 = time.perf_counter()
    deadline = None if time_limit is None else t0 + time_limit
    # a negative seed by its absolute value, as Python's random takes it (numpy's generator refuses one: 'fms solve
    # --solver sos --seed=-1' said only 'expected non-negative integer', where random and tabu take it)
    rng = np.random.default_rng(abs(seed))
    dec = KeyDecoder(instance)
    from .exact import simple_lower_bound

    search = _Search(dec, rng, deadline, progress, t0, bound=simple_lower_bound(instance))
    stopped = "iterations"

    # 1. rule seeds (time-capped), best distinct ones enter the population
    seed_deadline = None if time_limit is None else t0 + time_limit * cfg.seed_time_share
    seeded: list[tuple[int, int, str, np.ndarray]] = []
    seen: set[bytes] = set()
    best_seed: list[Any] | None = None
    interrupted = False
    try:
        for order, (name, policy) in enumerate(policies):
            if seed_deadline is not None and search.evaluations > 0 and time.perf_counter() >= seed_deadline:
                break
            try:
                keys, shop = keys_from_policy(dec, policy, search.budget())
            except TimeUp:
                stopped = "time_limit"
                break
            ms = search.evaluate(keys, shop)
            if best_seed is None or ms < best_seed[1]:
                best_seed = [name, ms]
            sig = keys.tobytes()
            if sig not in seen:
                seen.add(sig)
                seeded.append((ms, order, name, keys))
        seeded.sort(key=lambda s: (s[0], s[1]))
        n_seeded = min(len(seeded), round(cfg.population * cfg.seed_fraction))
        if seeded and n_seeded == 0 and cfg.seed_fraction > 0:
            n_seeded = 1
        pop: list[np.ndarray] = [s[3] for s in seeded[:n_seeded]]
        fit: list[int] = [s[0] for s in seeded[:n_seeded]]

        # 2. random organisms fill the ecosystem
        try:
            while stopped != "time_limit" and len(pop) < cfg.population:
                if search.out_of_time():
                    raise TimeUp("time limit reached while building the population")
                x = rng.random(dec.dim)
                f = search.evaluate(x)
                pop.append(x)
                fit.append(f)
            # 3. SOS iterations
            if stopped != "time_limit":
                stopped = _iterate(search, cfg, pop, fit, iterations)
        except TimeUp:
            stopped = "time_limit"
    except KeyboardInterrupt:  # the best found so far goes with the interrupt (fms solve --solver sos keeps it)
        if search.best_shop is None:
            raise
        interrupted, stopped = True, "interrupted"
    if search.at_bound:  # proven optimal: the search stopped there (a 1-operation shop ran its whole budget)
        stopped = "lower_bound"

    assert search.best_shop is not None  # at least one evaluation always happens
    sched = search.best_shop.schedule()
    hist = search.history if len(search.history) <= 20 else search.history[:5] + search.history[-15:]
    sched.meta.update({
        "solver": "sos", "seed": seed, "population": cfg.population, "evaluations": search.evaluations,
        "iterations": search.iteration, "best_makespan_history": hist, "best_seed": best_seed,
        "stopped": stopped, "time_limit": time_limit,
    })
    if interrupted:
        from .exact import SearchInterrupted

        sched.meta.update(status="INTERRUPTED", wall_time=round(time.perf_counter() - t0, 3))
        raise SearchInterrupted(sched, search.bound, time.perf_counter() - t0)
    return sched


def _iterate(search: _Search, cfg: SOSConfig, pop: list[np.ndarray], fit: list[int],
             iterations: int | None) -> str:
    """Run SOS iterations on ``pop``/``fit`` in place; returns why it stopped."""
    rng, n, dim = search.rng, len(pop), search.decoder.dim
    bfs = np.asarray(cfg.benefit_factors, dtype=float)
    max_par = max(1, int(round(cfg.parasite_rate * dim)))
    better = (lambda new, old: new <= old) if cfg.accept_equal else (lambda new, old: new < old)

    def partner(i: int) -> int:
        j = int(rng.integers(n - 1))
        return j + 1 if j >= i else j

    def best_vec() -> np.ndarray:
        return pop[min(range(n), key=lambda k: fit[k])]

    def offer(k: int, x: np.ndarray) -> None:
        """Evaluate ``x``; it replaces organism ``k`` if it is better."""
        f = search.evaluate(x)
        if better(f, fit[k]):
            pop[k], fit[k] = x, f

    while iterations is None or search.iteration < iterations:
        for i in range(n):
            # mutualism
            if search.out_of_time():
                return "time_limit"
            j = partner(i)
            xb = best_vec()
            mutual = (pop[i] + pop[j]) / 2.0
            bf1, bf2 = rng.choice(bfs, size=2)
            xi = np.clip(pop[i] + rng.random(dim) * (xb - mutual * bf1), 0.0, 1.0)
            xj = np.clip(pop[j] + rng.random(dim) * (xb - mutual * bf2), 0.0, 1.0)
            offer(i, xi)
            if search.out_of_time():
                return "time_limit"
            offer(j, xj)
            # commensalism
            if search.out_of_time():
                return "time_limit"
            j = partner(i)
            xb = best_vec()
            xi = np.clip(pop[i] + rng.uniform(-1.0, 1.0, dim) * (xb - pop[j]), 0.0, 1.0)
            offer(i, xi)
            # parasitism
            if search.out_of_time():
                return "time_limit"
            j = partner(i)
            parasite = pop[i].copy()
            dims = rng.choice(dim, size=int(rng.integers(1, max_par + 1)), replace=False)
            parasite[dims] = rng.random(len(dims))
            offer(j, parasite)
        search.iteration += 1
        search.report()
    return "iterations"
