"""Training: MaskablePPO on :class:`~fms_dispatch.rl.envs.FastShopEnv`, one model folder per run.

``fms train INSTANCES... --steps N --reward {idle,makespan,shaped} --seed S --out models/NAME`` trains on a set
of instances (one drawn at random per episode), evaluates the deterministic policy on held-out instances
every ``eval_freq`` steps (``MaskableEvalCallback``, best weights to ``best_model.zip``), saves the latest
weights to ``model.zip`` periodically and at the end (``--resume`` continues from there; the step count goes
on), logs to TensorBoard (``runs/NAME`` by default) and shows PPO's progress (a bar on a terminal,
else about 20 lines on standard error). Several environments run in
parallel (``SubprocVecEnv``) when ``n_envs > 1`` and ``vec_env`` is ``subproc``; every process uses one torch
thread. Hyper-parameters come from ``--config FILE`` (JSON) and the command line, and the merged config is
written to ``config.json`` next to the model. At the end each saved ``X.zip`` gets its numpy actor export
``X.actor.npz`` (:func:`fms_dispatch.rl.agent.export_actor`), so solving with the model needs no torch.

Instance specs are parsed by :func:`fms_sim.shopsets.expand_specs` (its module docstring has the syntax):
built-in names or files (as ``fms solve`` takes them), shell patterns over built-in names (``'EX?2'``,
``'sl[0-2]?'``), generated sets ``gen:JxMxT*COUNT@SEED`` (Taillard-LCG instances of that size from seeds
derived from SEED, with the large benchmark's travel matrices and fleets: 10 AGVs, 5 transporters; ``/aNtN``
or ``/notools`` give another fleet) and ``genbu:L*COUNT@SEED`` (random job sets on Bilge–Ulusoy layout L).
Seeds >= 900000 are reserved for the held-out shops ``ho00``..``ho49``; benchmarks and held-out shops must
not be trained or selected on (:func:`fms_sim.shopsets.check_training_specs`): ``fms train`` refuses a config
that names one in ``train``, ``eval`` or a refine stage unless it sets ``allow_benchmarks`` (``--allow-benchmarks``,
for reproducing the paper's own setting; the flag is saved in ``config.json``).

``init`` (``--init MODEL``) starts from a trained model's weights instead of a warm start (PPO fine-tuning; they
are evaluated first and kept as ``warm_start.zip``, so PPO must beat them to replace ``best_model.zip``); with a
warm-start expert and ``warm_start.dagger`` rounds, those rounds run from the initial weights (no fresh clone). The
model's ``training_shops`` include the initial model's.
``guide_effort`` (a dict of :class:`~fms_dispatch.rl.guide.PlanEffort` fields; default the plain list schedule)
sets how a guided model's plans are searched in training and evaluation. ``disruptions`` (full net; e.g.
``{"noise": 0.2, "breakdowns": 1}``) trains in disrupted shops, a fresh scenario per episode, and evaluates each
evaluation shop in a fixed scenario (:mod:`fms_sim.env`); plan experts' DAgger rounds then label the policy's
states in disrupted runs (:func:`fms_dispatch.rl.plan_expert.plan_dagger_round`). ``baseline: "init"`` (with
``init``) makes every episode's return relative to the initial weights' run of the same episode
(:mod:`fms_dispatch.rl.relative`), so that the scenario's luck cancels and the initial weights score 0 in
evaluation.

``decisions`` chooses the net: ``paper`` (the paper's net; experts ``search``, ``search+lookahead``, ``rules``,
``rules+nearest``) or ``full`` (the full-decision net; plan experts ``plan:SOLVER[:SECONDS]``,
:mod:`fms_dispatch.rl.plan_expert`). ``guide`` (full net only; ``--guide list``) adds a list-schedule plan's
orders to the observation (the better of the earliest-start and earliest-completion list schedules,
:mod:`fms_dispatch.rl.guide`; :mod:`fms_dispatch.rl.envs`).
"""

from __future__ import annotations

import argparse
import difflib
import json
import math
import sys
import time
import warnings
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from fms_sim.files import loads, read_text, write_atomically
from fms_sim.instance import Instance

from ..progress import say as progress_line
from .models import CONFIG_FILE, METRICS_FILE

__all__ = ["train", "expand_instances", "DEFAULT_CONFIG", "check_config", "add_train_parser", "cmd_train",
           "evaluate_model"]

#: Defaults of every config key (a config file or the command line overrides them).
DEFAULT_CONFIG: dict[str, Any] = {
    "name": None,
    "train": [],
    "eval": [],
    "fleet": {"agvs": None, "tool_transporters": None, "no_tools": False},
    "padding": "auto",
    "decisions": "paper",
    "guide": None,
    "guide_effort": None,
    "disruptions": None,
    "init": None,
    "baseline": None,
    "allow_benchmarks": False,
    "reward": "shaped",
    "steps": 100_000,
    "seed": 0,
    "arch": "entity",
    "hidden": 64,
    "net_arch": [64, 64],
    "n_envs": 2,
    "vec_env": "subproc",
    "eval_freq": 10_000,
    "warm_start": {"expert": None, "instances": 100, "search_iters": 2000, "search_insert": 0.0,
                   "search_restarts": 1, "search_starts": 1, "workers": 1, "epochs": 300, "lr": 1e-3,
                   "dagger": 0, "dagger_epochs": 10, "refine": []},
    "save_freq": 10_000,
    "ppo": {"learning_rate": 3e-4, "n_steps": 512, "batch_size": 256, "n_epochs": 5, "gamma": 1.0,
            "gae_lambda": 0.95, "clip_range": 0.2, "ent_coef": 0.01, "vf_coef": 0.5, "max_grad_norm": 0.5},
}

def _saved_config(path: Path) -> dict[str, Any]:
    """A model's saved config, read as ``fms train --config`` reads one (a damaged file was a traceback that did not
    name it: JSONDecodeError, UnicodeDecodeError, or a TypeError for a file holding a list)."""
    try:
        saved = loads(read_text(path))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"cannot resume: {path} cannot be read ({exc})") from None
    if not isinstance(saved, dict):
        raise ValueError(f"cannot resume: {path} holds no JSON object of hyper-parameters")
    return saved


def _named_twice(shops: Sequence[Instance]) -> str | None:
    """A name two different shops of ``shops`` share (the same shop listed twice is no clash), else None."""
    seen: dict[str, Instance] = {}
    for inst in shops:
        other = seen.setdefault(inst.name, inst)
        if other is not inst and other != inst:
            return inst.name
    return None


def expand_instances(specs: Sequence[str], fleet: dict[str, Any] | None = None) -> list[Instance]:
    """Load instance specs (see the module docstring), applying the fleet overrides to each."""
    from fms_sim.shopsets import expand_specs

    return expand_specs(specs, dict(DEFAULT_CONFIG["fleet"], **(fleet or {})))


class _Cycle:
    """Instance sampler that walks a list in order (evaluation: every held-out instance once per round)."""

    def __init__(self, instances: Sequence[Instance]):
        self.instances = list(instances)
        self.i = -1

    def __call__(self, rng: np.random.Generator) -> Instance:
        self.i = (self.i + 1) % len(self.instances)
        return self.instances[self.i]


