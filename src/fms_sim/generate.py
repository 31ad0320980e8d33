"""Instance generation with Taillard's linear congruential generator (LCG).

Taillard (1993) generated his flow-shop, job-shop and open-shop benchmarks with a tiny, portable LCG so that
anyone can regenerate them from a handful of published seeds. The project's large benchmark (``sl00``..``sl79``,
see :mod:`fms_sim.benchmarks`) extends the same scheme to AGV and tool data, so this module re-implements the
generator bit for bit and builds instances from independent streams:

* processing times (default seed 840612802): row-major ``n x m``, each ``U[1, 99]``;
* machine routing (default seed 398197754): per job a Taillard swap permutation of ``1..m``;
* tools (default seed 170719940): per job the same permutation scheme over ``1..n_tools``; operation ``o`` of a
  job gets entry ``o mod n_tools`` of its permutation, i.e. the permutation is truncated when
  ``n_tools >= m`` and repeated cyclically when ``n_tools < m`` (one permutation is drawn per job either way);
* travel matrices (AGV seed 180119550, tool-transporter seed 280219920): ``(m+1) x (m+1)``, index 0 = L/U,
  filled row-major with ``U[1, 30]`` (the diagonal is drawn too) and the diagonal then set to 0. They depend
  only on ``m`` (each matrix restarts its stream at its seed).

The three job streams start at their seeds for the first instance of a call and *continue* across the
following instances, one instance after the other; that is what "instance ``k`` of a group" means.
"""

from __future__ import annotations

import math
from typing import Any

from .instance import MAX_COUNT, Instance, InstanceError, Operation, _plain

__all__ = [
    "TaillardRNG",
    "taillard_permutation",
    "taillard_times",
    "taillard_routing",
    "taillard_tools",
    "travel_matrix",
    "generate_instances",
    "TIME_SEED",
    "ROUTE_SEED",
    "TOOL_SEED",
    "AGV_SEED",
    "TOOL_TRAVEL_SEED",
    "MAX_GENERATED_OPERATIONS",
]

TIME_SEED = 840612802
ROUTE_SEED = 398197754
TOOL_SEED = 170719940
AGV_SEED = 180119550
TOOL_TRAVEL_SEED = 280219920
#: the most operations one call of :func:`generate_instances` builds (``count x n_jobs x n_machines``: a ``gen:`` spec's
#: shops are held in memory at once; 10**7 operations take about 850 MB and 25 s)
MAX_GENERATED_OPERATIONS = 10**7

Grid = list[list[int]]


class TaillardRNG:
    """Taillard's LCG ``seed <- 16807 * seed mod (2^31 - 1)``, computed with Schrage's method.

    Schrage's decomposition (``b = m // a``, ``c = m % a``) keeps every intermediate value inside a signed
    32-bit integer, which is why Taillard's C and Pascal code look like this; reproducing it step by step
    gives exactly the published benchmark data.
    """

    A = 16807
    B = 127773
    C = 2836
    M = 2**31 - 1

    def __init__(self, seed: int) -> None:
        seed = _plain(seed)
        if not isinstance(seed, int) or isinstance(seed, bool) or not 0 < seed < self.M:
            raise InstanceError(f"a Taillard seed must be an integer in 1..{self.M - 1}, got {seed!r}")
        self.seed = seed

    def next_float(self) -> float:
        """Advance the state once and return ``u = seed / m`` in (0, 1)."""
        k = self.seed // self.B
        s = self.A * (self.seed % self.B) - k * self.C
        if s < 0:
            s += self.M
        self.seed = s
        return s / self.M

    def unif(self, lo: int, hi: int) -> int:
        """A draw from ``U[lo, hi]`` (integers, both ends included): ``lo + floor(u * (hi - lo + 1))``."""
        if hi < lo:
            raise ValueError(f"unif: empty range [{lo}, {hi}]")
        return lo + math.floor(self.next_float() * (hi - lo + 1))


def taillard_permutation(rng: TaillardRNG, n: int) -> list[int]:
    """Taillard's random permutation of ``1..n``: for ``j = 1..n`` swap positions ``j`` and ``U[j, n]``."""
    perm = list(range(1, n + 1))
    for j in range(1, n + 1):
        r = rng.unif(j, n)
        perm[j - 1], perm[r - 1] = perm[r - 1], perm[j - 1]
    return perm


def taillard_times(rng: TaillardRNG, n: int, m: int, lo: int = 1, hi: int = 99) -> Grid:
    """``n`` rows of ``m`` processing times ``U[lo, hi]``, drawn row-major (job by job)."""
    return [[rng.unif(lo, hi) for _ in range(m)] for _ in range(n)]


def taillard_routing(rng: TaillardRNG, n: int, m: int) -> Grid:
    """``n`` machine routings, each a Taillard permutation of ``1..m`` (1-based machines)."""
    return [taillard_permutation(rng, m) for _ in range(n)]


def taillard_tools(rng: TaillardRNG, n: int, m: int, n_tools: int) -> Grid:
    """``n`` rows of ``m`` tools: one Taillard permutation of ``1..n_tools`` per job, read cyclically.

    Operation ``o`` gets ``perm[o % n_tools]``: the permutation is truncated when ``n_tools >= m`` and
    repeated when ``n_tools < m`` (so a job then needs some tools more than once).
    """
    rows = []
    for _ in range(n):
        perm = taillard_permutation(rng, n_tools)
        rows.append([perm[o % n_tools] for o in range(m)])
    return rows


