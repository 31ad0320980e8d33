"""Decision speed of a trained model: the time its run takes once the plan is made (observation, numpy actor and
the full net's own steps), per decision; and the time of one list schedule (the guide's plan search is made of
them: ``fms_dispatch.exact.greedy_schedule``, earliest start).

Each shop is run by the model (default ``ppo``, the shipped guided model) with a reproducible plan (the plain list
schedule: ``--guide-restarts 0 --guide-tabu 0``, so the plan search's budget does not enter the time), first once to
plan, then ``--repeat`` times more, each timed; the best of them is reported. Only the run is timed. Every schedule
is validated. With ``--baseline REV`` the same measurement runs on the source of git revision REV (a temporary
worktree), alternating with this checkout's run by run, so both see the same machine load; the baseline must
make the same schedules (the same decisions), or the bench stops.

``--solve`` times the whole solve instead, as ``fms solve NAME --solver ppo`` reports it (``meta["wall_time"]``: the
model's load, the default plan search within its 1 s budget and the run; the plan search's share is reported beside
it, or, where it ran on the other core beside the run (``fms_dispatch.rl.beside``), its length and how often the run
went on with the first plan or started over), each run in a fresh process. This is how the large benchmark's sl70
time goal (<= 5 s) is measured: ``python bench/decide_speed.py --solve --instances sl70 sl70/notools``. In every mode a name ending in ``/notools`` drops the
shop's tools (``fms solve --no-tools``).

``--parts`` says where a run's time goes, per decision with a choice: the net's own steps, the observation's base
and full-net features, the guide's features and the numpy actor; with ``--baseline`` the baseline's too, alternating,
with each part's speed-up.

Usage: python bench/decide_speed.py [--instances sl00 sl31 sl70 EX104] [--model ppo] [--repeat 3] [--solve | --parts]
                                    [--baseline REV] [--json PATH]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import platform
import statistics
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any, Iterator

from checks import checked, output_file, positive, report, run_worker

ROOT = Path(__file__).resolve().parent.parent


def _load(name: str) -> Any:
    """The shop ``name`` (a built-in or a file); ``NAME/notools``: without its tools, as ``fms solve --no-tools``."""
    from fms_sim.formats import load_instance

    base, notools = _split(name)
    return load_instance(base, no_tools=notools)


def _split(name: str) -> tuple[str, bool]:
    """``NAME/notools`` as ``(NAME, True)``, another name as ``(name, False)`` (partitioned at the first "/", a file's
    path was cut at its first folder)."""
    base = name.removesuffix("/notools")
    return base, base != name


def _agent(inst: Any, model: str) -> Any:
    """The model that runs ``inst`` (``ppo``: the default for it), a guided one planning with the plain list
    schedule, so that the plan search's budget does not enter the times and every run makes the same plan."""
    from fms_dispatch.rl.guide import effort_from
    from fms_dispatch.rl.models import default_model_name, load_agent

    agent = load_agent(model if model != "ppo" else default_model_name(inst))
    if agent.guide is not None:
        agent.use_guide_effort(effort_from(restarts=0, budget=0, tabu=0))
    return agent


def measure(names: list[str], model: str, repeat: int) -> list[dict]:
    """Per shop: decisions with a choice, makespan, and the best of ``repeat`` timed runs (seconds); the same for
    one earliest-start list schedule."""
    from fms_dispatch.exact import greedy_schedule
    from fms_sim.full_shop import make_shop

    rows = []
    for name in names:
        inst = _load(name)
        agent = _agent(inst, model)
        best = None
        for rep in range(repeat + 1):  # the first run makes the plan; the others adopt it
            shop = make_shop(inst, agent.decisions)
            choices = 0
            t0 = time.perf_counter()
            while not shop.done:
                choices += len(shop.legal_actions()) > 1
                shop.act(agent.act(shop))
            dt = time.perf_counter() - t0
            if rep:
                best = dt if best is None else min(best, dt)
        row = {"instance": name, "decisions": choices, "seconds": best,
               "makespan": checked(inst, shop.schedule(), agent.name)}
        for _ in range(repeat):
            t0 = time.perf_counter()
            plan = greedy_schedule(inst, rule="est")
            dt = time.perf_counter() - t0
            row["list_seconds"] = min(dt, row.get("list_seconds", dt))
        row["list_makespan"] = checked(inst, plan, "list schedule")
        rows.append(row)
    return rows


