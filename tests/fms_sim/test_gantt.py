"""Tests of the Gantt chart renderer (fms_sim.gantt): rows, lanes, labels, files, errors, speed."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import PolyCollection

from fms_sim.gantt import chart_title, plot_gantt, save_gantt
from fms_sim.instance import Instance, jobs_from_rows
from fms_sim.schedule import AgvTrip, OperationRecord, Schedule, ToolTrip
from fms_sim.validate import validate

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def hand_instance() -> Instance:
    """2 jobs x 2 machines, 1 AGV, 2 tools, 1 tool transporter."""
    return Instance(
        name="hand",
        jobs=jobs_from_rows([[(1, 1, 4), (2, 2, 3)], [(2, None, 5), (1, 1, 2)]]),
        agv_travel=((0, 2, 3), (2, 0, 2), (3, 2, 0)),
        tool_travel=((0, 1, 2), (1, 0, 1), (2, 1, 0)),
        n_agvs=1,
        n_tool_transporters=1,
    )


def hand_schedule() -> Schedule:
    """A feasible schedule of :func:`hand_instance` worked out by hand (makespan 16)."""
    return Schedule(
        instance="hand", makespan=16, n_agvs=1, n_tool_transporters=1,
        operations=[
            OperationRecord(0, 0, 1, 1, 2, 6),
            OperationRecord(1, 0, 2, None, 7, 12),
            OperationRecord(0, 1, 2, 2, 12, 15),
            OperationRecord(1, 1, 1, 1, 14, 16),
        ],
        agv_trips=[
            AgvTrip(0, 0, 0, 0, 1, 0, 2, True),
            AgvTrip(0, None, None, 1, 0, 2, 4, False),
            AgvTrip(0, 1, 0, 0, 2, 4, 7, True),
            AgvTrip(0, None, None, 2, 1, 7, 9, False),
            AgvTrip(0, 0, 1, 1, 2, 9, 11, True),
            AgvTrip(0, 1, 1, 2, 1, 12, 14, True),
        ],
        tool_trips=[
            ToolTrip(0, 1, 0, 0, 0, 1, 0, 1, True),
            ToolTrip(0, None, None, None, 1, 0, 1, 2, False),
            ToolTrip(0, 2, 0, 1, 0, 2, 2, 4, True),
        ],
    )


def greedy_schedule(inst: Instance) -> Schedule:
    """A simple feasible schedule (operations in round-robin order, earliest vehicle) for test instances."""
    m_free = [0] * (inst.n_machines + 1)
    part_loc = [0] * inst.n_jobs
    part_ready = [0] * inst.n_jobs
    agvs = [[0, 0] for _ in range(inst.n_agvs)]  # [location, free at]
    tts = [[0, 0] for _ in range(inst.n_tool_transporters)]
    tool_loc = [0] * (inst.n_tools + 1)
    tool_free = [0] * (inst.n_tools + 1)
    ops, agv_trips, tool_trips = [], [], []
    for k in range(max(len(job) for job in inst.jobs)):
        for j, job in enumerate(inst.jobs):
            if k >= len(job):
                continue
            spec = job[k]
            m = spec.machine
            arrive = part_ready[j]
            if inst.has_agvs and part_loc[j] != m:
                src, tr = part_loc[j], inst.agv_travel
                a = min(range(inst.n_agvs), key=lambda i: agvs[i][1] + tr[agvs[i][0]][src])
                loc, free = agvs[a]
                if loc != src:
                    agv_trips.append(AgvTrip(a, None, None, loc, src, free, free + tr[loc][src], False))
                    free += tr[loc][src]
                s = max(free, part_ready[j])
                agv_trips.append(AgvTrip(a, j, k, src, m, s, s + tr[src][m], True))
                arrive = s + tr[src][m]
                agvs[a] = [m, arrive]
            tool_ready = 0
            if spec.tool is not None:
                t = spec.tool
                tool_ready = tool_free[t]
                if tool_loc[t] != m:
                    src, tr = tool_loc[t], inst.tool_travel
                    v = min(range(inst.n_tool_transporters), key=lambda i: tts[i][1] + tr[tts[i][0]][src])
                    loc, free = tts[v]
                    if loc != src:
                        tool_trips.append(ToolTrip(v, None, None, None, loc, src, free, free + tr[loc][src], False))
                        free += tr[loc][src]
                    s = max(free, tool_free[t])
                    tool_trips.append(ToolTrip(v, t, j, k, src, m, s, s + tr[src][m], True))
                    tool_ready = s + tr[src][m]
                    tts[v] = [m, tool_ready]
            start = max(arrive, m_free[m], tool_ready)
            end = start + spec.duration
            ops.append(OperationRecord(j, k, m, spec.tool, start, end))
            m_free[m] = end
            part_loc[j], part_ready[j] = m, end
            if spec.tool is not None:
                tool_loc[spec.tool], tool_free[spec.tool] = m, end
    return Schedule(inst.name, max(o.end for o in ops), inst.n_agvs, inst.n_tool_transporters, ops, agv_trips,
                    tool_trips)


def large_instance(n_jobs: int = 100, n_machines: int = 20, n_agvs: int = 10, n_tt: int = 4) -> Instance:
    rng = np.random.default_rng(7)
    jobs = []
    for _ in range(n_jobs):
        order = rng.permutation(n_machines) + 1
        jobs.append([(int(mc), int(rng.integers(1, 9)), int(rng.integers(2, 20))) for mc in order])
    pos = rng.uniform(0, 10, size=(n_machines + 1, 2))
    dist = np.rint(np.abs(pos[:, None, :] - pos[None, :, :]).sum(-1)).astype(int) + 1
    np.fill_diagonal(dist, 0)
    travel = tuple(tuple(int(x) for x in row) for row in dist)
    return Instance(name="big", jobs=jobs_from_rows(jobs), agv_travel=travel, tool_travel=travel,
                    n_agvs=n_agvs, n_tool_transporters=n_tt)


def tick_labels(fig) -> list[str]:
    return [t.get_text() for t in fig.axes[0].get_yticklabels()]


def test_hand_schedule_is_valid() -> None:
    assert validate(hand_instance(), hand_schedule()) == []


def test_renders_png_with_expected_rows(tmp_path: Path) -> None:
    out = tmp_path / "sub" / "hand.png"
    fig = plot_gantt(hand_schedule(), hand_instance(), out)
    assert isinstance(fig.canvas, FigureCanvasAgg)
    assert out.read_bytes()[:8] == PNG_MAGIC
    assert out.stat().st_size > 10_000
    assert tick_labels(fig) == ["M1", "M2", "AGV0", "TT0"]
    texts = {t.get_text() for t in fig.axes[0].texts}
    # machine bars labelled j.k, tool trips labelled by tool, sections named, makespan value shown
    assert {"0.0", "1.0", "0.1", "1.1", "T1", "T2", "Machines"} <= texts
    assert "makespan 16 " in texts
    assert any(t.startswith("AGVs") for t in texts) and any(t.startswith("Tool transporters") for t in texts)
    assert [t.get_text() for t in fig.texts] == ["hand — makespan 16"]
    assert fig.axes[0].get_xlabel() == "time"
    legend = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert legend == ["operation / loaded trip (colour = job)", "empty trip (deadheading)", "makespan"]


def test_empty_trips_drawn_apart(tmp_path: Path) -> None:
    fig = plot_gantt(hand_schedule(), hand_instance())
    colls = [c for c in fig.axes[0].collections if isinstance(c, PolyCollection)]
    hatched = [c for c in colls if c.get_hatch()]
    solid = [c for c in colls if not c.get_hatch()]
    assert len(hatched) == 1
    assert len(hatched[0].get_paths()) == 3  # 2 empty AGV trips + 1 empty tool trip
    assert sorted(len(c.get_paths()) for c in solid) == [4, 6]  # 4 operations, 4 + 2 loaded trips
    # empty trips are thinner than loaded ones and sit on their own lane
    h_empty = np.ptp(hatched[0].get_paths()[0].vertices[:, 1])
    loaded = max(solid, key=lambda c: len(c.get_paths()))
    h_loaded = np.ptp(loaded.get_paths()[0].vertices[:, 1])
    assert h_empty < h_loaded / 2
    e_ys = hatched[0].get_paths()[0].vertices[:, 1]
    l_ys = loaded.get_paths()[0].vertices[:, 1]
    assert e_ys.min() > l_ys.max()


def test_custom_title_and_save_gantt_writes_the_format_its_name_says(tmp_path: Path) -> None:
    out = save_gantt(hand_schedule(), tmp_path / "chart.pdf", title="My chart")
    assert out == tmp_path / "chart.pdf" and out.read_bytes()[:5] == b"%PDF-"
    assert b"<svg" in save_gantt(hand_schedule(), tmp_path / "chart.svg").read_bytes()[:400]
    for name in ("chart.png", "chart", "chart.xyz"):  # PNG where the suffix names no format matplotlib writes
        assert save_gantt(hand_schedule(), tmp_path / name).read_bytes()[:8] == PNG_MAGIC
    assert sorted(p.name for p in tmp_path.iterdir()) == ["chart", "chart.pdf", "chart.png", "chart.svg",
                                                          "chart.xyz"]  # no temporary left
    fig = plot_gantt(hand_schedule(), title="My chart")
    assert [t.get_text() for t in fig.texts] == ["My chart"]


def test_job_shop_only_rows_and_instance_widens(tmp_path: Path) -> None:
    inst = Instance(name="js", jobs=jobs_from_rows([[(1, None, 3), (2, None, 2)], [(2, None, 4)]]), n_machines=3)
    sched = Schedule("js", 6, operations=[OperationRecord(0, 0, 1, None, 0, 3), OperationRecord(1, 0, 2, None, 0, 4),
                                          OperationRecord(0, 1, 2, None, 4, 6)])
    assert validate(inst, sched) == []
    assert tick_labels(plot_gantt(sched)) == ["M1", "M2"]
    fig = plot_gantt(sched, inst, tmp_path / "js.png")
    assert tick_labels(fig) == ["M1", "M2", "M3"]
    legend = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert legend == ["operation (colour = job)", "makespan"]
    assert (tmp_path / "js.png").read_bytes()[:8] == PNG_MAGIC
    # without the instance at hand (the recorder's charts), the shop's machine count widens the chart too
    assert tick_labels(plot_gantt(sched, machines=3)) == ["M1", "M2", "M3"]
    assert tick_labels(plot_gantt(sched, machines=1)) == ["M1", "M2"]  # (never narrower than the schedule)
    for bad in (0, True, 2.0, 10**9):
        with pytest.raises(ValueError, match="machines must be an integer from 1 to"):
            plot_gantt(sched, machines=bad)


def test_empty_schedule_raises() -> None:
    with pytest.raises(ValueError, match="^empty schedule$"):
        plot_gantt(Schedule("x", 0))
    with pytest.raises(ValueError, match="^empty schedule$"):
        save_gantt(Schedule("x", 0), "never-written.png")
    assert not Path("never-written.png").exists()


def test_impossible_rows_raise() -> None:
    sched = hand_schedule()
    sched.agv_trips.append(AgvTrip(-1, None, None, 1, 0, 20, 22, False))
    with pytest.raises(ValueError, match="names AGV -1, which does not exist"):
        plot_gantt(sched)
    # one row per number up to the largest: machine 10**6 was killed at 24 GB (no instance has more than 1000)
    from dataclasses import replace

    from fms_sim.schedule import OperationRecord

    far = Schedule("x", 5, operations=[OperationRecord(0, 0, 10**6, None, 0, 5)])
    with pytest.raises(ValueError, match="names machine 1000000, which does not exist"):
        plot_gantt(far)
    with pytest.raises(ValueError, match=r"declares 5000 AGVs, more than an instance has \(at most 1000\)"):
        plot_gantt(replace(hand_schedule(), n_agvs=5000))


def test_large_schedule_renders_fast(tmp_path: Path) -> None:
    inst = large_instance()
    sched = greedy_schedule(inst)
    assert validate(inst, sched) == []
    assert len(sched.operations) == 2000 and len(sched.agv_trips) > 2500
    out = tmp_path / "big.png"
    t0 = time.perf_counter()
    save_gantt(sched, out, inst)
    elapsed = time.perf_counter() - t0
    assert elapsed < 10.0, f"rendering took {elapsed:.1f}s"
    fig = plot_gantt(sched, inst)
    labels = tick_labels(fig)
    assert labels == [f"M{i}" for i in range(1, 21)] + [f"AGV{i}" for i in range(10)] + [f"TT{i}" for i in range(4)]
    assert out.read_bytes()[:8] == PNG_MAGIC and out.stat().st_size > 50_000
    # readable: the figure grows with the rows but stays within sensible bounds
    w, h = fig.get_size_inches()
    assert 11 <= w <= 22 and 8 <= h <= 20


def test_does_not_touch_pyplot() -> None:
    code = (
        "import sys\n"
        "from fms_sim.gantt import plot_gantt\n"
        "from fms_sim.schedule import Schedule, OperationRecord\n"
        "plot_gantt(Schedule('s', 3, operations=[OperationRecord(0, 0, 1, None, 0, 3)]))\n"
        "assert 'matplotlib.pyplot' not in sys.modules\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr


def test_disruptions_are_drawn_on_their_rows():
    from fms_sim.benchmarks import builtin
    from fms_sim.disruptions import Breakdown, Outage, Scenario
    from fms_sim.full_shop import FullShop

    inst = builtin("ra01")
    sc = Scenario(breakdowns=(Breakdown(2, 30, 20),), outages=(Outage("agv", 1, 10, 15),))
    shop = FullShop(inst, scenario=sc)
    while not shop.done:
        shop.act(shop.legal_actions()[0])
    sched = shop.schedule()

    def legend(fig):
        return [t.get_text() for t in fig.axes[0].get_legend().get_texts()]

    def title(fig):
        return [t.get_text() for t in fig.texts]

    assert "down / out of service" in legend(plot_gantt(sched, inst))
    # the title says the run was disrupted, and by what (a disrupted chart was titled as a nominal one)
    assert title(plot_gantt(sched, inst)) == [
        f"ra01 — makespan {sched.makespan} (under disruptions: 1 breakdown, 1 outage)"]
    noisy = FullShop(inst, scenario=Scenario(breakdowns=(Breakdown(1, 0, 5), Breakdown(1, 9, 5)), noise=0.1, seed=2))
    while not noisy.done:
        noisy.act(noisy.legal_actions()[0])
    assert chart_title(noisy.schedule(), "r7") == (f"ra01 — run r7 — makespan {noisy.schedule().makespan} "
                                                   "(under disruptions: 2 breakdowns, noise 0.1)")
    nominal = FullShop(inst)
    while not nominal.done:
        nominal.act(nominal.legal_actions()[0])
    assert "down / out of service" not in legend(plot_gantt(nominal.schedule(), inst))
    assert title(plot_gantt(nominal.schedule(), inst)) == [f"ra01 — makespan {nominal.schedule().makespan}"]


def test_odd_titles_scenarios_and_paths(tmp_path: Path) -> None:
    # an unbalanced "$" in a title (or an instance name) was matplotlib's parse error; a malformed recorded scenario
    # an AttributeError; a folder as the path an IsADirectoryError naming a temporary file
    from dataclasses import replace

    sched = replace(hand_schedule(), instance="cell $\\frac{$")
    assert save_gantt(sched, tmp_path / "a.png").read_bytes()[:8] == PNG_MAGIC
    assert save_gantt(sched, tmp_path / "b.png", title="$x").exists()
    for bad in ({"outages": "x"}, {"breakdowns": None}, {"breakdowns": [1, 2]}, {"noise": "x"}, {"noise": True}):
        assert save_gantt(replace(sched, meta={"scenario": bad}), tmp_path / "c.png").exists()
        assert chart_title(replace(sched, meta={"scenario": bad})) == chart_title(sched)
    with pytest.raises(ValueError, match=f"cannot write the chart: {tmp_path} is a folder; name a file"):
        save_gantt(sched, tmp_path)


# ------------------------------------------------------------------------------------------------ an audit's findings
def _ops_collection(fig) -> PolyCollection:
    return [c for c in fig.axes[0].collections if isinstance(c, PolyCollection)][0]


def test_a_chart_that_needs_latex_is_not_offered_and_greys_are_no_job_colours() -> None:
    from fms_sim.gantt import _EMPTY_FACE, _palette, chart_formats
    from matplotlib.colors import to_rgba

    # .pgf was accepted by the CLI's check, and the run ended in a traceback ("xelatex not found") after its solve
    assert "pgf" not in chart_formats() and {"png", "svg", "pdf"} <= set(chart_formats())
    empty = to_rgba(_EMPTY_FACE)
    for n in (5, 100):  # a grey job read as no job; the lightest was all but the empty trips' grey
        cols = _palette(n)
        assert len(cols) >= (9 if n <= 10 else 50)
        assert all(max(c[:3]) - min(c[:3]) >= 0.1 for c in cols)
        assert min(sum(abs(a - b) for a, b in zip(c[:3], empty[:3])) for c in cols) > 0.1


def test_zero_duration_operations_are_visible_and_the_axis_spans_a_time_unit() -> None:
    ops = [OperationRecord(0, 0, 1, None, 0, 0)]
    fig = plot_gantt(Schedule("z", 0, 0, 0, ops, [], []))
    (x0, x1) = fig.axes[0].get_xlim()
    assert x0 < 0 and x1 >= 1  # (it was -0.01..0.02)
    verts = _ops_collection(fig).get_paths()[0].vertices
    assert verts[:, 0].max() - verts[:, 0].min() > 0  # drawn with a width, in its job's colour
    fig = plot_gantt(hand_schedule())  # a bar of its own length stays as it is
    o = hand_schedule().operations[0]
    v = _ops_collection(fig).get_paths()[0].vertices
    assert (v[:, 0].min(), v[:, 0].max()) == (o.start, o.end)


def test_downtime_is_drawn_over_the_bars_and_only_where_it_disrupted_the_run() -> None:
    from dataclasses import replace

    sched = hand_schedule()
    sc = {"breakdowns": [{"machine": 1, "start": 1, "duration": 2},
                         {"machine": 1, "start": sched.makespan + 5, "duration": 3}], "outages": []}
    fig = plot_gantt(replace(sched, meta={"scenario": sc}))
    bars, down = _ops_collection(fig), [c for c in fig.axes[0].collections if c.get_hatch() == "xxx"][0]
    assert down.get_zorder() > bars.get_zorder()  # (behind, a suspended operation read as running straight through)
    assert len(down.get_paths()) == 1  # the breakdown after the makespan disrupted nothing
    assert chart_title(replace(sched, meta={"scenario": sc})).endswith("(under disruptions: 1 breakdown)")


def test_long_titles_fit_the_chart_and_live_orders_are_said() -> None:
    from dataclasses import replace

    sched = replace(hand_schedule(), meta={"arrivals": [[1, 32], [2, 40]]})
    assert chart_title(sched).endswith("; 2 jobs ordered during the run, from time 32")
    fig = plot_gantt(sched, title="x" * 400)
    fig.canvas.draw()
    (title,) = fig.texts
    box = title.get_window_extent()
    assert box.x1 <= fig.bbox.x1 and title.get_text().count("\n") == 1  # shrunk, then wrapped (it ran off)


def test_past_the_label_cap_the_first_labels_are_drawn(monkeypatch) -> None:
    from fms_sim import gantt

    monkeypatch.setattr(gantt, "_MAX_LABELS", 3)  # (past the cap every label was dropped)
    fig = plot_gantt(hand_schedule())
    texts = [t for t in fig.axes[0].texts if "." in t.get_text()]
    assert len(texts) == 3
