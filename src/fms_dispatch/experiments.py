"""``fms experiment ablation|generalization|dynamic|disruptions``: the studies of issue 4 §5 and of disruptions.

Each experiment writes ``<results>/experiment_<name>.csv`` (one row per measurement), ``.json`` (the rows plus
the settings and a summary) and ``.png`` (drawn headless with a Figure + Agg canvas), and prints a Markdown
summary. ``--quick`` shrinks every budget so that the tests can run each experiment in seconds; the quick
figures show that the pipeline works, not what the methods are worth.

* **ablation** — three switches, one at a time:

  - *reward shaping*: two agents trained with the same budget and seed on generated shops of group 4's size
    (``gen:30x20x20*5@140``, quick: one), selected on two others (``@141``), one with the dense ``shaped``
    reward (lower-bound increments, on) and one with the sparse ``makespan`` reward (only the final makespan,
    off); both measured (deterministic, validated) on sl40..sl49 (quick: sl40, sl41), which no agent trains on;
  - *lookahead*: the shipped ``bu`` model (on the paper's net; ``--model``: another) with and without the twin's
    pre-positioning on EX12..EX102 (inference only; quick: EX12, EX22);
  - *masking*: MaskablePPO on five generated job sets on BU layout 2 (``genbu:2*5@150``, quick: one) with
    action masks vs the same algorithm with masking disabled, where an invalid action ends the episode with
    the env's penalty (-10); the curve is the mean reward of the episodes that ended in each rollout.

  Each trained variant (the shaped and the sparse agent, the masked and the unmasked curve) is kept once done in
  ``<results>/experiment_ablation_studies/<study>-<variant>-<digest>/`` (the digest: of the options it follows
  from, :func:`_ablation_key`): its rows (``variant.json``) and, for a reward-shaping agent, the agent in ``model/``,
  where it trains. An interrupt (Ctrl-C, or a stop signal) says what was kept; the same command run again reuses
  each finished variant, continues an interrupted agent's training for the steps it lacks (as ``fms train
  --resume`` does: not bit-identical to an uninterrupted run), trains an interrupted curve again from its start and
  measures the lookahead study again (it trains nothing; its rows follow the model given now); other ``--steps``,
  ``--seed``, ``--quick`` or ``--decisions`` reuse nothing. On stderr each variant's stages are said as they start,
  with PPO's progress, unless ``echo`` is off.

* **generalization** — per size group g of the large benchmark, the general shipped model (on the paper's net
  ``large``, or ``large-agv`` with ``--no-tools``; ``--model``: another) against a specialised agent trained only on
  generated instances of that group's size (``gen:JxMxT*4@(100+g)``, ``--steps`` each, default 20 000; quick: group
  0, 256 steps) and selected on another (``@(120+g)``), measured on sl{g}5..sl{g}9 (quick: sl{g}9). No model trains
  or is selected on a benchmark instance (``fms_sim.shopsets.check_training_specs``). Each group's specialist
  trains in ``<results>/experiment_generalization_groups/g<G>-<digest>/model`` (the digest: of the options it
  follows from, :func:`_group_key`), and its measured rows are kept beside it (``group.json``) once the group is
  done. An interrupt (Ctrl-C, or a stop signal) says what was kept; the same command run again reuses each
  finished group, continues an interrupted training for the steps it lacks (as ``fms train --resume`` does: not
  bit-identical to an uninterrupted run) and measures the general model again; other ``--steps``, ``--seed``,
  ``--quick``, ``--no-tools`` or ``--decisions`` reuse nothing. On stderr each group's stages (general model,
  training, measuring) are said as they start, with PPO's progress, unless ``echo`` is off.

* **dynamic** — an instance's jobs split into 10 partitions (job j in partition ``j*10//n``); partition p
  arrives at ``p*Δ`` with ``Δ`` = the instance's simple lower bound (max of the largest machine load and the
  longest job's processing time, transport ignored) / 10. The RL agent runs one live :class:`~fms_sim.shop.Shop`
  and adds each partition with :meth:`~fms_sim.shop.Shop.add_jobs` at the first decision moment at or after its
  arrival (``entered_at``; if the shop would otherwise finish first, the partition enters at that last decision,
  early, flagged ``early``); after each arrival the projected makespan of all jobs so far is the run of a twin to
  the end. SOS re-solves from scratch at each arrival the instance of all jobs arrived so far. The Instance
  model has no release times, so SOS schedules those jobs **released at 0**: its makespans are an optimistic
  bound, not a feasible plan under the arrivals. The RL time is the policy's decision time (cumulative; the
  projections are timed separately), the SOS time its cumulative search time.

The paper's net and the full one side by side: ``--decisions full`` runs the ablation and the generalization
study on the full net (the shipped default model, ``guided-dagger``, for the lookahead study and as the general
model; the trained agents train on the full net). ``--model`` names another shipped model (or a model folder) for
the lookahead study and as the general model, one that decides through the net the study runs on (``full``, the
full-net clone of CP-SAT plans, on the full net). The lookahead study's *on* is the model's own lookahead: the
verified twin (:func:`~fms_dispatch.rl.lookahead.run_agent`), or, for a guided model, its plan's empty trips
(``lookahead="guide"`` of :func:`~fms_dispatch.rl.ppo_solver`); a guided model searches its plan once per
instance, in the *off* run, and the *on* run acts out the same plan (its ``wall_time`` leaves the search out), so
the study measures the lookahead, not two searches that stop on the clock. ``fms experiment dynamic --model M``
continues model M on a live shop of its net.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import functools
import json
import math
import numbers
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from fms_sim.benchmarks import SL_GROUPS
from fms_sim.files import replacing, write_atomically
from fms_sim.shopsets import expand_specs
from fms_sim.instance import Instance
from fms_sim.schedule import Schedule
from fms_sim.shop import Shop
from fms_sim.validate import validate

from .progress import say

__all__ = ["run_ablation", "run_generalization", "run_dynamic", "run_arrivals", "add_experiment_parser", "lower_bound",
           "partition_jobs", "ABLATION_STUDIES", "ABLATION_COLUMNS", "GENERALIZATION_COLUMNS", "DYNAMIC_COLUMNS"]

ABLATION_COLUMNS = ("study", "variant", "instance", "makespan", "valid", "wall_time", "timesteps",
                    "mean_episode_reward", "episodes", "invalid_episodes")
ABLATION_STUDIES = ("reward_shaping", "lookahead", "masking")
GENERALIZATION_COLUMNS = ("group", "size", "agent", "instance", "makespan", "valid", "wall_time", "train_steps")
DISRUPTION_COLUMNS = ("instance", "mode", "noise", "seed", "breakdowns", "method", "makespan", "nominal_makespan",
                      "ratio", "decisions", "latency_ms", "plan_time")
DISRUPTION_METHODS = ("plan:cpsat", "plan:cpsat+replan", "best-rule", "ppo", "ppo+lookahead", "default")
#: the PPO model of the disruptions experiment: it must decide through the full net, which runs disruptions
DISRUPTION_MODEL = "full"
#: PPO + lookahead runs only on shops with at most this many operations by default: in a disrupted shop every
#: idle stop rolls the policy out afresh on a nominal copy (about 5 min per run on sl00, 225 operations)
DISRUPTION_LOOKAHEAD_MAX_OPS = 100
#: the shipped model of the ablation's lookahead study on the paper's net (on the full net: the default model,
#: :func:`~fms_dispatch.rl.models.default_model_name`)
ABLATION_LOOKAHEAD_MODEL = {"paper": "bu"}
#: the general shipped model of the generalization study on the paper's net, per tool mode (on the full net: the
#: default model, which covers both)
GENERAL_MODEL = {("paper", False): "large", ("paper", True): "large-agv"}
DYNAMIC_COLUMNS = ("partition", "arrival", "entered_at", "early", "jobs_so_far", "rl_makespan", "rl_time_cum",
                   "rl_projection_time", "sos_makespan", "sos_time_cum", "sos_valid")


# ---------------------------------------------------------------------- shared helpers
def _check_decisions(decisions: str) -> None:
    if decisions not in ("paper", "full"):
        raise ValueError(f"unknown decisions {decisions!r}; choose paper or full")


def _study_model(model: str | None, default: str | None, decisions: str, inst: Instance) -> tuple[str, Any]:
    """The model a study runs (``model``, else ``default``, else the shipped default model for ``inst``): its
    name or folder as given and the loaded agent, checked to decide through the study's net (``decisions``); a
    model of the other net is refused, naming the option that fits it."""
    from .rl.models import default_model_name, load_agent

    spec = model or default or default_model_name(inst)
    agent = load_agent(spec)
    if agent.decisions != decisions:
        raise ValueError(f"model {agent.name} decides through the {agent.decisions} net, but this study runs on the "
                         f"{decisions} net; run it with --decisions {agent.decisions} or name a {decisions}-net model")
    return spec, agent


def _model_run(spec: str, agent: Any, inst: Instance, lookahead: bool) -> Schedule:
    """``inst`` solved by the model ``spec`` (loaded as ``agent``) as ``fms solve --solver ppo:MODEL`` does, with
    the model's own lookahead if asked: the verified twin's pre-positioning, or, for a guided model, the plan's
    empty trips (``lookahead="guide"``)."""
    from .rl import ppo_solver

    mode: bool | str = ("guide" if agent.guide is not None else True) if lookahead else False
    return ppo_solver(f"ppo:{spec}")(inst, lookahead=mode)


def _checked(inst: Instance, sched: Schedule) -> bool:
    """Validate ``sched``; an infeasible schedule is a bug, so it raises instead of being reported."""
    problems = validate(inst, sched)
    if problems:
        raise RuntimeError(f"infeasible schedule for {inst.name}: {problems[0]}")
    return True


def _valid_makespan(inst: Instance, sched: Schedule) -> int:
    """``sched``'s makespan once :func:`_checked` found it valid: the reference makespans the tables divide by or
    compare with (disruptions' nominal runs, dynamic's static run) were taken unchecked."""
    _checked(inst, sched)
    return sched.makespan


def _write(name: str, results_dir: str | Path, columns: Sequence[str], rows: list[dict[str, Any]],
           meta: dict[str, Any], draw: Callable[[Path], None]) -> dict[str, Path]:
    """Write ``experiment_<name>.csv/.json/.png`` under ``results_dir``; returns their paths.

    All three are written to temporaries first and replace the last run's files only once all three are complete:
    they were written in place one after the other, so an interrupt or an error while drawing (or while writing the
    CSV) left a half-written file, or this run's CSV and JSON beside the last run's chart."""
    out = Path(results_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {ext: out / f"experiment_{name}.{ext}" for ext in ("csv", "json", "png")}
    doc = _no_nan(dict(meta, rows=rows))  # strict JSON: a missing value (NaN) becomes null
    text = json.dumps(doc, indent=2, default=_jsonable, allow_nan=False) + "\n"
    with replacing(paths["csv"]) as tmp_csv, replacing(paths["json"]) as tmp_json, \
            replacing(paths["png"], suffix=".tmp.png") as tmp_png:  # (matplotlib reads the format from the name)
        with tmp_csv.open("w", newline="", encoding="utf-8") as fh:
            w = csv.DictWriter(fh, fieldnames=list(columns), extrasaction="ignore")
            w.writeheader()
            for r in rows:
                w.writerow({c: ("" if r.get(c) is None else r.get(c)) for c in columns})
        tmp_json.write_text(text, encoding="utf-8")
        draw(tmp_png)
    return paths


def _no_nan(x: Any) -> Any:
    """``x`` with every NaN float (in nested dicts and lists) replaced by None."""
    if isinstance(x, float) and math.isnan(x):
        return None
    if isinstance(x, dict):
        return {k: _no_nan(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_no_nan(v) for v in x]
    return x


def _jsonable(x: Any) -> Any:
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.floating,)):
        return float(x)
    return str(x)


def _figure(w: float, h: float, ncols: int = 1, nrows: int = 1) -> tuple[Any, Any]:
    """A headless figure (no pyplot) and its axes."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w, h), dpi=100)
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=False)
    return fig, axes