def parts(names: list[str], model: str, repeat: int) -> list[dict]:
    """Per shop, where the run's time goes (best of ``repeat`` replays of the model's own run, the plan made
    beforehand as in :func:`measure`): the net's own steps (the legal actions and each action fired, every action of
    the run), and at each decision with a choice the observation's base and full-net features with the action mask
    (``fms_sim.env.ShopEnv._obs``), the guide's features (``PlanGuide.features``, joined to the observation as
    ``FastShopEnv._obs`` joins them) and the numpy actor's logits. The observation so built is checked against the
    env's own at the first decisions, and every decision against the run's."""
    import numpy as np

    from fms_sim.env import ShopEnv
    from fms_sim.full_shop import make_shop

    clock = time.perf_counter
    rows = []
    for name in names:
        inst = _load(name)
        agent = _agent(inst, model)
        shop = make_shop(inst, agent.decisions)
        acts = []
        while not shop.done:  # the plan is made here; the replays adopt it
            acts.append(agent.act(shop))
            shop.act(acts[-1])
        makespan = checked(inst, shop.schedule(), agent.name)
        best: dict[str, float] | None = None
        for _ in range(repeat):
            t = dict.fromkeys(("net", "observation", "guide", "actor"), 0.0)
            shop = make_shop(inst, agent.decisions)
            choices = 0
            for a in acts:
                t0 = clock()
                many = len(shop.legal_actions()) > 1
                t["net"] += clock() - t0
                if many:
                    env = agent._env(shop)
                    t0 = clock()
                    obs, mask = ShopEnv._obs(env), env.action_masks()
                    t1 = clock()
                    if agent.guide is not None:
                        tools = env.legal_of_kind(shop.legal_actions(), "tool").tolist()
                        guide = env._guide().features(shop, tools, env.max_jobs, env.max_tools, env.max_agvs,
                                                      env.max_tts)
                        obs = np.concatenate([obs] + [r.ravel() for r in guide])
                    t2 = clock()
                    logits = agent.actor.logits(obs, mask)
                    t3 = clock()
                    t["observation"] += t1 - t0
                    t["guide"] += t2 - t1
                    t["actor"] += t3 - t2
                    if choices < 20 and not np.array_equal(obs, env.observe()[0]):
                        raise SystemExit(f"{name}: the bench's observation is not the env's (bench/decide_speed.py "
                                         "must follow FastShopEnv._obs)")
                    if env.to_net_action(int(np.argmax(logits))) != a:
                        raise SystemExit(f"{name}: the replay decides differently from the run")
                    choices += 1
                t0 = clock()
                shop.act(a)
                t["net"] += clock() - t0
            if best is None or sum(t.values()) < sum(best.values()):
                best = t
        assert best is not None
        rows.append({"instance": name, "decisions": choices, "makespan": makespan, "model": agent.name,
                     **{k: round(v, 4) for k, v in best.items()}})
    return rows


def solve_once(name: str, model: str) -> dict:
    """One default solve of ``name`` (``/notools``: without tools), timed as ``fms solve`` times it."""
    from fms_dispatch.solvers import solve

    inst = _load(name)
    solver = model if model.lower().startswith("ppo") else f"ppo:{model}"
    sched = solve(inst, solver)
    return {"instance": name, "decisions": 0, "seconds": sched.meta["wall_time"],
            "search": sched.meta.get("guide_search_time"), "beside": sched.meta.get("guide_search_beside"),
            "makespan": checked(inst, sched, solver)}


def _worker(src: Path, names: list[str], model: str, repeat: int, whole: bool = False,
            split: bool = False) -> list[dict]:
    """:func:`measure` (or, ``whole``, :func:`solve_once` per shop, each in its own interpreter; or, ``split``,
    :func:`parts`) in a fresh interpreter on the package source at ``src``."""
    rows = []
    for group in ([[n] for n in names] if whole else [names]):
        rows += run_worker(src, __file__, ["--model", model, "--repeat", str(repeat), "--instances", *group]
                           + (["--solve"] if whole else []) + (["--parts"] if split else []))
    return rows


@contextlib.contextmanager
def _sources(here: Path, baseline: str | None) -> Iterator[list[tuple[str, Path]]]:
    """``[("base", its src), ("new", here)]``, the baseline revision checked out in a temporary git worktree for
    the while (removed afterwards); ``[("new", here)]`` without a baseline."""
    if not baseline:
        yield [("new", here)]
        return
    with tempfile.TemporaryDirectory() as tmp:
        tree = Path(tmp) / "baseline"
        made = subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(tree), baseline],
                              capture_output=True, text=True)
        if made.returncode:  # an unknown revision: git's own words, as one line (run_main: exit 2)
            raise ValueError(f"--baseline {baseline}: " + " ".join(made.stderr.split()))
        try:
            yield [("base", tree / "src"), ("new", here)]
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)], check=False,
                           capture_output=True)