def _make_env(instances: Sequence[Instance] | _Cycle, padding: dict[str, int], reward: str, seed: int,
              decisions: str = "paper", guide: str | None = None, guide_effort: Any = None,
              disruptions: dict[str, Any] | None = None, reference: Path | None = None):
    def make():
        import torch
        from stable_baselines3.common.monitor import Monitor

        from .envs import FastShopEnv
        from .guide import PlanEffort

        torch.set_num_threads(1)
        import multiprocessing

        if multiprocessing.parent_process() is not None:  # a SubprocVecEnv worker: Ctrl-C in a terminal reaches
            import signal  # the whole group; the worker died of it and the main process's clean stop (weights,
            signal.signal(signal.SIGINT, signal.SIG_IGN)  # metrics, exports) ended in an EOFError traceback
        effort = guide_effort or PlanEffort()
        env = FastShopEnv(instances, reward=reward, invalid_action="raise", decisions=decisions, guide=guide,
                          guide_effort=effort, disruptions=disruptions, **padding)
        if reference is not None:  # returns relative to the reference weights' run of the same episode
            from .agent import Agent
            from .relative import RelativeReturn

            ref = Agent(reference, padding, decisions=decisions, guide=guide)
            if guide is not None:
                ref.use_guide_effort(effort)
            env = RelativeReturn(env, ref)
        env.reset(seed=seed)
        return Monitor(env)

    return make


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        if v is None:
            continue
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)
        else:
            out[k] = v
    return out


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


#: the largest number a float32 holds (torch's), rounded down
_F32_MAX = 3.4e38

#: What each config value must be: (test, words for the error); null always passes (it leaves the default). Keys
#: checked elsewhere (padding, guide_effort, disruptions, warm_start.refine, the names of rules, rewards and
#: experts) only need the right JSON type here.
_KINDS: dict[str, tuple[Callable[[Any], bool], str]] = {
    "str": (lambda v: isinstance(v, str), "a string"),
    "bool": (lambda v: isinstance(v, bool), "true or false"),
    "int": (_is_int, "an integer"),
    "int>=0": (lambda v: _is_int(v) and v >= 0, "an integer >= 0"),
    "int>=1": (lambda v: _is_int(v) and v >= 1, "an integer >= 1"),
    "num>=0": (lambda v: _is_num(v) and v >= 0, "a number >= 0"),
    "num>0": (lambda v: _is_num(v) and v > 0, "a number > 0"),
    # torch computes in float32: a larger value (1e308) overflowed in a traceback
    "f32>0": (lambda v: _is_num(v) and 0 < v <= _F32_MAX, f"a number > 0 and at most {_F32_MAX:g}"),
    "f32>=0": (lambda v: _is_num(v) and 0 <= v <= _F32_MAX, f"a number >= 0 and at most {_F32_MAX:g}"),
    "gamma": (lambda v: _is_num(v) and 0 < v <= 1, "a number in (0, 1]"),
    "specs": (lambda v: isinstance(v, list) and all(isinstance(x, str) for x in v), "a list of instance specs"),
    "layers": (lambda v: isinstance(v, list) and all(_is_int(x) and x >= 1 for x in v),
               "a list of layer widths (integers >= 1)"),
    "padding": (lambda v: isinstance(v, (str, dict)), "a profile name, auto or a dict of sizes"),
    "dict": (lambda v: isinstance(v, dict), "an object"),
    "list": (lambda v: isinstance(v, list), "a list"),
    "vec_env": (lambda v: v in ("subproc", "dummy"), "subproc or dummy"),
    # numpy and gymnasium take seeds from 0 to 2**32 - 1, and the training adds each env's and stage's number to it
    "seed": (lambda v: _is_int(v) and 0 <= v < 2**31, f"an integer from 0 to {2**31 - 1}"),
}
_CONFIG_KINDS: dict[str, Any] = {
    "name": "str", "train": "specs", "eval": "specs",
    "fleet": {"agvs": "int>=1", "tool_transporters": "int>=1", "no_tools": "bool"},
    "padding": "padding", "decisions": "str", "guide": "str", "guide_effort": "dict", "disruptions": "dict",
    "init": "str", "baseline": "str", "allow_benchmarks": "bool", "reward": "str", "steps": "int>=0",
    "seed": "seed", "arch": "str", "hidden": "int>=1", "net_arch": "layers", "n_envs": "int>=1",
    "vec_env": "vec_env", "eval_freq": "int>=1", "save_freq": "int>=1",
    "warm_start": {"expert": "str", "instances": "int>=1", "search_iters": "int>=0", "search_insert": "num>=0",
                   "search_restarts": "int>=1", "search_starts": "int>=1", "workers": "int>=1", "epochs": "int>=0",
                   "lr": "f32>0", "dagger": "int>=0", "dagger_epochs": "int>=1", "refine": "list"},
    "ppo": {"learning_rate": "f32>0", "n_steps": "int>=1", "batch_size": "int>=1", "n_epochs": "int>=1",
            "gamma": "gamma", "gae_lambda": "gamma", "clip_range": "f32>0", "ent_coef": "f32>=0", "vf_coef": "f32>=0",
            "max_grad_norm": "f32>0"},
}
assert set(_CONFIG_KINDS) == set(DEFAULT_CONFIG)


def check_config(config: Any, where: str = "") -> None:
    """Raise ValueError, naming the key, for a training config key that :data:`DEFAULT_CONFIG` does not have (a
    misspelt ``step`` would silently train the default 100,000 steps) or a value of the wrong kind (a string
    ``hidden`` failed deep inside torch); null leaves a key at its default, as on the command line."""
    kinds = _CONFIG_KINDS
    for part in [p for p in where.split(".") if p]:
        kinds = kinds[part]
    if not isinstance(config, dict):
        raise ValueError(f"config{' key ' + where if where else ''} must be an object, got {config!r}")
    for key, value in config.items():
        name = f"{where}.{key}" if where else key
        if key not in kinds:
            near = difflib.get_close_matches(key, list(kinds), n=1)
            raise ValueError(f"unknown config key {name!r}" + (f" (did you mean {near[0]!r}?)" if near else "")
                             + f"; the keys{' of ' + where if where else ''} are {', '.join(kinds)}")
        if value is None:
            continue
        kind = kinds[key]
        if isinstance(kind, dict):
            check_config(value, name)
            continue
        test, words = _KINDS[kind]
        if not test(value):
            raise ValueError(f"config: {name} must be {words}, got {json.dumps(value)[:80]}")


def evaluate_model(weights: str | Path, padding: dict[str, int], instances: Sequence[Instance],
                   lookahead: bool = False, decisions: str = "paper", guide: str | None = None,
                   guide_effort: Any = None, disruptions: dict[str, Any] | None = None) -> dict[str, int]:
    """Makespan per instance of the deterministic policy on the net ``decisions`` (schedules validated), a guided
    model planning with ``guide_effort`` (default: the solver's default search); with
    ``disruptions``, each instance in its fixed scenario (as the training's evaluation draws it)."""
    from fms_sim.env import check_disruptions, episode_scenario
    from fms_sim.full_shop import make_shop
    from fms_sim.validate import validate

    from .lookahead import run_agent
    from .agent import Agent

    agent = Agent(weights, padding, decisions=decisions, guide=guide)
    if guide is not None and guide_effort is not None:
        agent.use_guide_effort(guide_effort)
    fixed = check_disruptions(dict(disruptions, fixed=True) if disruptions else None, decisions)
    out = {}
    for inst in instances:
        scenario = episode_scenario(inst, fixed) if fixed else None
        s = run_agent(make_shop(inst, decisions, scenario), agent.act, lookahead=lookahead)
        problems = validate(inst, s, scenario)
        if problems:
            raise RuntimeError(f"invalid schedule for {inst.name}: {problems[0]}")
        out[inst.name] = s.makespan
    return out


def _resolve_init(init: str | Path) -> Path:
    """``init`` as a path that exists: a folder or ``.zip`` as given, else a shipped model by name (``guided``),
    and a shipped config's ``models/NAME`` from any working folder (the shipped models' folder, not the current
    one); raises ValueError if there is no such model."""
    path = Path(init)
    if path.exists():
        return path
    from .models import ModelNotFoundError, resolve_model

    for spec in (str(init), path.name) if path.parent.name == "models" else (str(init),):
        try:
            return resolve_model(spec).folder
        except (ModelNotFoundError, ValueError):
            continue
    raise ValueError(f"init: no weights at {init} (give a model folder, a .zip or a shipped model's name)")