def _mean(xs: Sequence[float]) -> float:
    xs = [x for x in xs if x is not None and not (isinstance(x, float) and math.isnan(x))]
    return round(float(np.mean(xs)), 2) if xs else math.nan


def _ppo_budget(steps: int) -> dict[str, int]:
    """PPO rollout sizes that fit a (possibly tiny) budget: at least one full update per run."""
    n_steps = max(16, min(512, steps))
    return {"n_steps": n_steps, "batch_size": max(8, min(256, n_steps // 2))}


def lower_bound(inst: Instance) -> int:
    """Simple makespan lower bound: the largest machine load or the longest job (transport ignored)."""
    load = [0] * (inst.n_machines + 1)
    for ops in inst.jobs:
        for op in ops:
            load[op.machine] += op.duration
    return max(max(load), max(sum(op.duration for op in ops) for ops in inst.jobs))


def _train_agent(train_specs: list[str], eval_specs: list[str], steps: int, seed: int, reward: str,
                 folder: Path, padding: str | dict[str, int] = "auto",
                 fleet: dict[str, Any] | None = None, measure: list[str] | None = None,
                 decisions: str = "paper", progress: bool = False) -> dict[str, Any]:
    """Train one small agent with :func:`fms_dispatch.rl.train.train` on generated shops (``train_specs``,
    selected on ``eval_specs``); returns its metrics, with ``"measured"``: the validated deterministic
    makespans on the instances ``measure`` (benchmark instances, which training never sees). An interrupted
    training raises KeyboardInterrupt once its folder holds what was learnt (:func:`_stop_if_interrupted`);
    ``progress``: PPO's progress as ``fms train`` shows it."""
    from .rl.train import train

    metrics = train(_agent_config(train_specs, eval_specs, steps, seed, reward, padding, fleet, decisions), folder,
                    progress=progress, tensorboard=folder / "tb")
    _stop_if_interrupted(metrics)
    if measure:
        metrics["measured"] = _measure(folder, metrics, measure, fleet)
    return metrics


def _agent_config(train_specs: list[str], eval_specs: list[str], steps: int, seed: int, reward: str,
                  padding: str | dict[str, int], fleet: dict[str, Any] | None, decisions: str) -> dict[str, Any]:
    """The :func:`fms_dispatch.rl.train.train` config of one small agent of :func:`_train_agent`."""
    return {"train": train_specs, "eval": eval_specs, "steps": steps, "seed": seed, "reward": reward,
            "padding": padding, "n_envs": 1, "vec_env": "dummy", "eval_freq": 10 * steps + 10_000,
            "save_freq": 10 * steps + 10_000, "ppo": _ppo_budget(steps), "fleet": fleet or {},
            "decisions": decisions}


def _stop_if_interrupted(metrics: dict[str, Any]) -> None:
    """Raise KeyboardInterrupt if the training that returned ``metrics`` was interrupted. ``train`` keeps what was
    learnt on Ctrl-C (or a stop signal) and returns, as ``fms train`` should; an experiment went on with the agent cut
    short as if it had trained its budget (a specialist of 0 steps in the tables) and ran the next group's training,
    so one Ctrl-C did not stop it."""
    if metrics.get("training", {}).get("interrupted"):
        raise KeyboardInterrupt


def _measure(folder: Path, metrics: dict[str, Any], measure: list[str],
             fleet: dict[str, Any] | None) -> dict[str, int]:
    """The validated deterministic makespans of the agent trained in ``folder`` (its solving weights, named in
    ``metrics``) on the instances ``measure``."""
    from .rl.envs import padding_for
    from .rl.train import evaluate_model, expand_instances

    used = json.loads((folder / "config.json").read_text())
    weights = folder / metrics["training"]["weights"]
    return evaluate_model(weights, padding_for(used["padding"], []), expand_instances(measure, fleet),
                          decisions=used["decisions"])


# ---------------------------------------------------------------------- kept work
# The ablation and the generalization study keep each finished unit (an ablation variant, a generalization group)
# under ``<results>/experiment_<name>_<units>/<label>-<digest>/``: its rows (written last and whole) and, for a
# trained agent, the agent in ``model/``; the digest is of the unit's key, everything the unit follows from.


def _kept_folder(root: Path, label: str, key: dict[str, Any]) -> Path:
    """The folder of a unit's kept work under ``root``: ``<label>-<digest of its key>``."""
    import hashlib

    digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:12]
    return root / f"{label}-{digest}"


def _kept_rows(folder: Path, key: dict[str, Any], name: str) -> list[dict[str, Any]] | None:
    """The rows a finished unit kept in ``folder/name`` (written last and whole), or None where there are none of
    this ``key``."""
    try:
        doc = json.loads((folder / name).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(doc, dict) or doc.get("key") != key or not isinstance(doc.get("rows"), list):
        return None
    return doc["rows"]


def _kept_or_made(folder: Path, key: dict[str, Any], name: str,
                  make: Callable[[], list[dict[str, Any]]]) -> tuple[list[dict[str, Any]], bool]:
    """The rows a finished unit of ``key`` kept in ``folder/name`` and True; where there are none, the rows
    ``make()`` returns, kept there once it has returned (``key.json`` beside them says, from the start of the work,
    what the folder holds), and False."""
    kept = _kept_rows(folder, key, name)
    if kept is not None:
        return kept, True
    write_atomically(folder / "key.json", json.dumps(key, indent=2) + "\n")
    rows = make()
    write_atomically(folder / name, json.dumps({"key": key, "rows": rows}, indent=2, default=_jsonable) + "\n")
    return rows, False


def _kept_training(model: Path) -> dict[str, Any] | None:
    """The metrics of the training an earlier run left in the folder ``model`` (finished or interrupted with its
    weights saved), or None where there is none to go on from."""
    try:
        metrics = json.loads((model / "metrics.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    ok = (isinstance(metrics, dict) and isinstance(metrics.get("training"), dict)
          and (model / "config.json").is_file() and (model / str(metrics["training"].get("weights"))).is_file())
    return metrics if ok else None


def _trained_agent(folder: Path, key: dict[str, Any], fleet: dict[str, Any], note: Callable[[str], None],
                   progress: bool, agent: str = "agent") -> dict[str, Any]:
    """Train the agent of ``key`` (its ``train``, ``select``, ``steps``, ``seed``, ``reward``, ``padding`` and
    ``decisions``) in ``folder/model`` and return its metrics with ``"measured"`` (on ``key["measure"]``), going on
    from what an earlier run of the same key left there: a finished training is only measured, an interrupted one
    continues for the steps it lacks (``fms train --resume``), anything else trains afresh. ``note`` is told each
    stage as it starts (``agent``: what the measuring stage calls the agent)."""
    from .rl.train import train

    model = folder / "model"
    steps = int(key["steps"])
    metrics = _kept_training(model)
    done = int(metrics.get("ppo_steps", 0)) if metrics else 0
    if metrics is not None and not metrics["training"].get("interrupted"):
        note(f"its agent trained before ({done} steps) is reused")
    elif metrics is not None and done < steps and (model / "model.zip").is_file():
        note(f"training: continues the agent interrupted after {done} of {steps} steps")
        metrics = train({"steps": steps - done}, model, resume=True, progress=progress, tensorboard=model / "tb")
        _stop_if_interrupted(metrics)
    elif metrics is not None:
        note(f"its agent trained before ({done} steps; interrupted while evaluating) is reused")
    else:
        note(f"training: {steps} steps")
        metrics = train(_agent_config(key["train"], key["select"], steps, int(key["seed"]), key["reward"],
                                      key["padding"], fleet, key["decisions"]),
                        model, progress=progress, tensorboard=model / "tb", force=True)
        _stop_if_interrupted(metrics)
    note(f"measuring the {agent} on {len(key['measure'])} instance(s)")
    metrics["measured"] = _measure(model, metrics, key["measure"], fleet)
    return metrics


class _Stages:
    """What a resumable experiment says of its units (ablation variants, generalization groups) on stderr: with
    ``echo``, each unit's stages as they start, with the time elapsed; on an interrupt (always) in which unit and
    stage it stopped, which units were kept in ``root``, how far the unit's agent trained (``model``: where it
    trains, once known) and that the same command goes on."""

    def __init__(self, experiment: str, unit: str, total: int, root: Path, steps: int, echo: bool) -> None:
        self.experiment, self.unit, self.total, self.root, self.steps, self.echo = \
            experiment, unit, total, root, steps, echo
        self.t_start = self.t_unit = time.perf_counter()
        self.name = self.heading = "the start"  # the running unit, as the interrupt and the stage lines name it
        self.stage = "starting"
        self.model: Path | None = None
        self.finished = 0
        self.kept: list[str] = []

    def start(self, name: str, heading: str | None = None) -> None:
        """A unit starts: ``name`` in the interrupt's words, ``heading`` (default ``name``) in the stage lines'."""
        self.name, self.heading, self.model, self.t_unit = name, heading or name, None, time.perf_counter()

    def note(self, what: str) -> None:
        """The running unit's next stage."""
        self.stage = what
        if self.echo:
            say(f"{self.experiment}: {self.heading} [{self.finished + 1}/{self.total}]: {what} "
                f"({time.perf_counter() - self.t_start:.0f} s in all)")

    def finish(self, kept_as: str | None) -> None:
        """The running unit is done; ``kept_as``: its label in the list of the units kept in ``root`` (None: its
        work is not kept)."""
        self.note(f"done in {time.perf_counter() - self.t_unit:.0f} s")
        self.finished += 1
        self.model = None
        if kept_as is not None:
            self.kept.append(kept_as)

    def interrupted(self) -> None:
        """Say, on stderr, where the run was interrupted, what it kept, and how to go on."""
        partly = _kept_training(self.model) if self.model is not None else None
        left = ""
        if partly is not None:
            done = int(partly.get("ppo_steps", 0))
            left = (f"; {self.name}'s agent, trained {done} of {self.steps} steps, in {self.model}: its training "
                    "continues from there" if done < self.steps else f"; {self.name}'s trained agent, not yet "
                    f"measured, in {self.model}")
        say(f"{self.experiment}: interrupted in {self.name} ({self.stage}) after {self.finished} of {self.total} "
            f"{self.unit}(s); kept: {len(self.kept)} finished {self.unit}(s) ({', '.join(self.kept) or 'none'}) in "
            f"{self.root}{left}; the tables were not written: run the same command again to continue")


# ---------------------------------------------------------------------- ablation
def _episode_curve(use_masking: bool, instances: list[Instance], steps: int, seed: int,
                   decisions: str = "paper") -> list[dict[str, Any]]:
    """Train MaskablePPO (entity policy, shaped reward, on the ``decisions`` net) with or without masks; mean
    episode reward per rollout."""
    import torch
    from sb3_contrib import MaskablePPO
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.logger import Logger
    from stable_baselines3.common.monitor import Monitor
    from stable_baselines3.common.vec_env import DummyVecEnv

    from .rl.envs import FastShopEnv, obs_layout, padding_for
    from .rl.policy import EntityPolicy

    torch.set_num_threads(1)
    padding = padding_for("auto", instances)

    def make() -> Any:
        env = FastShopEnv(instances, reward="shaped", invalid_action="penalty", decisions=decisions, **padding)
        env.reset(seed=seed)
        return Monitor(env)

    venv = DummyVecEnv([make])
    points: list[dict[str, Any]] = []

    class Curve(BaseCallback):
        """Collects finished episodes' rewards; one point per rollout."""

        def __init__(self) -> None:
            super().__init__()
            self.rewards: list[float] = []
            self.invalid = 0

        def _on_step(self) -> bool:
            for info in self.locals.get("infos", []):
                if "episode" in info:
                    self.rewards.append(float(info["episode"]["r"]))
                    self.invalid += bool(info.get("invalid_action"))
            return True

        def _on_rollout_end(self) -> None:
            points.append({"timesteps": int(self.num_timesteps),
                           "mean_episode_reward": round(float(np.mean(self.rewards)), 4) if self.rewards
                           else math.nan,
                           "episodes": len(self.rewards), "invalid_episodes": self.invalid})
            self.rewards, self.invalid = [], 0

    # about 8+ rollouts, so that even a tiny budget draws a curve
    ppo = dict(learning_rate=3e-4, n_epochs=5, gamma=1.0, gae_lambda=0.95, ent_coef=0.01,
               **_ppo_budget(max(16, steps // 8)))
    model = MaskablePPO(EntityPolicy, venv, policy_kwargs={"layout": obs_layout(padding, decisions)}, seed=seed,
                        device="cpu", verbose=0, **ppo)
    model.set_logger(Logger(folder=None, output_formats=[]))  # the curve is all it keeps (sb3's default logger
    # made an empty SB3-<time> folder in the temp folder per run)
    model.learn(total_timesteps=steps, callback=Curve(), use_masking=use_masking)
    venv.close()
    return points


#: the folder under ``--results-dir`` that keeps each finished trained variant of the ablation (the reward-shaping
#: agents with their rows, the masking curves; one sub-folder per variant and options, :func:`_ablation_key`)
ABLATION_DIR = "experiment_ablation_studies"
#: the format of a kept variant (a kept variant of another format is done again)
ABLATION_FORMAT = 1


def _ablation_key(study: str, variant: str, steps: int, seed: int, decisions: str, **more: Any) -> dict[str, Any]:
    """Everything a trained variant of the ablation follows from (``more``: its study's inputs, such as the
    instances it trains on): a kept variant is reused only by a run whose key is equal (a run with other
    ``--steps``, ``--seed``, ``--quick`` or ``--decisions`` does its own). The lookahead study is not kept: it trains
    nothing, and its rows follow the model given now."""
    return {"format": ABLATION_FORMAT, "study": study, "variant": variant, "steps": steps, "seed": seed,
            "decisions": decisions, **more}


def _shaping_rows(folder: Path, key: dict[str, Any], note: Callable[[str], None],
                  progress: bool) -> list[dict[str, Any]]:
    """A reward-shaping agent of ``key`` trained (or its training continued) in ``folder/model`` and measured: its
    rows of the ablation table."""
    trained = _trained_agent(folder, key, key["fleet"], note, progress)
    m = trained["training"]
    return [{"study": key["study"], "variant": key["variant"], "instance": name, "makespan": ms, "valid": True,
             "wall_time": m["wall_seconds"], "timesteps": m["timesteps"]} for name, ms in trained["measured"].items()]


def _masking_rows(folder: Path, key: dict[str, Any], instances: list[Instance], masks: bool,
                  note: Callable[[str], None]) -> list[dict[str, Any]]:
    """The training curve of the masking variant ``key`` (with action masks or without) on ``instances``: its rows
    of the ablation table. Nothing of an interrupted curve is kept (``folder`` holds only the finished rows): it is
    trained again from its start."""
    t0 = time.perf_counter()
    note(f"training: {key['steps']} steps")
    return [dict(p, study=key["study"], variant=key["variant"], wall_time=round(time.perf_counter() - t0, 2))
            for p in _episode_curve(masks, instances, int(key["steps"]), int(key["seed"]), key["decisions"])]


def run_ablation(quick: bool = False, results_dir: str | Path = "results", seed: int = 0,
                 steps: int | None = None, studies: Sequence[str] | None = None,
                 echo: bool = True, decisions: str = "paper", model: str | None = None) -> dict[str, Any]:
    """The ablations in ``studies`` (default all of :data:`ABLATION_STUDIES`; see the module docstring) on the
    paper's net or the full one (``decisions``), the lookahead study with ``model`` (default: ``bu`` on the
    paper's net, the shipped default model on the full one); returns the JSON document written.

    Each trained variant is kept in ``<results_dir>/experiment_ablation_studies/<study>-<variant>-<digest>/`` once
    done (a reward-shaping agent trains there, in ``model/``): a later run with the same options reuses a finished
    variant, continues an agent's training that was interrupted, and measures the lookahead study again; a run
    with other options (:func:`_ablation_key`) does its own. On an interrupt (Ctrl-C, or a stop signal ``fms``
    turns into one) it says what was kept and re-raises. With ``echo`` each variant's stages are said on stderr as
    they start (and PPO's progress) and the summary is printed."""
    from fms_sim.formats import load_instance

    rows: list[dict[str, Any]] = []
    steps = int(steps) if steps else (128 if quick else 20_000)
    if steps <= 0:
        raise ValueError("--steps must be positive")
    _check_decisions(decisions)
    chosen = list(studies) if studies else list(ABLATION_STUDIES)
    for st in chosen:
        if st not in ABLATION_STUDIES:
            raise ValueError(f"unknown ablation study {st!r}; choose from {', '.join(ABLATION_STUDIES)}")
    look_sets = ([1, 2] if quick else list(range(1, 11))) if "lookahead" in chosen else []
    look_model = look_mode = None
    guided = False
    if look_sets:  # the lookahead study's model, checked before any training (the other net's would fail after it)
        spec, agent = _study_model(model, ABLATION_LOOKAHEAD_MODEL.get(decisions), decisions, load_instance("EX12"))
        look_model = agent.name
        guided = agent.guide is not None
        look_mode = "plan's empty trips" if guided else "verified twin"
    # (1) reward shaping
    # trained on generated shops of group 4's size, selected on others, measured on sl40.. (never trained on)
    j4, m4, t4 = SL_GROUPS[4]
    train_sl = [f"gen:{j4}x{m4}x{t4}*{1 if quick else 5}@140"]
    select_sl = [f"gen:{j4}x{m4}x{t4}*{1 if quick else 2}@141"]
    eval_sl = ["sl40", "sl41"] if quick else [f"sl4{k}" for k in range(10)]
    shaping = (("shaped", "shaped"), ("sparse", "makespan")) if "reward_shaping" in chosen else ()
    # (3) masking: generated job sets on BU layout 2 (the studies train on them; no benchmark instance is)
    mask_specs = [f"genbu:2*{1 if quick else 5}@150"]
    mask_insts = expand_specs(mask_specs)
    masking = (("masked", True), ("unmasked", False)) if "masking" in chosen else ()
    root = Path(results_dir) / ABLATION_DIR
    reused: list[str] = []
    stages = _Stages("ablation", "variant", len(shaping) + bool(look_sets) + len(masking), root, steps, echo)
    if echo:
        say(f"ablation: {', '.join(chosen)}: {stages.total} variant(s), {steps} training steps per agent; each "
            f"finished trained variant is kept in {root}")

    def run_variant(study: str, variant: str, key: dict[str, Any],
                    make: Callable[..., list[dict[str, Any]]]) -> None:
        """Rows of one trained variant: kept ones, or those ``make(folder)`` returns, kept once it has returned."""
        name = f"{study.replace('_', ' ')} {variant}"
        stages.start(name)
        folder = _kept_folder(root, f"{study}-{variant}", key)
        stages.model = folder / "model" if study == "reward_shaping" else None
        got, was_kept = _kept_or_made(folder, key, "variant.json", functools.partial(make, folder))
        if was_kept:
            stages.note(f"its {len(got)} row(s) reused from {folder}")
            reused.append(f"{study}/{variant}")
        rows.extend(got)
        stages.finish(name)

    try:
        for variant, reward in shaping:
            key = _ablation_key("reward_shaping", variant, steps, seed, decisions, train=train_sl, select=select_sl,
                                measure=eval_sl, fleet={}, reward=reward, padding="auto", ppo=_ppo_budget(steps))
            run_variant("reward_shaping", variant, key,
                        functools.partial(_shaping_rows, key=key, note=stages.note, progress=echo))
        # (2) lookahead with the study's model (shipped, of BU scale or general), measured again on every run
        if look_sets:
            stages.start("lookahead")
        for i, s in enumerate(look_sets):
            inst = load_instance(f"EX{s}2")
            stages.note(f"{look_model} off and on, {inst.name} [{i + 1}/{len(look_sets)}]")
            for variant, la in (("off", False), ("on", True)):
                if not la:  # a guided model searches its plan once per instance, in the off run; the on run acts
                    agent.forget()  # out the same plan, so the study sees the lookahead alone, not two searches
                t0 = time.perf_counter()
                sched = _model_run(spec, agent, inst, la)
                wall = time.perf_counter() - t0
                rows.append({"study": "lookahead", "variant": variant, "instance": inst.name,
                             "makespan": sched.makespan, "valid": _checked(inst, sched), "wall_time": round(wall, 4)})
        if look_sets:
            stages.finish(None)
        for variant, flag in masking:
            key = _ablation_key("masking", variant, steps, seed, decisions, instances=mask_specs, reward="shaped",
                                invalid_action="penalty", ppo=_ppo_budget(max(16, steps // 8)))
            run_variant("masking", variant, key,
                        functools.partial(_masking_rows, key=key, instances=mask_insts, masks=flag, note=stages.note))
    except KeyboardInterrupt:  # (every finished study was lost: agents in a temporary folder, rows in memory)
        stages.interrupted()
        raise

    summary: dict[str, Any] = {}
    for study, variants in (("reward_shaping", ("shaped", "sparse")), ("lookahead", ("off", "on"))):
        summary[study] = {v: _mean([r["makespan"] for r in rows if r["study"] == study and r["variant"] == v])
                          for v in variants}
    summary["masking"] = {v: {"final_mean_episode_reward": next(
        (r["mean_episode_reward"] for r in reversed(rows) if r["study"] == "masking" and r["variant"] == v
         and not math.isnan(r["mean_episode_reward"])), None),
        "invalid_episodes": sum(r["invalid_episodes"] for r in rows if r["study"] == "masking"
                                and r["variant"] == v)} for v in ("masked", "unmasked")}
    summary = {k: v for k, v in summary.items() if k in chosen}
    meta = {"experiment": "ablation", "quick": quick, "seed": seed, "steps": steps, "studies": chosen,
            "decisions": decisions,
            "reward_shaping": {"train": train_sl, "eval": eval_sl, "on": "shaped", "off": "makespan (sparse)"},
            "lookahead": {"model": look_model, "mode": look_mode,
                          "plan": "searched in the off run, acted out again in the on run" if guided else None},
            "masking": {"instances": [i.name for i in mask_insts], "invalid_penalty": -10.0},
            "kept_in": str(root), "reused_variants": reused, "summary": summary}

    def draw(path: Path) -> None:
        fig, ax = _figure(15, 4.5, ncols=3)
        a0, a1, a2 = ax[0]
        rs = summary.get("reward_shaping", {})
        a0.bar(["shaped", "sparse"], [rs.get("shaped", math.nan), rs.get("sparse", math.nan)],
               color=["tab:blue", "tab:orange"])
        a0.set_title(f"reward shaping ({steps} steps)")
        a0.set_ylabel(f"mean makespan ({eval_sl[0]}-{eval_sl[-1][2:]}, never trained on)")
        la_names = sorted({r["instance"] for r in rows if r["study"] == "lookahead"},
                          key=lambda n: int(n[2:-1]))
        for v, c in (("off", "tab:gray"), ("on", "tab:green")):
            cell = {r["instance"]: r["makespan"] for r in rows if r["study"] == "lookahead" and r["variant"] == v}
            a1.plot(la_names, [cell[n] for n in la_names], marker="o", color=c, label=f"lookahead {v}")
        a1.set_title(f"lookahead ({look_model} model, {look_mode})")
        a1.set_ylabel("makespan")
        a1.tick_params(axis="x", labelrotation=60)
        a1.legend()
        for v, c in (("masked", "tab:blue"), ("unmasked", "tab:red")):
            pts = [r for r in rows if r["study"] == "masking" and r["variant"] == v]
            a2.plot([p["timesteps"] for p in pts], [p["mean_episode_reward"] for p in pts], marker=".", color=c,
                    label=v)
        a2.set_title("action masking: training curve")
        a2.set_xlabel("timesteps")
        a2.set_ylabel("mean episode reward")
        a2.legend()
        for a, study in ((a0, "reward_shaping"), (a1, "lookahead"), (a2, "masking")):
            if study not in chosen:
                a.clear()
                a.axis("off")
                a.text(0.5, 0.5, f"{study}: not run", ha="center", va="center", transform=a.transAxes)
        fig.tight_layout()
        fig.savefig(path)

    paths = _write("ablation", results_dir, ABLATION_COLUMNS, rows, meta, draw)
    if echo:
        print("| study | variant | result |\n|---|---|---|")
        for study in ("reward_shaping", "lookahead"):
            label = f"lookahead ({look_model}: {look_mode})" if study == "lookahead" else study
            for v, x in summary.get(study, {}).items():
                print(f"| {label} | {v} | mean makespan {x} |")
        for v, d in summary.get("masking", {}).items():
            print(f"| masking | {v} | final mean episode reward {d['final_mean_episode_reward']}, "
                  f"invalid episodes {d['invalid_episodes']} |")
        print(f"\nwritten: {', '.join(str(p) for p in paths.values())}")
    return dict(meta, rows=rows)


# ---------------------------------------------------------------------- generalization
#: the folder under ``--results-dir`` that keeps each finished group's specialised agent and rows (one sub-folder
#: per group and options, :func:`_group_key`), so that an interrupted run loses no finished group
GROUPS_DIR = "experiment_generalization_groups"
#: the format of a kept group (a kept group of another format is trained again)
GROUP_FORMAT = 1


def _group_key(g: int, train_spec: list[str], select: list[str], held: list[str], steps: int, seed: int,
               fleet: dict[str, Any], decisions: str) -> dict[str, Any]:
    """Everything a group's specialised agent and its rows follow from: a kept group is reused only by a run whose
    key is equal (a run with other ``--steps``, ``--seed``, ``--quick``, ``--no-tools`` or ``--decisions`` trains
    its own). The general model is not in it: its rows are measured again on every run."""
    return {"format": GROUP_FORMAT, "group": g, "size": "x".join(map(str, SL_GROUPS[g])), "train": train_spec,
            "select": select, "measure": held, "steps": steps, "seed": seed, "fleet": fleet, "decisions": decisions,
            "reward": "shaped", "padding": "auto", "ppo": _ppo_budget(steps)}


def _specialist_rows(folder: Path, key: dict[str, Any], size: str, note: Callable[[str], None],
                     progress: bool) -> list[dict[str, Any]]:
    """Group ``key``'s specialised agent trained (or its training continued) in ``folder/model`` and measured: its
    rows of the generalization table."""
    trained = _trained_agent(folder, key, key["fleet"], note, progress, agent="specialised agent")
    met = trained["training"]
    return [{"group": key["group"], "size": size, "agent": "specialized", "instance": name, "makespan": ms,
             "valid": True, "wall_time": met["wall_seconds"],  # validated by evaluate_model
             "train_steps": int(trained.get("ppo_steps", met["timesteps"]))}
            for name, ms in trained["measured"].items()]


def run_generalization(quick: bool = False, results_dir: str | Path = "results", seed: int = 0,
                       steps: int | None = None, groups: Sequence[int] | None = None, no_tools: bool = False,
                       echo: bool = True, decisions: str = "paper", model: str | None = None) -> dict[str, Any]:
    """General shipped model vs an agent specialised per size group (see the module docstring), on the paper's
    net or the full one (``decisions``); the general model is ``model`` (default: ``large`` / ``large-agv`` on the
    paper's net, the shipped default model on the full one).

    Each group's specialised agent trains in ``<results_dir>/experiment_generalization_groups/g<G>-<digest>/model``
    and its rows are kept beside it (``group.json``) once measured: a later run with the same options reuses a
    finished group, continues a training that was interrupted, and measures the general model again; a run with
    other options (:func:`_group_key`) trains its own. On an interrupt (Ctrl-C, or a stop signal ``fms`` turns into
    one) it says what was kept and re-raises. With ``echo`` each group's stages are said on stderr as they start
    (and PPO's progress) and the summary is printed."""
    from .rl.train import expand_instances

    steps = int(steps) if steps else (256 if quick else 20_000)
    if steps <= 0:
        raise ValueError("--steps must be positive")
    groups = list(groups) if groups is not None else ([0] if quick else list(range(len(SL_GROUPS))))
    for g in groups:
        if not 0 <= g < len(SL_GROUPS):
            raise ValueError(f"size group {g} does not exist (0-{len(SL_GROUPS) - 1})")
    _check_decisions(decisions)
    fleet = {"no_tools": no_tools}
    first = expand_instances([f"sl{groups[0] if groups else 0}9"], fleet)[0]
    general_spec, agent = _study_model(model, GENERAL_MODEL.get((decisions, bool(no_tools))), decisions, first)
    general = agent.name
    root = Path(results_dir) / GROUPS_DIR
    rows: list[dict[str, Any]] = []
    reused: list[int] = []
    stages = _Stages("generalization", "group", len(groups), root, steps, echo)
    if echo:
        say(f"generalization: {len(groups)} group(s), {steps} training steps per specialised agent; each finished "
            f"group is kept in {root}")
    try:
        for g in groups:
            j, m, t = SL_GROUPS[g]
            size = f"{j}x{m}x{t}"
            held = [f"sl{g}9"] if quick else [f"sl{g}{k}" for k in range(5, 10)]
            stages.start(f"group {g}", f"group {g} ({size})")
            stages.note(f"general model {general} on {len(held)} instance(s)")
            for inst in expand_instances(held, fleet):
                agent.forget()  # planned from scratch and timed with its plan search, whatever ran before
                t0 = time.perf_counter()
                sched = _model_run(general_spec, agent, inst, False)
                rows.append({"group": g, "size": size, "agent": f"general ({general})", "instance": inst.name,
                             "makespan": sched.makespan, "valid": _checked(inst, sched),
                             "wall_time": round(time.perf_counter() - t0, 3), "train_steps": None})
            train_spec = [f"gen:{j}x{m}x{t}*{2 if quick else 4}@{100 + g}"]
            select = [f"gen:{j}x{m}x{t}*1@{120 + g}"]  # model selection on generated shops, never on sl
            key = _group_key(g, train_spec, select, held, steps, seed, fleet, decisions)
            folder = _kept_folder(root, f"g{g}", key)
            stages.model = folder / "model"
            kept, was_kept = _kept_or_made(folder, key, "group.json", functools.partial(
                _specialist_rows, folder, key, size, stages.note, echo))
            if was_kept:
                stages.note(f"specialised agent and its {len(kept)} row(s) reused from {folder}")
                reused.append(g)
            rows.extend(kept)
            stages.finish(str(g))
    except KeyboardInterrupt:  # (only "fms: interrupted" was said, and every group's work was lost)
        stages.interrupted()
        raise
    summary = {str(g): {a: _mean([r["makespan"] for r in rows if r["group"] == g and r["agent"] == a])
                        for a in (f"general ({general})", "specialized")} for g in groups}
    meta = {"experiment": "generalization", "quick": quick, "seed": seed, "steps": steps, "groups": groups,
            "general_model": general, "no_tools": no_tools, "decisions": decisions, "kept_in": str(root),
            "reused_groups": reused, "summary": summary}

    def draw(path: Path) -> None:
        fig, ax = _figure(max(5.0, 1.3 * len(groups) + 2), 4.5)
        a = ax[0][0]
        x = np.arange(len(groups))
        for i, (agent_name, c) in enumerate(((f"general ({general})", "tab:blue"), ("specialized", "tab:orange"))):
            a.bar(x + (i - 0.5) * 0.38, [summary[str(g)][agent_name] for g in groups], width=0.38, color=c,
                  label=agent_name)
        a.set_xticks(x)
        a.set_xticklabels([f"{g}: {'x'.join(map(str, SL_GROUPS[g]))}" for g in groups], rotation=30)
        a.set_xlabel("size group (jobs x machines x tools)")
        a.set_ylabel("mean makespan (held-out)")
        a.set_title(f"general vs specialized agents ({steps} training steps per group)")
        a.legend()
        fig.tight_layout()
        fig.savefig(path)

    paths = _write("generalization", results_dir, GENERALIZATION_COLUMNS, rows, meta, draw)
    if echo:
        print(f"| group | general ({general}) | specialized |\n|---|---|---|")
        for g in groups:
            s = summary[str(g)]
            print(f"| {g} ({'x'.join(map(str, SL_GROUPS[g]))}) | {s[f'general ({general})']} | {s['specialized']} |")
        print(f"\nwritten: {', '.join(str(p) for p in paths.values())}")
    return dict(meta, rows=rows)


# ---------------------------------------------------------------------- dynamic
def partition_jobs(n_jobs: int, parts: int = 10) -> list[list[int]]:
    """Job j goes to partition ``j*parts//n_jobs`` (contiguous blocks; empty ones when n_jobs < parts)."""
    for name, v in (("n_jobs", n_jobs), ("parts", parts)):  # parts=0 was an IndexError
        if not isinstance(v, numbers.Integral) or isinstance(v, bool) or v < 1:
            raise ValueError(f"{name} must be an integer >= 1, got {v!r}")
    out: list[list[int]] = [[] for _ in range(parts)]
    for j in range(n_jobs):
        out[j * parts // n_jobs].append(j)
    return out


def _sub_instance(inst: Instance, jobs: Sequence[int], label: str) -> Instance:
    return dataclasses.replace(inst, name=f"{inst.name}{label}", jobs=tuple(inst.jobs[j] for j in jobs))


def run_arrivals(agent: Any, inst: Instance, groups: Sequence[Sequence[int]], arrival: Sequence[float],
                 on_arrival: Callable[[Shop, int, bool, float], None] | None = None) -> tuple[Shop, float]:
    """``agent`` runs one live shop (its net: ``agent.decisions``) to the end while job partitions arrive:
    partition p (``groups[p]``, jobs of ``inst``) is added with :meth:`~fms_sim.shop.Shop.add_jobs` at the first
    decision moment at or after ``arrival[p]``, or at the last decision before the shop would run dry (early).
    ``on_arrival(shop, p, early, decision_seconds_so_far)`` is called after each partition enters (partition 0 is
    the shop's start). Returns the finished shop and the agent's decision time in seconds."""
    from fms_sim.full_shop import make_shop

    shop = make_shop(_sub_instance(inst, groups[0], "-dyn"), agent.decisions)
    decide = 0.0
    nxt = 1
    if on_arrival is not None:
        on_arrival(shop, 0, False, decide)
    while True:
        while nxt < len(groups) and shop.now >= arrival[nxt]:
            shop.add_jobs([inst.jobs[j] for j in groups[nxt]])
            if on_arrival is not None:
                on_arrival(shop, nxt, False, decide)
            nxt += 1
        if shop.done:
            break
        t0 = time.perf_counter()
        a = agent.act(shop)
        decide += time.perf_counter() - t0
        if nxt < len(groups) and shop.instance.n_operations - sum(shop.job_started_ops) <= 2:
            with shop.trial():
                shop.act(a)
                runs_dry = shop.done
            if runs_dry:  # the shop would run dry before the next arrival: the partition enters now (early)
                shop.add_jobs([inst.jobs[j] for j in groups[nxt]])
                if on_arrival is not None:
                    on_arrival(shop, nxt, True, decide)
                nxt += 1
                continue  # decide again with the new jobs in view
        shop.act(a)
    return shop, decide


def run_dynamic(quick: bool = False, results_dir: str | Path = "results", seed: int = 0,
                instance: str | None = None, model: str | None = None, sos_time: float | None = None,
                parts: int = 10, echo: bool = True) -> dict[str, Any]:
    """Partitions arriving over time: RL continues on one live shop, SOS re-solves (see the module docstring).
    A full-net ``model`` (``full``) runs on the full net."""
    from fms_sim.formats import load_instance
    from fms_sim.full_shop import make_shop

    from .rl.lookahead import finish, run_agent
    from .rl.models import default_model_name, load_agent
    from .sos import solve_sos

    inst = load_instance(instance or ("sl00" if quick else "sl30"))
    sos_time = float(sos_time) if sos_time is not None else (0.2 if quick else 5.0)
    if sos_time <= 0:
        raise ValueError("--sos-time must be positive")
    if parts < 2:
        raise ValueError("need at least 2 partitions")
    # with fewer jobs than partitions some are empty: the others keep their index, so partition p still arrives
    # at p * delta (renumbered, they arrived earlier than the lower bound's share says)
    partitions = partition_jobs(inst.n_jobs, parts)
    slots = [p for p, g in enumerate(partitions) if g]
    groups = [partitions[p] for p in slots]
    lb = lower_bound(inst)
    delta = lb / parts
    arrival = [round(p * delta, 2) for p in slots]
    agent = load_agent(model or default_model_name(inst))
    if not agent.fits(inst):
        raise ValueError(agent.misfit(inst))

    rows: list[dict[str, Any]] = []

    def arrive(shop: Shop, p: int, early: bool, decide: float) -> None:
        """Record partition p (already in the shop): project the RL makespan, re-solve with SOS."""
        t0 = time.perf_counter()
        proj = finish(shop, agent.act) if not shop.done else shop.makespan
        proj_t = time.perf_counter() - t0
        so_far = [j for q in groups[:p + 1] for j in q]
        sub = _sub_instance(inst, so_far, f"-p{p}")
        t0 = time.perf_counter()
        s = solve_sos(sub, time_limit=sos_time, seed=seed)
        sos_t = time.perf_counter() - t0
        prev = rows[-1]["sos_time_cum"] if rows else 0.0
        rows.append({"partition": slots[p], "arrival": arrival[p], "entered_at": shop.now, "early": early,
                     "jobs_so_far": len(so_far), "rl_makespan": proj, "rl_time_cum": round(decide, 4),
                     "rl_projection_time": round(proj_t, 4), "sos_makespan": s.makespan,
                     "sos_time_cum": round(prev + sos_t, 3), "sos_valid": _checked(sub, s)})

    shop, decide = run_arrivals(agent, inst, groups, arrival, arrive)
    final = shop.schedule()
    _checked(shop.instance, final)
    static_ms = _valid_makespan(inst, run_agent(make_shop(inst, agent.decisions), agent.act))  # all jobs at 0
    last = rows[-1]
    summary = {"rl_final_makespan": final.makespan, "rl_decision_time": round(decide, 4),
               "rl_static_makespan": static_ms, "sos_final_makespan": last["sos_makespan"],
               "sos_total_time": last["sos_time_cum"], "early_partitions": sum(bool(r["early"]) for r in rows)}
    meta = {"experiment": "dynamic", "quick": quick, "seed": seed, "instance": inst.name, "model": agent.name,
            "decisions": agent.decisions,
            "partitions": len(groups), "lower_bound": lb, "delta": round(delta, 2), "sos_time_limit": sos_time,
            "sos_release": "all arrived jobs released at 0 (optimistic for SOS)", "summary": summary}

    def draw(path: Path) -> None:
        fig, ax = _figure(11, 4.5, ncols=2)
        a0, a1 = ax[0]
        x = [r["partition"] for r in rows]
        a0.plot(x, [r["rl_makespan"] for r in rows], marker="o", label=f"RL ({agent.name}), continuing")
        a0.plot(x, [r["sos_makespan"] for r in rows], marker="s", label="SOS re-solve (released at 0)")
        a0.set_xlabel("partitions arrived (index)")
        a0.set_ylabel("makespan of the jobs so far")
        a0.set_title(f"{inst.name}: {len(groups)} partitions, Δ = {delta:.0f}")
        a0.legend()
        a1.plot(x, [max(1e-4, r["rl_time_cum"]) for r in rows], marker="o", label="RL decisions")
        a1.plot(x, [max(1e-4, r["sos_time_cum"]) for r in rows], marker="s", label="SOS searches")
        a1.set_yscale("log")
        a1.set_xlabel("partitions arrived (index)")
        a1.set_ylabel("cumulative computation time [s]")
        a1.legend()
        fig.tight_layout()
        fig.savefig(path)

    paths = _write("dynamic", results_dir, DYNAMIC_COLUMNS, rows, meta, draw)
    if echo:
        print("| partition | arrival | entered | jobs | RL makespan | RL time [s] | SOS makespan | SOS time [s] |")
        print("|---|---|---|---|---|---|---|---|")
        for r in rows:
            print(f"| {r['partition']} | {r['arrival']} | {r['entered_at']}{' (early)' if r['early'] else ''} | "
                  f"{r['jobs_so_far']} | {r['rl_makespan']} | {r['rl_time_cum']} | {r['sos_makespan']} | "
                  f"{r['sos_time_cum']} |")
        print(f"\nRL static (all jobs at 0): {static_ms}; written: {', '.join(str(p) for p in paths.values())}")
    return dict(meta, rows=rows)


# ---------------------------------------------------------------------- disruptions
def _timed_run(inst: Instance, scenario: Any, plan: Schedule | None, rule: Any) -> tuple[Schedule, int, float]:
    """Run a plan (by replay), a full-net rule (by name) or a policy (``shop -> action``) under ``scenario``;
    (schedule, decisions, seconds)."""
    from fms_sim.full_shop import FullShop
    from fms_sim.replay import PlanPolicy, execute

    from .full_rules import parse_full_rule

    t0 = time.perf_counter()
    shop = FullShop(inst, scenario=scenario)
    n = 0
    if plan is not None:
        n = execute(shop, PlanPolicy(inst, plan))
    else:
        choose = rule if callable(rule) else parse_full_rule(rule or "FIFO")
        while not shop.done:
            shop.act(choose(shop))
            n += 1
    return shop.schedule(), n, time.perf_counter() - t0


def run_disruptions(quick: bool = False, results_dir: str | Path = "results", seed: int = 0,
                    seeds: int | None = None, cpsat_time: float | None = None, echo: bool = True,
                    replan_budget: float | None = None,
                    lookahead_max_ops: int = DISRUPTION_LOOKAHEAD_MAX_OPS,
                    instances: Sequence[str] | None = None, model: str | None = None) -> dict[str, Any]:
    """Plans and rules in disrupted shops: breakdowns (2 per run, in the first half of the nominal plan, 5-15 %
    of it long) and noise 0 / 10 / 20 % on every duration, several seeds (issue 18 §5).

    Methods: ``plan:cpsat`` — a CP-SAT plan of the nominal instance (``cpsat_time`` s) executed as it is (orders
    kept, times shift); ``plan:cpsat+replan`` — the same plan re-planned within ``replan_budget`` s (default 1;
    quick 0.2) on breakdowns and lateness (:mod:`fms_dispatch.replan`; the simulated shop waits for it, so its
    latency column includes the re-plans), each re-plan also weighing the best rule's continuation when that
    rule is a full-net rule; ``best-rule`` — the best full-net rule or list schedule *on the nominal instance*, then
    run in the disrupted shop (a list schedule is a plan: executed as one); ``ppo`` — a full-net model (``model``;
    default the shipped :data:`DISRUPTION_MODEL`), deciding in the disrupted shop as it goes; ``ppo+lookahead`` — the
    same with the verified lookahead (fast mode), whose twins are nominal copies of the shop
    (:func:`~fms_dispatch.rl.lookahead.nominal_twin`: what a dispatcher can know), on shops of at most
    ``lookahead_max_ops`` operations (the others are listed in ``not_measured``). Instances: sl{g}0 for
    groups 0-4 in both modes and EX12..EX102 (quick: EX12 and ra01, noise 0 / 10 %, one seed); ``instances``
    (names among those) runs only these. ``default`` — the shipped default model
    (:func:`~fms_dispatch.rl.models.default_model_name`: a guided model acting out its searched plan), deciding in the
    disrupted shop and re-planning its guide at breakdowns and delays (:class:`~fms_dispatch.rl.agent.GuideReplanner`):
    what ``fms solve --solver ppo`` does in a disrupted shop."""
    from fms_sim.disruptions import Scenario
    from fms_sim.formats import load_instance

    from .replan import solve_with_replanning
    from .rl.models import ModelNotFoundError, default_model_name, load_agent
    from .solvers import solve

    from .rl.lookahead import nominal_twin, run_with_lookahead

    missing: dict[str, str] = {}
    methods = DISRUPTION_METHODS
    try:
        agent = load_agent(model or DISRUPTION_MODEL)  # must decide through the full net, which runs the disruptions
    except (ModelNotFoundError, ImportError) as exc:
        if model is not None:  # a model asked for by name is bad input; only the shipped one may be absent
            raise
        agent, methods = None, tuple(m for m in DISRUPTION_METHODS if not m.startswith("ppo"))
        missing["ppo"] = missing["ppo+lookahead"] = (f"model {DISRUPTION_MODEL!r} not available: "
                                                     f"{str(exc).splitlines()[0]}")
    if agent is not None and agent.decisions != "full":
        raise ValueError(f"model {agent.name} decides through the paper's net, which runs no disruptions; name a "
                         "full-net model (e.g. full, guided-dagger)")
    if agent is not None and agent.guide is not None:
        agent.use_guide_effort(None)  # a cached agent: a guided model searches its plans as fms solve does
    skipped_la: list[str] = []

    def default_run(inst: Instance, sc: Any) -> tuple[Schedule, int, float]:
        from .rl.agent import GuideReplanner

        model = load_agent(default_model_name(inst))
        model.use_guide_effort(None)  # a cached agent: the default plan search for every run
        choose = GuideReplanner(model) if sc is not None and model.guide is not None else model.act
        return _timed_run(inst, sc, None, choose)

    def lookahead_run(inst: Instance, sc: Any) -> tuple[Schedule, int, float]:
        from fms_sim.full_shop import FullShop

        t0 = time.perf_counter()
        decisions: list[Any] = []
        sched = run_with_lookahead(FullShop(inst, scenario=sc), agent.act, retry=False, twin=nominal_twin,
                                   decisions=decisions)
        return sched, len(decisions), time.perf_counter() - t0

    if lookahead_max_ops < 0:
        raise ValueError(f"--lookahead-max-ops must be >= 0, got {lookahead_max_ops}")
    cpsat_time = float(cpsat_time) if cpsat_time is not None else (1.0 if quick else 10.0)
    budget = float(replan_budget) if replan_budget is not None else (0.2 if quick else 1.0)
    n_seeds = int(seeds) if seeds else (1 if quick else 3)
    noises = (0.0, 0.1) if quick else (0.0, 0.1, 0.2)
    if quick:
        insts = [("EX12", "agvs"), ("ra01", "tools")]
    else:
        insts = ([(f"sl{g}0", mode) for g in range(5) for mode in ("tools", "agvs")]
                 + [(f"EX{s}2", "agvs") for s in range(1, 11)])
    if instances:
        unknown = sorted(set(instances) - {n for n, _ in insts})
        if unknown:
            raise ValueError(f"--instances: {', '.join(unknown)} not in this experiment (choose from "
                             f"{', '.join(dict.fromkeys(n for n, _ in insts))})")
        insts = [(n, m) for n, m in insts if n in set(instances)]
    try:  # the default model is the same for every shop (models.default_model_name)
        load_agent(default_model_name(load_instance(insts[0][0])))
    except (ModelNotFoundError, ImportError) as exc:
        methods = tuple(m for m in methods if m != "default")
        missing["default"] = f"the default model is not available: {str(exc).splitlines()[0]}"
    rows: list[dict[str, Any]] = []
    for i, (name, mode) in enumerate(insts):
        inst = load_instance(name)
        if mode == "agvs" and inst.has_tools:
            inst = inst.without_tools()
        if echo:
            say(f"[{i + 1}/{len(insts)}] {inst.name} ({mode}): plans, then {len(noises)} noise levels x "
                f"{n_seeds} seeds x {len(methods)} methods")
        t0 = time.perf_counter()
        plan = solve(inst, "cpsat", time_limit=cpsat_time)
        plan_time = time.perf_counter() - t0
        t0 = time.perf_counter()
        best = solve(inst, "rules")
        rule_time = time.perf_counter() - t0
        winner = best.meta["rule"]
        rule_plan = solve(inst, winner) if winner.startswith("list") else None
        # the nominal makespans divide every disrupted one (ratio): validated as the disrupted runs are
        nominal = {"plan:cpsat": _valid_makespan(inst, plan), "best-rule": _valid_makespan(inst, best)}
        nominal["plan:cpsat+replan"] = nominal["plan:cpsat"]
        look = agent is not None and sum(len(ops) for ops in inst.jobs) <= lookahead_max_ops
        if agent is not None:
            nominal["ppo"] = _valid_makespan(inst, _timed_run(inst, None, None, agent.act)[0])
            if look:
                nominal["ppo+lookahead"] = _valid_makespan(inst, lookahead_run(inst, None)[0])
            else:
                skipped_la.append(f"{inst.name} ({mode})")
        if "default" in methods:
            nominal["default"] = _valid_makespan(inst, default_run(inst, None)[0])
        for noise in noises:
            for k in range(n_seeds):
                sc = Scenario.draw(inst, noise=noise, breakdowns=2, horizon=max(1, plan.makespan // 2),
                                   duration=(max(1, plan.makespan // 20), max(1, plan.makespan // 7)),
                                   seed=seed * 1000 + k)
                for method in methods:
                    if method == "ppo+lookahead" and not look:
                        continue
                    if method == "plan:cpsat":
                        sched, n, secs = _timed_run(inst, sc, plan, None)
                    elif method == "plan:cpsat+replan":
                        t1 = time.perf_counter()
                        sched = solve_with_replanning(inst, plan, budget=budget, scenario=sc, seed=k,
                                                      rules=() if rule_plan else (winner,))
                        n, secs = sched.meta["answers"], time.perf_counter() - t1
                    elif method == "ppo":
                        sched, n, secs = _timed_run(inst, sc, None, agent.act)
                    elif method == "ppo+lookahead":
                        sched, n, secs = lookahead_run(inst, sc)
                    elif method == "default":
                        sched, n, secs = default_run(inst, sc)
                    else:
                        sched, n, secs = _timed_run(inst, sc, rule_plan, None if rule_plan else winner)
                    _checked(inst, sched)
                    rows.append({"instance": inst.name, "mode": mode, "noise": noise, "seed": k,
                                 "breakdowns": len(sc.breakdowns), "method": method if method != "best-rule"
                                 else f"best-rule ({winner})", "makespan": sched.makespan,
                                 "nominal_makespan": nominal[method],
                                 "ratio": round(sched.makespan / nominal[method], 4), "decisions": n,
                                 "latency_ms": round(1000 * secs / max(1, n), 4),
                                 # seconds spent before the run: the CP-SAT plan, or choosing the best rule; a
                                 # policy plans (if at all) inside its run, in its latency
                                 "plan_time": round(plan_time if method.startswith("plan:") else rule_time
                                                    if method == "best-rule" else 0.0, 3)})
    if skipped_la:
        missing["ppo+lookahead"] = (f"not run on shops over {lookahead_max_ops} operations (--lookahead-max-ops): "
                                    + ", ".join(skipped_la))
    summary: dict[str, Any] = {}
    for noise in noises:
        for method in methods:
            sel = [r for r in rows if r["noise"] == noise and r["method"].split(" ")[0] == method]
            summary[f"{method} noise {noise:g}"] = {"mean_makespan": _mean([r["makespan"] for r in sel]),
                                                    "mean_ratio_to_nominal": _mean([r["ratio"] for r in sel]),
                                                    "runs": len(sel)}
    wins, rwins, pwins, lwins, dwins = {}, {}, {}, {}, {}
    for noise in noises:
        pairs = {}
        for r in rows:
            if r["noise"] == noise:
                pairs.setdefault((r["instance"], r["mode"], r["seed"]), {})[r["method"].split(" ")[0]] = r["makespan"]
        wins[f"noise {noise:g}"] = sum(1 for v in pairs.values() if v["plan:cpsat"] < v["best-rule"]), len(pairs)
        rwins[f"noise {noise:g}"] = (sum(1 for v in pairs.values() if v["plan:cpsat+replan"] < v["best-rule"]),
                                     sum(1 for v in pairs.values() if v["plan:cpsat+replan"] < v["plan:cpsat"]),
                                     len(pairs))
        if "ppo" in methods:
            pwins[f"noise {noise:g}"] = (sum(1 for v in pairs.values() if v["plan:cpsat+replan"] < v["ppo"]),
                                         sum(1 for v in pairs.values() if v["ppo"] < v["best-rule"]), len(pairs))
            la = [v for v in pairs.values() if "ppo+lookahead" in v]
            lwins[f"noise {noise:g}"] = (sum(1 for v in la if v["plan:cpsat+replan"] < v["ppo+lookahead"]),
                                         sum(1 for v in la if v["ppo+lookahead"] < v["ppo"]), len(la))
        if "default" in methods:
            dwins[f"noise {noise:g}"] = (sum(1 for v in pairs.values() if v["plan:cpsat+replan"] < v["default"]),
                                         sum(1 for v in pairs.values() if v["default"] < v["plan:cpsat+replan"]),
                                         sum(1 for v in pairs.values() if v["default"] < v["best-rule"]), len(pairs))
    meta = {"experiment": "disruptions", "quick": quick, "seed": seed, "seeds": n_seeds, "noises": list(noises),
            "cpsat_time": cpsat_time, "instances": [f"{n} ({m})" for n, m in insts],
            "ppo_model": agent.name if agent is not None else None,
            "not_measured": missing, "summary": summary,
            "plan_beats_best_rule": {k: f"{a}/{b}" for k, (a, b) in wins.items()},
            "replan_beats_best_rule": {k: f"{a}/{c}" for k, (a, b, c) in rwins.items()},
            "replan_beats_plan": {k: f"{b}/{c}" for k, (a, b, c) in rwins.items()}, "replan_budget": budget,
            "replan_beats_ppo": {k: f"{a}/{c}" for k, (a, b, c) in pwins.items()},
            "ppo_beats_best_rule": {k: f"{b}/{c}" for k, (a, b, c) in pwins.items()},
            "replan_beats_ppo_lookahead": {k: f"{a}/{c}" for k, (a, b, c) in lwins.items()},
            "ppo_lookahead_beats_ppo": {k: f"{b}/{c}" for k, (a, b, c) in lwins.items()},
            "replan_beats_default": {k: f"{a}/{d}" for k, (a, b, c, d) in dwins.items()},
            "default_beats_replan": {k: f"{b}/{d}" for k, (a, b, c, d) in dwins.items()},
            "default_beats_best_rule": {k: f"{c}/{d}" for k, (a, b, c, d) in dwins.items()},
            "lookahead_max_ops": lookahead_max_ops}

    def draw(path: Path) -> None:
        fig, ax = _figure(7, 4.5)
        a = ax[0][0]
        for method in methods:
            a.plot([f"{n:g}" for n in noises],
                   [summary[f"{method} noise {n:g}"]["mean_ratio_to_nominal"] for n in noises], marker="o",
                   label=method)
        a.set_xlabel("noise spread (with 2 breakdowns per run)")
        a.set_ylabel("realised / nominal makespan (mean)")
        a.set_title("Plans, re-planning and rules in disrupted shops")
        a.legend()
        fig.tight_layout()
        fig.savefig(path)

    paths = _write("disruptions", results_dir, DISRUPTION_COLUMNS, rows, meta, draw)
    if echo:
        print("| method | noise | runs | mean makespan | realised / nominal |")
        print("|---|---|---|---|---|")
        for key, v in summary.items():
            method, _, noise = key.partition(" noise ")
            print(f"| {method} | {noise} | {v['runs']} | {v['mean_makespan']} | {v['mean_ratio_to_nominal']} |")
        print("\nplan:cpsat beats the best rule: " + ", ".join(f"{k}: {v}" for k, v in meta["plan_beats_best_rule"]
                                                               .items()))
        print("plan:cpsat+replan beats the best rule: " + ", ".join(
            f"{k}: {v}" for k, v in meta["replan_beats_best_rule"].items()) + "; beats plan:cpsat without re-planning: "
            + ", ".join(f"{k}: {v}" for k, v in meta["replan_beats_plan"].items()))
        if pwins:
            print("plan:cpsat+replan beats PPO: " + ", ".join(f"{k}: {v}" for k, v in meta["replan_beats_ppo"].items())
                  + "; PPO beats the best rule: " + ", ".join(f"{k}: {v}" for k, v in meta["ppo_beats_best_rule"]
                                                             .items()))
        if lwins:
            print("plan:cpsat+replan beats PPO + lookahead: " + ", ".join(
                f"{k}: {v}" for k, v in meta["replan_beats_ppo_lookahead"].items()) + "; PPO + lookahead beats PPO: "
                + ", ".join(f"{k}: {v}" for k, v in meta["ppo_lookahead_beats_ppo"].items()))
        if dwins:
            print("plan:cpsat+replan beats the default model: " + ", ".join(
                f"{k}: {v}" for k, v in meta["replan_beats_default"].items()) + "; the default model beats it: "
                + ", ".join(f"{k}: {v}" for k, v in meta["default_beats_replan"].items())
                + "; the default model beats the best rule: "
                + ", ".join(f"{k}: {v}" for k, v in meta["default_beats_best_rule"].items()))
        if missing:
            print("not measured: " + "; ".join(f"{k} ({why})" for k, why in missing.items()))
        print(f"written: {', '.join(str(p) for p in paths.values())}")
    return dict(meta, rows=rows)


# ---------------------------------------------------------------------- CLI
def add_experiment_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``fms experiment ablation|generalization|dynamic`` to the CLI's subparsers."""
    s = subparsers.add_parser("experiment", help="studies: ablation, generalization, dynamic arrivals, disruptions")
    sub = s.add_subparsers(dest="experiment", required=True)

    def common(p: argparse.ArgumentParser) -> None:
        p.add_argument("--quick", action="store_true", help="tiny budgets (seconds; for tests)")
        p.add_argument("--results-dir", default="results", help="output folder (default results)")
        p.add_argument("--seed", type=int, default=0, help="seed (>= 0) of the runs that train or draw (default 0)")

    p = sub.add_parser("ablation", help="reward shaping, lookahead and action masking on/off",
                       description="Reward shaping (two agents trained), the lookahead (a model with and without "
                                   "it) and action masking (two training curves) on and off. Resumable: each "
                                   f"finished trained variant is kept in RESULTS_DIR/{ABLATION_DIR}/ (its rows, "
                                   "and its agent, per options); after an interrupt the same command reuses them, "
                                   "continues the interrupted agent's training and measures the lookahead again "
                                   "(other --steps, --seed, --quick or --decisions reuse nothing). Progress on "
                                   "stderr.")
    common(p)
    p.add_argument("--steps", type=int, help="training steps per agent (default 20000; quick 128); kept variants "
                                             "of other steps are not reused")
    p.add_argument("--studies", nargs="+", choices=ABLATION_STUDIES, help="run only these (default all)")
    p.add_argument("--decisions", choices=("paper", "full"), default="paper",
                   help="the net the agents decide through (default paper; full: the default model in the "
                        "lookahead study, full-net training in the others)")
    p.add_argument("--model", help="the lookahead study's model, of the --decisions net (default: bu on the paper's "
                                   "net, the shipped default model on the full net)")
    p.set_defaults(fn=_cmd)
    p = sub.add_parser("generalization", help="general vs specialized agents per size group",
                       description="The general shipped model against an agent trained per size group of the large "
                                   f"benchmark. Resumable: each finished group is kept in RESULTS_DIR/{GROUPS_DIR}/ "
                                   "(its agent and rows, per options); after an interrupt the same command reuses "
                                   "them and continues the interrupted group's training (other --steps, --seed, "
                                   "--quick, --no-tools or --decisions reuse nothing). Progress on stderr.")
    common(p)
    p.add_argument("--steps", type=int, help="training steps per specialized agent (default 20000; quick 256); "
                                             "kept groups of other steps are not reused")
    p.add_argument("--groups", type=int, nargs="+", help="size groups 0-7 (default all; quick 0)")
    p.add_argument("--no-tools", action="store_true",
                   help="instances without tools (paper net: general model large-agv)")
    p.add_argument("--decisions", choices=("paper", "full"), default="paper",
                   help="the net (default paper; full: the default model as the general one, specialists trained "
                        "on the full net)")
    p.add_argument("--model", help="the general model, of the --decisions net (default: large or large-agv on the "
                                   "paper's net, the shipped default model on the full net)")
    p.set_defaults(fn=_cmd)
    p = sub.add_parser("dynamic", help="jobs arriving in 10 partitions: RL continues, SOS re-solves")
    common(p)
    p.add_argument("--instance", help="instance (default sl30; quick sl00)")
    p.add_argument("--model", help="RL model (default: the shipped model for the instance)")
    p.add_argument("--sos-time", type=float, help="SOS time limit per re-solve in s (default 5; quick 0.2)")
    p.set_defaults(fn=_cmd)
    p = sub.add_parser("disruptions", help="plans, re-planning and rules under breakdowns and noise")
    common(p)
    p.add_argument("--seeds", type=int, help="disruption seeds per instance and noise level (default 3; quick 1)")
    p.add_argument("--cpsat-time", type=float, help="CP-SAT plan time limit in s (default 10; quick 1)")
    p.add_argument("--replan-budget", type=float, help="seconds per re-plan (default 1; quick 0.2)")
    p.add_argument("--instances", nargs="+", help="only these of the experiment's instances (e.g. sl00 EX12)")
    p.add_argument("--model", help=f"the ppo method's model, a full-net one (default {DISRUPTION_MODEL})")
    p.add_argument("--lookahead-max-ops", type=int, default=DISRUPTION_LOOKAHEAD_MAX_OPS,
                   help=f"PPO + lookahead only on shops with at most this many operations "
                        f"(default {DISRUPTION_LOOKAHEAD_MAX_OPS})")
    p.set_defaults(fn=_cmd)
    return s


def _cmd(a: argparse.Namespace) -> int:
    from fms_sim.files import file_above, folder_problem

    if not a.results_dir.strip():  # Path("") is the current folder
        raise ValueError("--results-dir names no folder (an empty name); give one, e.g. --results-dir .")
    out = Path(a.results_dir)
    blocker = out if out.exists() and not out.is_dir() else file_above(out)
    if blocker is not None:  # found before the work, not after hours of it
        raise ValueError(f"--results-dir {a.results_dir}: {blocker} is a file; name a folder")
    problem = folder_problem(out)  # (one that cannot be made, under /proc, was found after the work)
    if problem is not None:
        raise ValueError(f"--results-dir {a.results_dir}: {problem}")
    for flag in ("steps", "seeds", "cpsat_time", "replan_budget", "sos_time"):  # 0 would silently mean the default
        v = getattr(a, flag, None)
        if v is not None and not 0 < v < math.inf:  # (inf: a search that never ends)
            raise ValueError(f"--{flag.replace('_', '-')} must be positive and finite, got {v}")
    if a.seed < 0:  # (training refused it only after the studies before it had run; sos took its absolute value)
        raise ValueError(f"--seed must be an integer >= 0, got {a.seed}")
    if a.experiment == "ablation" and a.model is not None and a.studies and "lookahead" not in a.studies:
        raise ValueError("--model is the lookahead study's model; these studies train their own agents (add "
                         "--studies lookahead, or leave --model out)")
    if a.experiment == "ablation":
        run_ablation(a.quick, a.results_dir, a.seed, a.steps, a.studies, decisions=a.decisions, model=a.model)
    elif a.experiment == "generalization":
        run_generalization(a.quick, a.results_dir, a.seed, a.steps, a.groups, a.no_tools, decisions=a.decisions,
                           model=a.model)
    elif a.experiment == "disruptions":
        run_disruptions(a.quick, a.results_dir, a.seed, a.seeds, a.cpsat_time, replan_budget=a.replan_budget,
                        lookahead_max_ops=a.lookahead_max_ops, instances=a.instances, model=a.model)
    else:
        run_dynamic(a.quick, a.results_dir, a.seed, a.instance, a.model, a.sos_time)
    return 0