def _alternating(a: argparse.Namespace, here: Path, whole: bool, split: bool = False) -> dict[str, list[dict]]:
    """Per source ("base", "new"), the rows of ``a.repeat`` rounds of one run per shop each, the sources taking turns
    round by round so that both see the same machine load."""
    out: dict[str, list[dict]] = {"new": [], "base": []}
    with _sources(here, a.baseline) as sources:
        for _ in range(a.repeat):
            for who, src in sources:
                out[who] += _worker(src, a.instances, a.model, 1, whole=whole, split=split)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--instances", nargs="+", default=["EX104", "sl00", "sl31", "sl70"])
    ap.add_argument("--model", default="ppo", help="ppo (the default per shop) or a model name")
    ap.add_argument("--repeat", type=positive, default=3, help="timed runs per shop (best reported)")
    ap.add_argument("--baseline", help="git revision to measure alongside, run by run")
    ap.add_argument("--solve", action="store_true", help="time the whole default solve (fresh process per run)")
    ap.add_argument("--parts", action="store_true",
                    help="where a run's time goes: the net's steps, the observation, the guide's features, the actor")
    ap.add_argument("--json", type=output_file, help="write the rows and summary here")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if not a.worker:  # the workers run in the repository's root: a file is named there by its absolute path
        a.instances = [str(Path(base).resolve()) + ("/notools" if notools else "") if Path(base).is_file() else n
                       for n in a.instances for base, notools in [_split(n)]]
    if a.worker:
        print(json.dumps([solve_once(n, a.model) for n in a.instances] if a.solve
                         else parts(a.instances, a.model, a.repeat) if a.parts
                         else measure(a.instances, a.model, a.repeat)))
        return
    here = ROOT / "src"
    if a.parts:
        if a.solve:
            raise ValueError("give one of --parts and --solve")
        _parts_report(a, here)
        return
    if a.solve:
        _solve_report(a, here)
        return
    if not a.baseline:
        rows = _worker(here, a.instances, a.model, a.repeat)
        lines = [f"{platform.node()} {time.strftime('%Y-%m-%d')}, model {a.model}, best of {a.repeat}"]
        for r in rows:
            per = 1000 * r["seconds"] / max(1, r["decisions"])
            lines.append(f"{r['instance']}: {r['decisions']} decisions, {r['seconds']:.3f} s, {per:.3f} ms per "
                         f"decision, makespan {r['makespan']}; list schedule {1000 * r['list_seconds']:.1f} ms")
        report(lines, rows, a.json)
        return
    best: dict[str, dict[str, dict]] = {"new": {}, "base": {}}
    for who, runs in _alternating(a, here, whole=False).items():
        for r in runs:
            old = best[who].get(r["instance"])
            if old is None or r["seconds"] < old["seconds"]:
                best[who][r["instance"]] = r
    rows = []
    lines = [f"{platform.node()} {time.strftime('%Y-%m-%d')}, model {a.model}, best of {a.repeat} alternating runs, "
             f"baseline {a.baseline}"]
    for name in a.instances:
        n, b = best["new"][name], best["base"][name]
        if (n["makespan"], n["decisions"], n["list_makespan"]) != (b["makespan"], b["decisions"], b["list_makespan"]):
            raise SystemExit(f"{name}: the baseline decides or plans differently (makespan {b['makespan']} against "
                             f"{n['makespan']}, decisions {b['decisions']} against {n['decisions']}, list schedule "
                             f"{b['list_makespan']} against {n['list_makespan']})")
        rows.append({"instance": name, "decisions": n["decisions"], "makespan": n["makespan"],
                     "seconds": n["seconds"], "baseline_seconds": b["seconds"], "list_makespan": n["list_makespan"],
                     "list_seconds": n["list_seconds"], "baseline_list_seconds": b["list_seconds"]})
        lines.append(f"{name}: {n['decisions']} decisions, {n['seconds']:.3f} s "
                     f"({1000 * n['seconds'] / max(1, n['decisions']):.3f} ms per decision) against "
                     f"{b['seconds']:.3f} s, {b['seconds'] / n['seconds']:.2f}x; makespan {n['makespan']} (same); list "
                     f"schedule {1000 * n['list_seconds']:.1f} ms against {1000 * b['list_seconds']:.1f} ms, "
                     f"{b['list_seconds'] / n['list_seconds']:.2f}x")
    report(lines, rows, a.json)


PARTS = ("net", "observation", "guide", "actor")