def _init_weights(init: str | Path) -> Path:
    """The weights file of ``init``: a ``.zip``, or a model folder's ``best_model.zip`` (else its ``model.zip``);
    raises ValueError if there is none."""
    path = Path(init)
    if path.is_dir():
        path = path / "best_model.zip" if (path / "best_model.zip").is_file() else path / "model.zip"
    if not path.is_file():
        raise ValueError(f"init: no weights at {init}")
    return path


def _init_shops(init: str | Path) -> list[str]:
    """The training shops recorded in the metrics of ``init``'s model folder (the folder of a ``.zip``): a
    fine-tuned model has seen them too."""
    path = Path(init)
    folder = path if path.is_dir() else path.parent
    try:
        return list(json.loads((folder / METRICS_FILE).read_text()).get("training_shops", []))
    except (OSError, json.JSONDecodeError):
        return []


def _check_init_apart(init: Path) -> None:
    """Refuse initial weights that saw a benchmark instance or a held-out shop: a model trained with
    ``allow_benchmarks`` (its config says so) or whose recorded training shops carry such a name. Its shops join the
    new model's record, and the new config's own specs are all that :func:`fms_sim.shopsets.check_training_specs`
    sees (a model fine-tuned from one trained on EX12 was recorded as trained apart)."""
    from fms_sim.benchmarks import builtin_names
    from fms_sim.shopsets import heldout_names

    folder = init if init.is_dir() else init.parent
    try:
        allowed = bool(_saved_config(folder / CONFIG_FILE).get("allow_benchmarks"))
    except (OSError, ValueError):
        allowed = False  # no readable config: its recorded shops decide
    reserved = set(builtin_names()) | set(heldout_names())
    seen = [name for name in _init_shops(init) if name in reserved or name.partition("L")[0] in reserved]
    if allowed or seen:
        what = f"its training shops include {', '.join(seen[:5])}" if seen else "its config sets allow_benchmarks"
        raise ValueError(f"init {init}: a model trained on benchmark instances or held-out shops ({what}); a model "
                         "fine-tuned from it has seen them too: set allow_benchmarks for such a model, or start "
                         "from one trained on generated shops")


#: the entries of a model's metrics.json measured on its solving weights (bench/heldout.py, bench/rl_eval.py,
#: bench/plan_assignments.py: with new weights the network may choose otherwise than the plan's assignments)
_WEIGHT_FIGURES = ("heldout", "benchmark", "plan_assignments")


def _solving_weights_sha(out: Path) -> str | None:
    """The SHA-256 of the weights a model in ``out`` solves with (``best_model.zip``, else ``model.zip``)."""
    from .actors import file_sha256

    weights = out / "best_model.zip" if (out / "best_model.zip").is_file() else out / "model.zip"
    return file_sha256(weights) if weights.is_file() else None


def _load_init(model: Any, init: str | Path, run: dict[str, Any] | None = None) -> None:
    """Copy the policy weights of ``init`` (a ``.zip``, or a model folder: its ``best_model.zip``, else its
    ``model.zip``) into ``model``; raises ValueError if they do not fit (another padding, net, guide or
    architecture), naming what differs between the initial model's config and ``run`` (this run's ``decisions``,
    ``guide`` and ``padding``) where the initial model's folder has its config."""
    from sb3_contrib import MaskablePPO

    path = _init_weights(init)
    src = MaskablePPO.load(str(path), device="cpu")
    if (src.observation_space.shape != model.observation_space.shape
            or src.action_space.n != model.action_space.n):
        differ = ""
        try:
            theirs = json.loads((path.parent / CONFIG_FILE).read_text())
        except (OSError, ValueError):
            theirs = None
        if isinstance(theirs, dict) and run:  # (it gave only the shapes: observation (127,), 10 actions)
            from .envs import padding_for

            mine = dict(run)
            theirs = {"decisions": theirs.get("decisions") or "paper", "guide": theirs.get("guide") or None,
                      "padding": theirs.get("padding")}
            for side in (mine, theirs):  # a profile's name as its sizes
                if isinstance(side.get("padding"), str):
                    try:
                        side["padding"] = padding_for(side["padding"], [])
                    except ValueError:
                        pass
            what = {"decisions": "net", "guide": "guide", "padding": "padding"}
            differ = "; ".join(f"its {what[k]} {theirs[k]!r}, this run's {mine[k]!r}" for k in what
                               if k in mine and theirs[k] != mine[k])
            differ = f": {differ}" if differ else ""
        raise ValueError(f"init: the weights in {path} were trained for another layout{differ} (observation "
                         f"{src.observation_space.shape}, {src.action_space.n} actions; this model: "
                         f"{model.observation_space.shape}, {model.action_space.n})")
    try:
        model.policy.load_state_dict(src.policy.state_dict())
    except RuntimeError as exc:
        raise ValueError(f"init: the weights in {path} do not fit this architecture: {exc}") from None


def _effort(cfg: dict[str, Any]) -> Any:
    """The config's ``guide_effort`` as a :class:`~fms_dispatch.rl.guide.PlanEffort` (None: the plain list
    schedule); raises ValueError for unknown fields or bad values."""
    from .guide import PlanEffort

    d = cfg.get("guide_effort")
    if d is None:
        return None
    if not isinstance(d, dict):
        raise ValueError(f"guide_effort must be a dict of PlanEffort fields, not {d!r}")
    if not cfg.get("guide"):
        raise ValueError("guide_effort searches the plan of a guided model: set guide to list")
    try:
        return PlanEffort(**d)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"bad guide_effort {d!r}: {exc}") from None


def _refine_stages(stages: Any, fleet: dict[str, Any], seed: int
                   ) -> list[tuple[str, list[Instance], int, float, int]]:
    """The validated ``warm_start.refine`` stages as ``(pair, instances, epochs, lr, seed)`` (stage ``k``'s
    seed defaults to ``seed + 1 + k``)."""
    from fms_dispatch.rules import parse_rule_name

    if not isinstance(stages, list):
        raise ValueError("warm_start.refine must be a list of stages ({train, pair, epochs, lr, seed})")
    out = []
    for k, st in enumerate(stages):
        unknown = set(st) - {"train", "pair", "epochs", "lr", "seed"} if isinstance(st, dict) else {"?"}
        if unknown or not st.get("train") or not st.get("pair"):
            raise ValueError(f"warm_start.refine[{k}] needs train (instance specs) and pair (e.g. "
                             f"'MTWR+nearest'), with optional epochs, lr and seed, not {st!r}")
        parse_rule_name(str(st["pair"]))  # unknown rules fail here, before any work
        # (int() and float() took 2.9 epochs as 2, True as 1, "nan" and inf as rates, and 'x' was a bare error)
        epochs, lr, stage_seed = st.get("epochs", 10), st.get("lr", 3e-4), st.get("seed", seed + 1 + k)
        for name, value, kind, words in (("epochs", epochs, "int>=1", "an integer >= 1"),
                                         ("lr", lr, "num>0", "a positive, finite number"),
                                         ("seed", stage_seed, "seed", "an integer from 0 to 2**31 - 1")):
            if not _KINDS[kind][0](value):  # the config's own tests (_KINDS)
                raise ValueError(f"warm_start.refine[{k}]: {name} must be {words}, got {value!r}")
        if isinstance(st["train"], str):  # split into its letters
            raise ValueError(f"warm_start.refine[{k}]: train must be a list of instance specs, got {st['train']!r}")
        out.append((str(st["pair"]), expand_instances(list(st["train"]), fleet), epochs, float(lr), stage_seed))
    return out