def travel_matrix(m: int, seed: int, lo: int = 1, hi: int = 30) -> Grid:
    """An ``(m+1) x (m+1)`` travel matrix: row-major ``U[lo, hi]`` from ``seed``, diagonal then set to 0."""
    rng = TaillardRNG(seed)
    rows = [[rng.unif(lo, hi) for _ in range(m + 1)] for _ in range(m + 1)]
    for i in range(m + 1):
        rows[i][i] = 0
    return rows


def _check_size(name: str, value: Any, minimum: int = 1, top: int = MAX_COUNT) -> None:
    """``value`` is an integer from ``minimum`` to ``top`` (more than a shop may have ran for minutes)."""
    if not isinstance(value, int) or isinstance(value, bool) or not minimum <= value <= top:
        raise InstanceError(f"{name} must be an integer from {minimum} to {top}, got {value!r}")


def generate_instances(
    n_jobs: int,
    n_machines: int,
    n_tools: int,
    count: int,
    *,
    time_seed: int = TIME_SEED,
    route_seed: int = ROUTE_SEED,
    tool_seed: int = TOOL_SEED,
    agv_seed: int = AGV_SEED,
    tool_travel_seed: int = TOOL_TRAVEL_SEED,
    n_agvs: int = 10,
    n_tool_transporters: int = 5,
    tools: bool = True,
    agvs: bool = True,
    name_prefix: str = "gen",
) -> list[Instance]:
    """``count`` instances of ``n_jobs x n_machines`` (every job visits every machine once), named
    ``f"{name_prefix}{i:02d}"`` for ``i = 0..count-1``.

    The time, routing and tool streams start at their seeds and continue from one instance to the next, so
    with the default seeds ``generate_instances(15, 15, 15, 10)`` is benchmark group 0 (``sl00``..``sl09``,
    here named ``gen00``..``gen09``). ``tools=False`` gives operations without tools and no tool transport (``n_tools``
    is then ignored, the tool stream is not drawn); ``agvs=False`` gives no AGV matrix (parts move instantly).
    All instances share the same travel matrices (they depend on ``n_machines`` and the seeds only).
    """
    # numpy's integers are taken as Python's (they were refused as "not an integer"; Instance takes them)
    n_jobs, n_machines, n_tools, count, time_seed, route_seed, tool_seed, agv_seed, tool_travel_seed, n_agvs, \
        n_tool_transporters = (_plain(v) for v in (
            n_jobs, n_machines, n_tools, count, time_seed, route_seed, tool_seed, agv_seed, tool_travel_seed, n_agvs,
            n_tool_transporters))
    _check_size("n_jobs", n_jobs)
    _check_size("n_machines", n_machines)
    for flag, value in (("tools", tools), ("agvs", agvs)):
        if not isinstance(value, bool):  # "no" read as True
            raise InstanceError(f"{flag} must be True or False, got {value!r}")
    _check_size("n_tools", n_tools, 1 if tools else 0)
    _check_size("count", count, top=10**6)
    if count * n_jobs * n_machines > MAX_GENERATED_OPERATIONS:  # (about 85 bytes and 2.4 us each: 10**7 is 850 MB)
        raise InstanceError(f"count x n_jobs x n_machines is {count * n_jobs * n_machines:,} operations; at most "
                            f"{MAX_GENERATED_OPERATIONS:,} are generated at once")
    if agvs:
        _check_size("n_agvs", n_agvs)
    if tools:
        _check_size("n_tool_transporters", n_tool_transporters)
    if not isinstance(name_prefix, str) or not name_prefix:
        raise InstanceError("name_prefix must be a non-empty string")

    time_rng = TaillardRNG(time_seed)
    route_rng = TaillardRNG(route_seed)
    tool_rng = TaillardRNG(tool_seed)
    agv_travel = travel_matrix(n_machines, agv_seed) if agvs else None
    tool_travel = travel_matrix(n_machines, tool_travel_seed) if tools else None
    seeds = {"time": time_seed, "route": route_seed}
    if tools:
        seeds.update(tool=tool_seed, tool_travel=tool_travel_seed)
    if agvs:
        seeds["agv"] = agv_seed

    out = []
    for i in range(count):
        times = taillard_times(time_rng, n_jobs, n_machines)
        routes = taillard_routing(route_rng, n_jobs, n_machines)
        tool_rows = taillard_tools(tool_rng, n_jobs, n_machines, n_tools) if tools else None
        jobs = tuple(
            tuple(
                Operation(routes[j][o], tool_rows[j][o] if tool_rows else None, times[j][o])
                for o in range(n_machines)
            )
            for j in range(n_jobs)
        )
        out.append(
            Instance(
                name=f"{name_prefix}{i:02d}",
                jobs=jobs,
                agv_travel=agv_travel,
                tool_travel=tool_travel,
                n_agvs=n_agvs if agvs else 0,
                n_tool_transporters=n_tool_transporters if tools else 0,
                n_machines=n_machines,
                n_tools=n_tools if tools else 0,
                meta={"generator": "taillard-lcg", "seeds": dict(seeds), "index": i},
            )
        )
    return out