def _parts_report(a: argparse.Namespace, here: Path) -> None:
    """``--parts``: each part's time per decision with a choice (best of ``--repeat`` replays by their total), and
    with ``--baseline`` the same of the baseline's source, alternating with this checkout's replays, with each part's
    speed-up; both must decide alike (the bench stops otherwise)."""
    best: dict[str, dict[str, dict]] = {"new": {}, "base": {}}
    runs = _alternating(a, here, whole=False, split=True) if a.baseline else {"new": _worker(
        here, a.instances, a.model, a.repeat, split=True)}
    for who, rows in runs.items():
        for r in rows:
            old = best[who].get(r["instance"])
            if old is None or sum(r[k] for k in PARTS) < sum(old[k] for k in PARTS):
                best[who][r["instance"]] = r
    head = f"{platform.node()} {time.strftime('%Y-%m-%d')}, best of {a.repeat} replays"
    lines = [head + (f", alternating with baseline {a.baseline}" if a.baseline else "") + ", ms per decision with a "
             "choice (the net's steps: over every action of the run)"]
    rows = []
    for name in a.instances:
        n = best["new"][name]
        total = sum(n[k] for k in PARTS)
        share = ", ".join(f"{k} {1000 * n[k] / n['decisions']:.3f} ({100 * n[k] / total:.0f} %)" for k in PARTS)
        lines.append(f"{name} ({n['model']}): {n['decisions']} decisions, {total:.3f} s: {share}")
        row = dict(n)
        if a.baseline:
            b = best["base"][name]
            if (b["makespan"], b["decisions"]) != (n["makespan"], n["decisions"]):
                raise SystemExit(f"{name}: the baseline decides differently (makespan {b['makespan']} against "
                                 f"{n['makespan']}, decisions {b['decisions']} against {n['decisions']})")
            lines.append("  baseline: " + ", ".join(f"{k} {1000 * b[k] / b['decisions']:.3f} ({b[k] / n[k]:.2f}x)"
                                                    for k in PARTS)
                         + f"; total {sum(b[k] for k in PARTS):.3f} s ({sum(b[k] for k in PARTS) / total:.2f}x)")
            row["baseline"] = {k: b[k] for k in PARTS}
        rows.append(row)
    report(lines, rows, a.json)


def _solve_report(a: argparse.Namespace, here: Path) -> None:
    """``--solve``: every run of every shop in a fresh process, alternating with the baseline's when given; all
    times reported (the search's clock makes the plan, and so the makespan, vary a little between runs)."""
    times: dict[str, dict[str, list[float]]] = {"new": {}, "base": {}}
    spans: dict[str, dict[str, list[int]]] = {"new": {}, "base": {}}
    search: dict[str, list[float]] = {}  # this source's plan search at the start (a baseline may not time it)
    beside: dict[str, list[str]] = {}  # where it ran beside the run: whether the run went on ("kept") or started over
    for who, runs in _alternating(a, here, whole=True).items():
        for r in runs:
            times[who].setdefault(r["instance"], []).append(r["seconds"])
            spans[who].setdefault(r["instance"], []).append(r["makespan"])
            if who == "new" and r.get("search") is not None:
                search.setdefault(r["instance"], []).append(r["search"])
                if r.get("beside") is not None:
                    beside.setdefault(r["instance"], []).append(r["beside"])
    lines = [f"{platform.node()} {time.strftime('%Y-%m-%d')}, {a.model}, whole solves, {a.repeat} each, fresh processes"
             + (f", baseline {a.baseline} alternating" if a.baseline else "")]
    rows = []
    for name in a.instances:
        t = times["new"][name]
        row = {"instance": name, "seconds": t, "makespans": spans["new"][name]}
        line = f"{name}: {min(t):.2f}-{max(t):.2f} s"
        if name in search and name in beside:  # a guided model whose search ran on the other core
            st, outcome = search[name], beside[name]
            row.update(search_seconds=st, search_beside=outcome)
            line += (f" (the plan search {min(st):.2f}-{max(st):.2f} s beside the run; the run went on in "
                     f"{outcome.count('kept')} of {len(outcome)}, started over in {outcome.count('restarted')})")
        elif name in search:  # a guided model: how much of it the plan search took
            st = search[name]
            row["search_seconds"] = st
            line += f" ({min(st):.2f}-{max(st):.2f} s of it the plan search)"
        line += f" (makespans {sorted(set(spans['new'][name]))})"
        if a.baseline:
            b = times["base"][name]
            row.update(baseline_seconds=b, baseline_makespans=spans["base"][name])
            line += (f" against {min(b):.2f}-{max(b):.2f} s (makespans {sorted(set(spans['base'][name]))}), "
                     f"{statistics.mean(b) / statistics.mean(t):.2f}x on the means")
        rows.append(row)
        lines.append(line)
    report(lines, rows, a.json)


if __name__ == "__main__":
    from checks import run_main

    run_main(main)
