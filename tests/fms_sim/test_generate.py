"""Taillard's LCG and the instance generator built on it."""

from __future__ import annotations

import pytest

from fms_sim.generate import (
    AGV_SEED,
    ROUTE_SEED,
    TIME_SEED,
    TOOL_SEED,
    TOOL_TRAVEL_SEED,
    TaillardRNG,
    generate_instances,
    taillard_permutation,
    taillard_routing,
    taillard_times,
    taillard_tools,
    travel_matrix,
)
from fms_sim.instance import InstanceError

TA01_TIMES_ROW0 = [94, 66, 10, 53, 26, 15, 65, 82, 10, 27, 93, 92, 96, 70, 83]
TA01_MACHINES_ROW0 = [7, 13, 5, 8, 4, 3, 11, 12, 9, 15, 10, 14, 6, 1, 2]


def test_lcg_first_states_follow_schrage_formula() -> None:
    rng = TaillardRNG(1)
    rng.next_float()
    assert rng.seed == 16807
    rng.next_float()
    assert rng.seed == 16807 * 16807 % (2**31 - 1)
    # Schrage's method equals the plain modular product for any state.
    rng = TaillardRNG(TIME_SEED)
    expected = TIME_SEED
    for _ in range(1000):
        expected = expected * 16807 % (2**31 - 1)
        u = rng.next_float()
        assert rng.seed == expected
        assert u == expected / (2**31 - 1)


def test_unif_bounds_and_formula() -> None:
    rng = TaillardRNG(12345)
    ref = TaillardRNG(12345)
    for _ in range(500):
        v = rng.unif(3, 7)
        assert 3 <= v <= 7
        assert v == 3 + int(ref.next_float() * 5)
    with pytest.raises(ValueError):
        rng.unif(5, 4)


@pytest.mark.parametrize("seed", [0, -1, 2**31 - 1, 1.5, True])
def test_bad_seed(seed: object) -> None:
    with pytest.raises(InstanceError, match="seed"):
        TaillardRNG(seed)  # type: ignore[arg-type]


def test_reproduces_taillard_ta01_first_rows() -> None:
    times = taillard_times(TaillardRNG(TIME_SEED), 15, 15)
    routes = taillard_routing(TaillardRNG(ROUTE_SEED), 15, 15)
    assert times[0] == TA01_TIMES_ROW0
    assert routes[0] == TA01_MACHINES_ROW0
    assert all(1 <= t <= 99 for row in times for t in row)
    assert all(sorted(r) == list(range(1, 16)) for r in routes)


def test_permutation_is_taillard_swap_scheme() -> None:
    rng, ref = TaillardRNG(777), TaillardRNG(777)
    perm = taillard_permutation(rng, 6)
    expected = [1, 2, 3, 4, 5, 6]
    for j in range(1, 7):
        r = ref.unif(j, 6)
        expected[j - 1], expected[r - 1] = expected[r - 1], expected[j - 1]
    assert perm == expected
    assert rng.seed == ref.seed  # exactly n draws
    assert taillard_permutation(TaillardRNG(5), 1) == [1]


def test_tools_truncate_or_cycle() -> None:
    # n_tools >= m: the first m entries of a permutation of 1..n_tools.
    wide = taillard_tools(TaillardRNG(TOOL_SEED), 3, 4, 6)
    rng = TaillardRNG(TOOL_SEED)
    perms = [taillard_permutation(rng, 6) for _ in range(3)]
    assert wide == [p[:4] for p in perms]
    # n_tools < m: the permutation repeats.
    narrow = taillard_tools(TaillardRNG(TOOL_SEED), 2, 5, 2)
    rng = TaillardRNG(TOOL_SEED)
    for row in narrow:
        p = taillard_permutation(rng, 2)
        assert row == [p[0], p[1], p[0], p[1], p[0]]


def test_travel_matrix() -> None:
    mat = travel_matrix(4, AGV_SEED)
    rng = TaillardRNG(AGV_SEED)
    draws = [rng.unif(1, 30) for _ in range(25)]
    for i in range(5):
        for j in range(5):
            assert mat[i][j] == (0 if i == j else draws[5 * i + j])
    assert travel_matrix(4, AGV_SEED) == mat  # restarts at its seed
    assert travel_matrix(4, TOOL_TRAVEL_SEED) != mat


def test_generate_instances_continue_streams() -> None:
    a, b, c = generate_instances(4, 3, 3, 3, name_prefix="x")
    assert [i.name for i in (a, b, c)] == ["x00", "x01", "x02"]
    t, r, k = TaillardRNG(TIME_SEED), TaillardRNG(ROUTE_SEED), TaillardRNG(TOOL_SEED)
    for inst in (a, b, c):
        times = taillard_times(t, 4, 3)
        routes = taillard_routing(r, 4, 3)
        tools = taillard_tools(k, 4, 3, 3)
        assert [[(op.machine, op.tool, op.duration) for op in ops] for ops in inst.jobs] == [
            [(routes[j][o], tools[j][o], times[j][o]) for o in range(3)] for j in range(4)
        ]
        assert inst.agv_travel == tuple(map(tuple, travel_matrix(3, AGV_SEED)))
        assert inst.tool_travel == tuple(map(tuple, travel_matrix(3, TOOL_TRAVEL_SEED)))
        assert (inst.n_agvs, inst.n_tool_transporters, inst.n_machines, inst.n_tools) == (10, 5, 3, 3)


def test_generate_without_tools_or_agvs_keeps_times_and_routes() -> None:
    full = generate_instances(5, 4, 4, 2)
    plain = generate_instances(5, 4, 0, 2, tools=False, agvs=False)
    for f, p in zip(full, plain):
        assert p.mode == "jobshop"
        assert (p.n_agvs, p.n_tool_transporters, p.n_tools) == (0, 0, 0)
        assert [[(o.machine, o.duration) for o in ops] for ops in f.jobs] == [
            [(o.machine, o.duration) for o in ops] for ops in p.jobs
        ]
        assert all(o.tool is None for ops in p.jobs for o in ops)
    assert generate_instances(2, 2, 2, 1, agvs=False)[0].mode == "tools"


def test_generate_seeds_and_fleet() -> None:
    inst = generate_instances(3, 3, 3, 1, time_seed=1, n_agvs=2, n_tool_transporters=1)[0]
    assert inst.jobs[0][0].duration == TaillardRNG(1).unif(1, 99)
    assert (inst.n_agvs, inst.n_tool_transporters) == (2, 1)


@pytest.mark.parametrize(
    "args, kwargs, match",
    [
        ((0, 3, 3, 1), {}, "n_jobs"),
        ((3, 0, 3, 1), {}, "n_machines"),
        ((3, 3, 0, 1), {}, "n_tools"),
        ((3, 3, 3, 0), {}, "count"),
        ((3, 3, 3, 1), {"n_agvs": 0}, "n_agvs"),
        ((3, 3, 3, 1), {"n_tool_transporters": 0}, "n_tool_transporters"),
        ((3, 3, 3, 1), {"time_seed": 0}, "seed"),
        ((3, 3, 3, 1), {"name_prefix": ""}, "name_prefix"),
        ((2.5, 3, 3, 1), {}, "n_jobs"),
        # all of them are built at once: 1000x1000 shops 11 times over were 11 GB before a word was said
        ((1000, 1000, 3, 11), {}, "is 11,000,000 operations; at most 10,000,000 are generated at once"),
    ],
)
def test_generate_validates_arguments(args: tuple, kwargs: dict, match: str) -> None:
    with pytest.raises(InstanceError, match=match):
        generate_instances(*args, **kwargs)