def _refine(model: Any, stages: list[tuple[str, list[Instance], int, float, int]], padding: dict[str, int],
            reward: str, say: Any) -> list[dict[str, Any]]:
    """Run the refine stages after the warm-start cloning: each clones one rule pair's demonstrations on its
    instances for a few epochs; returns each stage's figures."""
    from .imitation import clone, pair_demonstrations

    figures = []
    for pair, insts, epochs, lr, seed in stages:
        demos, ms = pair_demonstrations(insts, pair, padding, reward, progress=say)
        bc = clone(model, demos, epochs=epochs, lr=lr, seed=seed, progress=say)
        figures.append(dict(pair=pair, instances=len(insts), epochs=epochs, lr=lr, seed=seed, **bc,
                            mean_makespan=round(float(np.mean(list(ms.values()))), 1)))
    return figures


def _ppo_progress(total: int, rollout: int, best: Callable[[], float], say: Callable[[str], None]) -> Any:
    """A callback that says how far PPO is, about 20 times in a run of ``total`` steps (after whole rollouts of
    ``rollout`` steps), with the best evaluation's mean reward so far (``best()``) and an estimate of the time
    left. For runs without sb3's progress bar (standard output is no terminal: a log file, ``nohup``): the PPO
    phase of such a run said nothing for hours between the warm start and the final line."""
    from stable_baselines3.common.callbacks import BaseCallback

    class _Progress(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.every = max(rollout, -(-total // 20))
            self.start = self.last = 0
            self.t0 = 0.0

        def _on_training_start(self) -> None:
            self.start = self.last = self.num_timesteps  # (a resumed model's count goes on from its own)
            self.t0 = time.perf_counter()

        def _on_rollout_end(self) -> None:
            done = self.num_timesteps - self.start
            if done - (self.last - self.start) < self.every and done < total:
                return
            self.last = self.num_timesteps
            wall = time.perf_counter() - self.t0
            left = wall * (total - done) / done if done else 0.0
            b = best()
            evaluated = f"; best eval mean reward {b:.4f}" if math.isfinite(b) else ""
            say(f"PPO: {done}/{total} steps ({100 * done / total:.0f} %), {wall:.0f} s, about {left:.0f} s "
                f"left{evaluated}")

        def _on_step(self) -> bool:
            return True

    return _Progress()


def _lone_sample(ppo: dict[str, Any], n_envs: int) -> str | None:
    """Why PPO's updates would fail on these hyper-parameters (None: they do not). PPO normalises the advantages of
    each mini-batch by their standard deviation, which one sample does not have: a mini-batch of one step (batch_size
    1, or a rollout of n_steps x n_envs one more than a multiple of batch_size) made every loss NaN, and the run
    ended in the "PPO diverged" message, which sent the user to the learning rate."""
    rollout, batch = int(ppo["n_steps"]) * n_envs, int(ppo["batch_size"])
    if batch == 1:
        return ("ppo.batch_size must be >= 2: PPO normalises each mini-batch's advantages by their standard "
                "deviation, which a single step does not have")
    if rollout % batch == 1:
        return (f"a rollout of ppo.n_steps x n_envs = {int(ppo['n_steps'])} x {n_envs} = {rollout} steps in "
                f"mini-batches of ppo.batch_size {batch} leaves a last mini-batch of one step, whose advantages "
                "cannot be normalised (PPO's losses would be NaN): choose n_steps, n_envs or batch_size so that "
                "batch_size divides the rollout, or leaves at least 2 steps over")
    return None


def _misfit(instances: Sequence[Instance], padding: dict[str, int]) -> str | None:
    """Why the first of ``instances`` that exceeds ``padding`` does not fit (None: all fit), as the env checks it
    (:func:`fms_sim.env.padding_excess`)."""
    from fms_sim.env import padding_excess

    for inst in instances:
        over = padding_excess(inst, padding)
        if over is not None:
            what, n, cap = over
            return f"shop {inst.name} has {n} {what}, more than the model's padded maximum {cap}"
    return None


#: the files of a trained model in its folder (with a ``.actor.npz`` export beside each ``.zip``)
MODEL_FILES = (CONFIG_FILE, METRICS_FILE, "model.zip", "best_model.zip", "warm_start.zip")


def _save_model(model: Any, path: Path) -> None:
    """``model.save`` to ``path`` through a temporary beside it, renamed when complete: an interrupt while sb3 writes
    the zip left a truncated model that no run could load (the actor exports are written the same way)."""
    tmp = path.with_name(f".{path.name}.tmp.zip")
    try:
        model.save(str(tmp))
        tmp.replace(path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


class _HeldInterrupts:
    """While entered, Ctrl-C and the stop signals (SIGTERM, SIGHUP, SIGQUIT) are held instead of raised;
    :attr:`seen` says whether one came. For the few seconds that write a finished run's files: interrupted there, a
    run kept weights that its metrics did not describe. Outside the main thread nothing can be held."""

    def __init__(self) -> None:
        self.seen = False
        self._old: dict[int, Any] = {}

    def _hold(self, signum: int, frame: Any) -> None:
        self.seen = True

    def __enter__(self) -> "_HeldInterrupts":
        import signal

        from ..up import STOP_SIGNALS

        try:
            for sig in (signal.SIGINT, *STOP_SIGNALS):
                self._old[sig] = signal.signal(sig, self._hold)
        except ValueError:  # not the main thread
            self.__exit__()
        return self

    def __exit__(self, *exc: Any) -> None:
        import signal

        for sig, old in self._old.items():
            signal.signal(sig, old)
        self._old = {}


def _model_files(out: Path) -> list[Path]:
    """The files of a trained model that folder ``out`` holds (:data:`MODEL_FILES` and their actor exports)."""
    names = list(MODEL_FILES) + [n[:-len(".zip")] + ".actor.npz" for n in MODEL_FILES if n.endswith(".zip")]
    return [out / n for n in names if (out / n).is_file()]


def train(config: dict[str, Any], out: str | Path, resume: bool = False, progress: bool = True,
          tensorboard: str | Path | None = None, verbose: int = 0, dagger: int = 0,
          force: bool = False) -> dict[str, Any]:
    """Train (or continue) the model in folder ``out`` per ``config``; returns the metrics written.

    A new model is never trained over another: a fresh run (not ``resume``) into a folder that holds a model's
    files is refused, unless ``force``, which removes them (:data:`MODEL_FILES` and their actor exports; nothing
    else) once the configuration is checked and before training starts. (A run over another model rewrote its
    config but kept its ``best_model.zip``, which the new run then reported and solved with as its own.)

    A fresh run with a warm-start expert first clones the expert, then runs the ``warm_start.refine`` stages
    (each clones one rule pair on its own instances), then ``warm_start.dagger`` DAgger rounds (rule-pair or
    plan experts), then ``steps`` PPO steps. With ``init`` and a warm-start expert the DAgger rounds start from
    the initial weights, without the clone.

    With ``resume``, the config is read from ``out/config.json`` (``config`` may override ``steps``) and
    training continues from ``out/model.zip``: first ``dagger`` more DAgger rounds (rule-pair or plan experts; the
    expert demonstrations are made again to aggregate with), then ``steps`` more PPO steps.
    """
    import torch
    from sb3_contrib import MaskablePPO
    from sb3_contrib.common.maskable.callbacks import MaskableEvalCallback
    from stable_baselines3.common.callbacks import BaseCallback, CallbackList
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv

    from .envs import obs_layout, padding_for

    torch.set_num_threads(1)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ValueError(f"the model folder {out} is a file")
    check_config(config)
    if resume and force:
        raise ValueError("--force trains a new model over the one in the folder; --resume continues it: give one")
    held = _model_files(out) if not resume and out.is_dir() else []
    if held and not force:
        raise ValueError(f"{out} already holds a model ({', '.join(p.name for p in held)}): continue it with "
                         "--resume, give another --out, or --force to replace it")
    if resume:
        ignored = sorted(k for k, v in config.items() if k != "steps" and v is not None)
        if ignored:  # they were dropped without a word (the CLI refuses their flags)
            raise ValueError(f"resume continues the model in {out} with its own {CONFIG_FILE}: the config gives only "
                             f"steps, not {', '.join(ignored)} (train a new model for those)")
        earlier = _saved_config(out / CONFIG_FILE) if (out / CONFIG_FILE).is_file() else None
        has_model = (out / "model.zip").is_file()
        if earlier is None:
            raise ValueError(f"cannot resume: {out} has no {CONFIG_FILE}{'' if has_model else ' and no model.zip'} "
                             "from an earlier run")
        if not has_model:  # (it said "no config.json and model.zip" of a folder holding its config.json)
            raise ValueError(f"cannot resume: {out} has no model.zip from an earlier run (the latest weights, which a "
                             "model shipped without them or a run that ended before its first save does not have: "
                             "train a new model, from it with --init)")
        try:  # (an edited config.json ran unchecked: eval_freq 0 evaluated at every step)
            check_config(earlier)
        except ValueError as exc:
            raise ValueError(f"cannot resume: {out / CONFIG_FILE}: {exc}") from None
        cfg = _merge(earlier, {"steps": config.get("steps")})
    else:
        cfg = _merge(DEFAULT_CONFIG, config)
    cfg["name"] = (cfg.get("name") or out.name) if resume else out.name
    if not cfg["train"]:
        raise ValueError("no training instances given")
    if not cfg.get("allow_benchmarks"):  # a resume too: its config.json may have been edited since
        from fms_sim.shopsets import check_training_specs

        try:
            check_training_specs(cfg)
        except ValueError as exc:
            if resume:  # (its edited train list trained on EX12 and the model was still recorded as apart)
                raise ValueError(f"cannot resume: {out / CONFIG_FILE}: {exc}") from None
            if not str(exc).startswith("training must use generated shops"):
                raise  # a spec that does not expand is a typo, not a benchmark: no hint about benchmarks
            raise ValueError(f"{exc}\n(a model for reproducing the paper's own setting may train on benchmark "
                             "instances with --allow-benchmarks; its config then says so, and the figures measured "
                             "on those instances are not held-out results)") from None
    decisions = cfg.get("decisions") or "paper"
    if decisions not in ("paper", "full"):
        raise ValueError(f"unknown decisions {decisions!r}; choose paper (the paper's net) or full (the "
                         "full-decision net)")
    cfg["decisions"] = decisions
    guide = cfg.get("guide") or None  # "" (--guide none) overrides a config file's guide
    from .envs import check_guide

    check_guide(guide, decisions)
    cfg["guide"] = guide
    effort = _effort(cfg)
    from fms_sim.env import check_disruptions

    disruptions = check_disruptions(cfg.get("disruptions"), decisions)
    eval_disruptions = dict(disruptions, fixed=True) if disruptions else None
    if cfg["reward"] not in ("idle", "makespan", "shaped"):
        raise ValueError(f"unknown reward {cfg['reward']!r}; choose from idle, makespan, shaped")
    steps = int(cfg["steps"])
    warm = dict(DEFAULT_CONFIG["warm_start"], **(cfg.get("warm_start") or {}))
    # a resumed run continues its own weights: the initial model is needed again only as the baseline (resolving it
    # made a resume fail once that model was moved, or from another working folder)
    init = _resolve_init(cfg["init"]) if cfg.get("init") and (not resume or cfg.get("baseline")) else None
    if init and not resume and (init if init.is_dir() else init.parent).resolve() == out.resolve():
        # --force removed the model it was to start from (its recorded shops with it), and the config then named the
        # folder's own new weights as the initial ones
        raise ValueError(f"init {cfg['init']} is the model folder being trained: fine-tune into another folder "
                         "(--out), which keeps the initial model as it is")
    if init and not resume and not cfg.get("allow_benchmarks"):
        _check_init_apart(init)
    if init and not resume and warm["expert"] and not int(warm["dagger"]):
        raise ValueError("init starts from a trained model's weights: it replaces the cloning of a warm-start "
                         "expert (unset warm_start.expert, or set warm_start.dagger for DAgger rounds from the "
                         "initial weights)")
    baseline = cfg.get("baseline") or None
    if baseline not in (None, "init"):
        raise ValueError(f"unknown baseline {baseline!r}; the only one is init (returns relative to the initial "
                         "weights' run of the same episode)")
    if baseline and not init:
        raise ValueError("baseline init compares with the weights a run starts from: set init")
    if baseline and cfg["reward"] != "shaped":
        raise ValueError("baseline init needs the shaped reward")
    if baseline and warm["expert"] and not resume:
        raise ValueError("baseline init compares with the initial weights, which DAgger rounds would change: run "
                         "the DAgger rounds first (steps 0), then PPO with init set to their model")
    reference = _init_weights(init) if baseline else None
    from .imitation import EXPERTS, RULE_EXPERTS
    from .plan_expert import GUIDE_EXPERT, is_plan_expert

    planned = is_plan_expert(warm["expert"])
    if planned and str(warm["expert"]).lower() == GUIDE_EXPERT and guide is None and not resume:
        raise ValueError("the guide expert follows the plan that a guided observation shows: set guide to list "
                         "(--guide list)")
    if warm["expert"] and not resume:
        if planned and decisions != "full":
            raise ValueError(f"the plan expert {warm['expert']!r} demonstrates on the full-decision net: set "
                             "decisions to full")
        if not planned and warm["expert"] not in EXPERTS:
            raise ValueError(f"unknown warm-start expert {warm['expert']!r}; choose from {', '.join(EXPERTS)} "
                             "(paper net) or plan:SOLVER[:SECONDS] (full net, e.g. plan:cpsat:5, plan:list)")
        if not planned and decisions == "full":
            raise ValueError(f"the expert {warm['expert']!r} acts on the paper's net; on the full net use a plan "
                             "expert (plan:SOLVER[:SECONDS], e.g. plan:cpsat:5 or plan:list)")
    if dagger < 0:  # it said the rounds are for a model being resumed, of a model being resumed
        raise ValueError(f"--dagger must be >= 0 (DAgger rounds to add), got {dagger}")
    if dagger and not resume:
        raise ValueError("--dagger N adds rounds to a model being resumed; for a new model set "
                         "warm_start.dagger in its config")
    rounds = dagger if resume else int(warm["dagger"])
    if rounds and warm["expert"] not in RULE_EXPERTS and not planned:
        raise ValueError(f"DAgger needs a rule-pair or plan warm-start expert (rules, rules+nearest, "
                         f"plan:SOLVER[:SECONDS]), not {warm['expert']!r}: only those can label the policy's own "
                         "states")
    if steps < 0 or (steps == 0 and not rounds and (resume or not warm["expert"])):
        # (after "--steps must be >= 0 (0: the warm start or DAgger rounds only)", a bare "must be positive" for 0)
        raise ValueError("--steps must be positive: 0 trains only a warm start or DAgger rounds, and this run has "
                         + ("no --dagger rounds to add" if resume else "no warm-start expert"))
    refine = _refine_stages(warm["refine"], cfg["fleet"], int(cfg["seed"])) if not resume else []
    if refine and not warm["expert"]:
        raise ValueError("warm_start.refine follows the cloning of a warm-start expert: set warm_start.expert")
    if refine and decisions == "full":
        raise ValueError("warm_start.refine clones rule pairs of the paper's net; it does not apply to the full net")
    train_set = expand_instances(cfg["train"], cfg["fleet"])
    eval_set = expand_instances(cfg["eval"], cfg["fleet"]) if cfg["eval"] else train_set[:10]
    for what, shops in (("train", train_set), ("eval", eval_set)):
        twice = _named_twice(shops)
        if twice is not None:  # results are kept by name: metrics.json lost one of them (and its mean was wrong)
            raise ValueError(f"two shops of the {what} set are named {twice!r} (gen: names leave out the tool count "
                             "and the fleet): give them different seeds")
    everything = train_set + eval_set + [i for st in refine for i in st[1]]
    padding = padding_for(cfg["padding"], everything)
    misfit = _misfit(everything, padding)
    if misfit:  # checked here: found in a worker process it ended in a traceback and a broken pipe
        raise ValueError(f"{misfit} (padding {cfg['padding'] if isinstance(cfg['padding'], str) else padding}; "
                         "--padding auto fits every shop)")
    if cfg["padding"] in (None, "auto"):
        cfg["padding"] = padding
    if int(cfg["n_envs"]) < 1:
        raise ValueError(f"n_envs must be >= 1, got {cfg['n_envs']}")
    lone = _lone_sample(dict(DEFAULT_CONFIG["ppo"], **(cfg.get("ppo") or {})), int(cfg["n_envs"]))
    if lone:  # checked before the warm start: PPO met it in its first update, after the cloning
        raise ValueError(lone)
    tb = Path(tensorboard) if tensorboard else Path("runs") / cfg["name"]

    n_envs = int(cfg["n_envs"])
    seed = int(cfg["seed"])
    fns = [_make_env(train_set, padding, cfg["reward"], seed + i, decisions, guide, effort, disruptions, reference)
           for i in range(n_envs)]
    venv = SubprocVecEnv(fns) if n_envs > 1 and cfg["vec_env"] == "subproc" else DummyVecEnv(fns)
    eval_env = DummyVecEnv([_make_env(_Cycle(eval_set), padding, cfg["reward"], seed + 10_000, decisions, guide,
                                      effort, eval_disruptions, reference)])

    ppo = dict(cfg["ppo"])
    if resume:
        try:
            model = MaskablePPO.load(str(out / "model.zip"), env=venv, device="cpu", tensorboard_log=str(tb))
        except OSError:
            raise
        except Exception as exc:  # a damaged save: sb3's own words were "fms: error: Error: the file ... wasn't a
            venv.close()  # zip-file"
            eval_env.close()
            cause = str(exc).removeprefix("Error: ").strip() or type(exc).__name__
            raise ValueError(f"cannot resume: {out / 'model.zip'} is not a readable MaskablePPO model ({cause})") \
                from None
    else:
        if cfg["arch"] == "entity":
            from .policy import EntityPolicy

            policy: Any = EntityPolicy
            pkw = {"layout": obs_layout(padding, decisions, guide), "hidden": int(cfg["hidden"])}
        elif cfg["arch"] == "mlp":
            policy, pkw = "MlpPolicy", {"net_arch": list(cfg["net_arch"])}
        else:
            raise ValueError(f"unknown arch {cfg['arch']!r}; choose entity or mlp")
        model = MaskablePPO(policy, venv, policy_kwargs=pkw, seed=seed, device="cpu", verbose=verbose,
                            tensorboard_log=str(tb), **ppo)
        if init:
            try:
                _load_init(model, init, {"decisions": decisions, "guide": guide, "padding": padding})
            except ValueError:  # weights that do not fit: refused before the folder is made or a model removed
                venv.close()
                eval_env.close()
                raise
    for stale in held:  # force: the model replaced (checked above: only with force)
        stale.unlink()
    out.mkdir(parents=True, exist_ok=True)

    metrics_path = out / METRICS_FILE
    old = json.loads(metrics_path.read_text()) if resume and metrics_path.is_file() else {}
    best_before = _solving_weights_sha(out) if resume else None

    class _Saver(BaseCallback):
        """Save ``model.zip`` every ``save_freq`` steps, so that an interrupted run can be resumed."""

        def __init__(self, every: int):
            super().__init__()
            self.every, self.last = every, 0

        def _on_step(self) -> bool:
            if self.num_timesteps - self.last >= self.every:
                self.last = self.num_timesteps
                _save_model(self.model, out / "model.zip")
            return True

    class _SaveBest(BaseCallback):
        """Save the best weights (the evaluation callback's new best) to ``best_model.zip``, atomically."""

        def _on_step(self) -> bool:
            _save_model(self.model, Path(out) / "best_model.zip")
            return True

    class _Trained(BaseCallback):
        """Count the steps PPO trained on: each rollout once it is collected (its update follows at once). The
        steps of a rollout cut short by an interrupt were collected but never learnt from (they were counted as PPO
        steps, so an interrupted clone was reported as a PPO model)."""

        def __init__(self) -> None:
            super().__init__()
            self.steps = 0
            self._start = 0

        def _on_rollout_start(self) -> None:
            self._start = self.num_timesteps

        def _on_rollout_end(self) -> None:
            self.steps += self.num_timesteps - self._start

        def _on_step(self) -> bool:
            return True

    eval_cb = MaskableEvalCallback(eval_env, n_eval_episodes=len(eval_set),
                                   eval_freq=max(1, int(cfg["eval_freq"]) // n_envs),
                                   best_model_save_path=None, callback_on_new_best=_SaveBest(), log_path=None,
                                   deterministic=True, verbose=0)
    if old.get("training", {}).get("best_mean_reward") is not None:
        eval_cb.best_mean_reward = float(old["training"]["best_mean_reward"])

    t0 = time.perf_counter()
    warm_metrics = None
    if (not resume and warm["expert"]) or rounds:
        from sb3_contrib.common.maskable.evaluation import evaluate_policy

        from .imitation import clone, dagger as run_dagger, demonstrations
        from .plan_expert import plan_dagger, plan_demonstrations

        say = progress_line if (verbose or progress) else None
        warm_set = train_set[:int(warm["instances"])]
        pairs: dict[str, str] = {}
        plans: dict[str, Any] = {}
        if planned:
            demos, expert_ms = plan_demonstrations(warm_set, padding, cfg["reward"], warm["expert"], seed=seed,
                                                   progress=say, plans=plans, guide=guide)
        else:
            demos, expert_ms = demonstrations(warm_set, padding, cfg["reward"], warm["expert"],
                                              iters=int(warm["search_iters"]), seed=seed, progress=say,
                                              pairs=pairs, insert=float(warm["search_insert"]),
                                              restarts=int(warm["search_restarts"]),
                                              starts=int(warm["search_starts"]), workers=int(warm["workers"]))
        bc: dict[str, Any] = {}
        refined: list[dict[str, Any]] = []
        if not resume and not init:  # with init the DAgger rounds start from its weights
            bc = clone(model, demos, epochs=int(warm["epochs"]), lr=float(warm["lr"]), seed=seed, progress=say)
            refined = _refine(model, refine, padding, cfg["reward"], say)
        history: list[dict[str, Any]] = []
        if rounds:
            dagger_seed = seed + 100 * int(old.get("warm_start", {}).get("dagger", 0))
            if planned:
                _, history = plan_dagger(model, demos, plans, expert_ms, warm_set, padding, cfg["reward"], rounds,
                                         epochs=int(warm["dagger_epochs"]), lr=float(warm["lr"]),
                                         seed=dagger_seed, progress=say, guide=guide,
                                         follow=str(warm["expert"]).lower() == GUIDE_EXPERT, disruptions=disruptions)
            else:
                _, history = run_dagger(model, demos, pairs, expert_ms, warm_set, padding, cfg["reward"], rounds,
                                        epochs=int(warm["dagger_epochs"]), lr=float(warm["lr"]), seed=dagger_seed,
                                        progress=say)
        mean_r, _ = evaluate_policy(model, eval_env, n_eval_episodes=len(eval_set), deterministic=True)
        if not resume or float(mean_r) >= eval_cb.best_mean_reward:  # the best weights are kept
            eval_cb.best_mean_reward = float(mean_r)  # PPO must beat the warm-started policy to replace it
            _save_model(model, out / "best_model.zip")
        _save_model(model, out / "model.zip")
        _save_model(model, out / "warm_start.zip")  # the clone as it was before PPO, to measure what PPO adds
        if resume:  # extend the record of the first warm start
            warm_metrics = dict(old.get("warm_start", {}))
            warm_metrics["dagger"] = int(warm_metrics.get("dagger", 0)) + rounds
            warm_metrics["dagger_epochs"] = int(warm["dagger_epochs"])
            cfg["warm_start"] = dict(cfg.get("warm_start") or {}, dagger=warm_metrics["dagger"],
                                     dagger_epochs=int(warm["dagger_epochs"]))
            (out / CONFIG_FILE).write_text(json.dumps(cfg, indent=2) + "\n")
        else:
            warm_metrics = dict(warm, **bc, expert_makespan=expert_ms, refine=refined)  # stages with figures
            if init:  # the rounds started from these weights: no clone ran, so no clone epochs either
                warm_metrics["init"] = str(cfg["init"])  # as given (resolved, a shipped one was this machine's path)
                warm_metrics.pop("epochs", None)
        earlier_rounds = list(warm_metrics.get("dagger_rounds", []))  # a resumed run's rounds follow them (all
        warm_metrics["dagger_rounds"] = earlier_rounds + [  # were numbered from 1)
            dict(r, round=len(earlier_rounds) + int(r.get("round", k + 1))) for k, r in enumerate(history)]
        warm_metrics.update(mean_reward=round(float(mean_r), 4),
                            seconds=round(float(warm_metrics.get("seconds", 0.0)) + time.perf_counter() - t0, 1))
        if verbose or progress:
            progress_line(f"warm start ({warm['expert']}, {len(history)} DAgger rounds): {bc or history[-1]}; "
                          f"eval mean reward {mean_r:.4f}")
    if init and not resume and warm_metrics is None:  # the starting weights are the baseline PPO must beat
        from sb3_contrib.common.maskable.evaluation import evaluate_policy

        mean_r, _ = evaluate_policy(model, eval_env, n_eval_episodes=len(eval_set), deterministic=True)
        eval_cb.best_mean_reward = float(mean_r)
        for name in ("best_model.zip", "model.zip", "warm_start.zip"):
            _save_model(model, out / name)
        warm_metrics = {"init": str(cfg["init"]), "mean_reward": round(float(mean_r), 4)}
        if verbose or progress:
            progress_line(f"initial weights {init}: eval mean reward {mean_r:.4f}")
    # written once the folder holds weights to continue from: written before the warm start, an interrupted one left
    # a folder that a new run refused (it holds a model) and --resume too (it has no model.zip)
    (out / CONFIG_FILE).write_text(json.dumps(cfg, indent=2) + "\n")
    interrupted = False
    rollout = int(model.n_steps) * n_envs
    total = -(-steps // rollout) * rollout  # PPO learns from whole rollouts: what sb3 runs for ``steps``
    if steps and steps % rollout:
        progress_line(f"note: PPO collects rollouts of n_steps x n_envs = {rollout} steps, so {steps} steps run as "
                      f"{total}")
    trained = _Trained()
    if steps:
        try:
            with warnings.catch_warnings():
                # sb3 warns whenever the training envs run in subprocesses and the evaluation env does not; ours
                # is meant so
                warnings.filterwarnings("ignore", message="Training and eval env are not of the same type",
                                        category=UserWarning)
                # sb3's bar is drawn on stdout: only where someone watches it (piped, a reader that left ended
                # the run through rich's SystemExit, without its files); elsewhere progress lines on stderr
                bar = progress and sys.stdout.isatty()
                callbacks = [eval_cb, _Saver(int(cfg["save_freq"])), trained]
                if (progress or verbose) and not bar:
                    callbacks.append(_ppo_progress(total, rollout, lambda: float(eval_cb.best_mean_reward),
                                                   progress_line))
                model.learn(total_timesteps=total, callback=CallbackList(callbacks),
                            reset_num_timesteps=not resume, progress_bar=bar, tb_log_name="ppo")
        except KeyboardInterrupt:  # Ctrl-C: keep what was learnt; --resume continues from here
            interrupted = True
        except BaseException as exc:
            if not resume and not (out / "model.zip").is_file():  # a config of no weights: the folder was refused
                (out / CONFIG_FILE).unlink(missing_ok=True)  # by a new run and by --resume alike
            if isinstance(exc, ValueError) and "found invalid values" in str(exc):  # torch's check of the logits
                raise ValueError("PPO diverged: the policy's outputs became NaN (lower ppo.learning_rate, vf_coef or "
                                 "clip_range)") from None
            raise
    wall = time.perf_counter() - t0
    from .agent import export_actor

    with _HeldInterrupts() as stop:  # a few seconds: the files of what was learnt, complete
        _save_model(model, out / "model.zip")
        try:
            venv.close()
        except (EOFError, BrokenPipeError, ConnectionResetError):  # a worker already gone (killed): nothing to close
            if not (interrupted or stop.seen):  # (a stop signal to the process group, held here, ends the workers)
                raise
        eval_env.close()
        for saved in ("model.zip", "best_model.zip", "warm_start.zip"):  # numpy exports: inference without torch
            if (out / saved).is_file():
                export_actor(out / saved)
    interrupted = interrupted or stop.seen
    weights = out / "best_model.zip" if (out / "best_model.zip").is_file() else out / "model.zip"
    try:
        makespans: dict[str, int] | None = evaluate_model(weights, padding, eval_set, decisions=decisions, guide=guide,
                                                          guide_effort=effort, disruptions=disruptions)
    except KeyboardInterrupt:  # the weights are saved: the metrics say what they are, without the evaluation
        interrupted, makespans = True, None
    prev = old.get("training", {})
    metrics = dict(old)
    if resume and _solving_weights_sha(out) != best_before:  # figures measured on the weights this run replaced
        dropped = [k for k in _WEIGHT_FIGURES if metrics.pop(k, None) is not None]
        if dropped and (verbose or progress):
            progress_line(f"note: {weights.name} changed, so its {' and '.join(dropped)} figures in {METRICS_FILE} were "
                          "of the old weights and are dropped (measure them again: bench/heldout.py --write-metrics, "
                          "bench/plan_assignments.py --record)")
    if warm_metrics is not None:
        metrics["warm_start"] = warm_metrics
    metrics["training"] = {
        "timesteps": int(model.num_timesteps),
        "wall_seconds": round(prev.get("wall_seconds", 0.0) + wall, 1),
        # None (JSON null) when no evaluation ran: -inf is not JSON
        "best_mean_reward": float(eval_cb.best_mean_reward) if np.isfinite(eval_cb.best_mean_reward) else None,
        "weights": weights.name,
        "eval_makespan": makespans,  # None: interrupted before the evaluation of the weights
        "eval_mean_makespan": round(float(np.mean(list(makespans.values()))), 2) if makespans else None,
        "interrupted": interrupted,
    }
    metrics["training_shops"] = list(dict.fromkeys([inst.name for inst in train_set]
                                                   + [inst.name for st in refine for inst in st[1]]
                                                   + list(old.get("training_shops", []))
                                                   + (_init_shops(init) if init else [])))
    # the steps PPO learnt from (0: a clone, DAgger included, not a PPO-trained model); timesteps above counts the
    # steps collected, with those of a rollout an interrupt cut short
    before = int(old.get("ppo_steps", 0)) if resume else 0
    metrics["ppo_steps"] = before + trained.steps
    if resume:  # each continuation on record: what it added to the model the config alone would train
        metrics["resumes"] = list(old.get("resumes", [])) + [{
            "ppo_steps_before": before, "ppo_steps_after": metrics["ppo_steps"],
            "dagger_rounds": int(rounds), "wall_seconds": round(wall, 1), "interrupted": interrupted}]
    with _HeldInterrupts():  # (written whole: an interrupt after it is of a complete run)
        write_atomically(metrics_path, json.dumps(metrics, indent=2) + "\n")
    return metrics


# ---------------------------------------------------------------------- CLI
def add_train_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``fms train`` to the CLI's subparsers."""
    s = subparsers.add_parser("train", help="train a MaskablePPO dispatching agent (sb3-contrib)")
    s.add_argument("instances", nargs="*", help="training instances: names, files, patterns ('EX?2'), "
                                                 "gen:JxMxT*COUNT@SEED")
    s.add_argument("--eval", nargs="+", metavar="INSTANCE", help="held-out evaluation instances (default: the "
                                                                 "first 10 training instances)")
    s.add_argument("--steps", type=int, help="environment steps to train (more steps with --resume)")
    s.add_argument("--reward", choices=("idle", "makespan", "shaped"), help="reward (default shaped)")
    s.add_argument("--seed", type=int)
    s.add_argument("--out", required=True, help="model folder (e.g. models/NAME)")
    s.add_argument("--config", help="JSON file with hyper-parameters (see fms_dispatch.rl.train.DEFAULT_CONFIG)")
    s.add_argument("--padding", help="auto | bu | large: the padded maximum layout")
    s.add_argument("--arch", choices=("entity", "mlp"))
    s.add_argument("--n-envs", type=int, help="parallel environments")
    s.add_argument("--eval-freq", type=int, help="evaluate every N steps")
    s.add_argument("--agvs", type=int, help="override the number of AGVs of every instance")
    s.add_argument("--tool-transporters", type=int, help="override the number of tool transporters")
    s.add_argument("--no-tools", action="store_true", help="drop tools (AGV-only model)")
    s.add_argument("--resume", action="store_true", help="continue training the model in --out (takes --steps "
                                                          "and --dagger; the rest comes from its config.json)")
    s.add_argument("--force", action="store_true", help="train a new model into an --out that holds one, "
                                                         "replacing its model files (refused otherwise)")
    s.add_argument("--decisions", choices=("paper", "full"), help="the net the model decides through (default "
                                                                    "paper)")
    s.add_argument("--guide", choices=("list", "none"),
                   help="full net: add a list-schedule plan's orders to the observation (the better of the "
                        "earliest-start and earliest-completion list schedules; default none)")
    s.add_argument("--allow-benchmarks", action="store_true",
                   help="allow benchmark instances or held-out shops in training and evaluation (paper "
                        "reproductions only; refused otherwise)")
    s.add_argument("--dagger", type=int, default=0, metavar="N",
                   help="with --resume: N more DAgger rounds (label the policy's own states with the model's "
                        "warm-start expert, a rule pair or a plan, and clone again) before the PPO steps; "
                        "--steps 0 runs DAgger only")
    s.add_argument("--init", metavar="MODEL", help="start PPO from the weights of a trained model (a folder or "
                                                  ".zip with the same padding, net and guide) instead of a "
                                                  "warm start; they are kept as warm_start.zip")
    s.add_argument("--tensorboard", help="TensorBoard log folder (default runs/NAME)")
    s.add_argument("--no-progress", action="store_true", help="no progress bar")
    s.set_defaults(fn=cmd_train)
    return s


def cmd_train(a: argparse.Namespace) -> int:
    if a.steps is not None and a.steps < 0:  # named as --steps 0's refusal names it (not as a config key)
        raise ValueError(f"--steps must be >= 0 (0: the warm start or DAgger rounds only), got {a.steps}")
    if a.resume:  # a resumed model keeps its own config: an option it cannot apply is refused, not dropped
        given = [flag for flag, v in (("training instances", a.instances), ("--config", a.config), ("--eval", a.eval),
                                      ("--reward", a.reward), ("--seed", a.seed), ("--padding", a.padding),
                                      ("--arch", a.arch), ("--n-envs", a.n_envs), ("--eval-freq", a.eval_freq),
                                      ("--agvs", a.agvs), ("--tool-transporters", a.tool_transporters),
                                      ("--no-tools", a.no_tools), ("--decisions", a.decisions), ("--guide", a.guide),
                                      ("--allow-benchmarks", a.allow_benchmarks), ("--init", a.init))
                 if v not in (None, False, [])]
        if given:
            raise ValueError(f"--resume continues the model in {a.out} with its own {CONFIG_FILE}: it takes --steps "
                             f"and --dagger, not {', '.join(given)} (train a new model for those)")
    cfg: dict[str, Any] = {}
    if a.config:
        try:
            cfg = loads(read_text(a.config))
        except OSError as exc:
            raise ValueError(f"cannot read config {a.config}: {exc.strerror}") from None
        except json.JSONDecodeError as exc:
            raise ValueError(f"config {a.config} is not valid JSON: {exc.msg} (line {exc.lineno})") from None
        except UnicodeDecodeError:
            raise ValueError(f"config {a.config} is not a text (UTF-8 JSON) file") from None
        if not isinstance(cfg, dict):  # [] trained with the defaults, [["steps", 5]] was read as {"steps": 5}
            raise ValueError(f"config {a.config} must hold a JSON object of hyper-parameters, got "
                             f"{type(cfg).__name__}")
    for flag, value in (("--out", a.out), ("--tensorboard", a.tensorboard)):
        if value is not None and not value.strip():  # --out '': a model named '' in the current folder
            raise ValueError(f"{flag} names nothing (an empty name)")
    if a.tensorboard and Path(a.tensorboard).exists() and not Path(a.tensorboard).is_dir():
        raise ValueError(f"--tensorboard {a.tensorboard} is a file, not a folder")  # found after the model was built
    over: dict[str, Any] = {"steps": a.steps, "reward": a.reward, "seed": a.seed, "padding": a.padding,
                            "arch": a.arch, "n_envs": a.n_envs, "eval_freq": a.eval_freq,
                            "train": a.instances or None, "eval": a.eval, "decisions": a.decisions,
                            "guide": {"none": "", "list": "list"}.get(a.guide) if a.guide else None,
                            "allow_benchmarks": True if a.allow_benchmarks else None, "init": a.init}
    fleet = {"agvs": a.agvs, "tool_transporters": a.tool_transporters, "no_tools": True if a.no_tools else None}
    over["fleet"] = {k: v for k, v in fleet.items() if v is not None} or None
    cfg = _merge(cfg, over)
    if not a.resume and not cfg.get("train"):
        raise ValueError("give training instances (or --resume)")
    try:
        m = train(cfg, a.out, resume=a.resume, progress=not a.no_progress, tensorboard=a.tensorboard,
                  dagger=a.dagger, force=a.force)
    except KeyboardInterrupt:  # PPO's interrupts are caught in train: this one came before, in a warm start
        if a.resume or _model_files(Path(a.out)):
            raise
        # (it said only "fms: interrupted", after minutes or hours of demonstrations and cloning)
        print(f"fms: interrupted before the first weights were saved (in the warm start): nothing was kept; a new "
              f"run into {a.out} starts over", file=sys.stderr)
        return 130
    t = m["training"]
    evaluated = (f"eval mean makespan {t['eval_mean_makespan']}" if t["eval_mean_makespan"] is not None
                 else "not evaluated")
    print(f"{a.out}: {t['timesteps']} steps ({m['ppo_steps']} learnt from by PPO), {t['wall_seconds']} s; {evaluated} "
          f"({t['weights']})")
    if t["interrupted"]:  # (it exited 0 without a word: only metrics.json said so)
        print(f"fms: interrupted: the model is saved at {t['timesteps']} steps; fms train --out {a.out} --resume "
              "--steps N continues it", file=sys.stderr)
        return 130
    return 0
