"""Model folders, their config files, the shipped models and which one serves an instance by default.

A model folder (``models/NAME``) holds:

* ``config.json`` — everything needed to rebuild and re-train it (instances, padding, reward, policy
  architecture, PPO hyper-parameters, seed), written by ``fms train`` and committed next to the model;
* ``model.zip`` — the latest weights (what ``fms train --resume`` continues from);
* ``best_model.zip`` — the best weights by periodic evaluation on held-out instances (used for solving when
  present);
* ``metrics.json`` — training figures and benchmark results;
* ``best_model.actor.npz`` / ``model.actor.npz`` — the actor in numpy for inference without torch, with the
  SHA-256 of the weights it was exported from (:mod:`fms_dispatch.rl.actors`; ignored when stale).

Shipped models: ``guided-dagger`` (the full-decision net with a list-schedule plan's guide, any shop up to
100 x 20 x 20; the default: ``guided`` with DAgger rounds in disrupted runs), and, chosen by name, ``guided`` (the
clone it started from), ``guided-ppo`` (``guided`` fine-tuned by PPO in disrupted shops), ``bu`` (Bilge-Ulusoy-size
shops, 2 AGVs, no tools; the paper's net), ``large`` and ``large-agv`` (the paper's net; large shops with and
without tools) and ``full`` (the full net without a guide). A model name is looked up in :func:`model_dirs`,
one list of places for every caller (``fms solve``, ``fms up``, the agent node):

* ``$FMS_MODELS_DIR`` when it is set (then nothing else);
* the repository's ``models/`` folder when the package runs from a source checkout (editable install,
  ``colcon build --symlink-install``);
* ``<prefix>/share/fms_dispatch/models`` for the prefix the package is installed under (a non-editable pip
  install into a venv or ``--prefix``, a colcon install space), for ``sys.prefix`` and for every prefix in
  ``$AMENT_PREFIX_PATH``: both pip (setup.cfg ``data_files``) and colcon (``ros/fms_dispatch``) install the
  shipped models there, with the files solving needs (``config.json``, ``metrics.json``, ``best_model.zip``,
  ``best_model.actor.npz``).

A name found in none of them raises :class:`ModelNotFoundError`, which names every place searched.
"""

from __future__ import annotations

import functools
import gc
import json
import os
import sys
from pathlib import Path
from typing import Any

from fms_sim.instance import Instance

__all__ = ["ModelRef", "ModelNotFoundError", "model_dirs", "models_dir", "resolve_model", "default_model_name",
           "load_config", "SHIPPED", "SHARE_SUBDIR", "load_agent"]

SHIPPED = ("bu", "large", "large-agv", "full", "guided", "guided-dagger", "guided-ppo")
CONFIG_FILE = "config.json"
METRICS_FILE = "metrics.json"


#: where an install puts the shipped models, relative to its prefix
SHARE_SUBDIR = Path("share", "fms_dispatch", "models")


class ModelNotFoundError(ValueError):
    """A model name that is in none of the places :func:`model_dirs` lists (the message names them)."""


def _candidates() -> list[Path]:
    env = os.environ.get("FMS_MODELS_DIR")
    if env:
        return [Path(env)]
    here = Path(__file__).resolve()          # <root>/src/fms_dispatch/rl/models.py in a checkout,
    places = []                              # <prefix>/lib/pythonX.Y/site-packages/fms_dispatch/rl/... installed
    if here.parents[2].name == "src":
        places.append(here.parents[3] / "models")
    if here.parents[2].name in ("site-packages", "dist-packages") and here.parents[4].name.startswith("lib"):
        places.append(here.parents[5] / SHARE_SUBDIR)
    places.append(Path(sys.prefix) / SHARE_SUBDIR)
    places += [Path(p) / SHARE_SUBDIR for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    return list(dict.fromkeys(places))


def model_dirs() -> list[Path]:
    """The folders searched for a model given by name, in order (see the module docstring): those of the
    places that exist, without repeats."""
    found: list[Path] = []
    for place in _candidates():
        if place.is_dir() and not any(place.samefile(f) for f in found):
            found.append(place)
    return found


def _searched() -> str:
    return "searched " + ", ".join(str(p) for p in _candidates()) + " (FMS_MODELS_DIR sets the folder)"


def models_dir() -> Path:
    """The first folder of :func:`model_dirs` that holds every shipped model."""
    for place in model_dirs():
        if all((place / name).is_dir() for name in SHIPPED):
            return place
    raise ModelNotFoundError(f"the shipped models ({', '.join(SHIPPED)}) are not installed; {_searched()}")


def load_config(folder: str | Path) -> dict[str, Any]:
    path = Path(folder) / CONFIG_FILE
    try:
        config = json.loads(path.read_text(encoding="utf-8"))
    except OSError:
        raise ValueError(f"model folder {folder} has no readable {CONFIG_FILE}") from None
    except UnicodeDecodeError:
        raise ValueError(f"{path} is not a text (UTF-8 JSON) file") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path} is not valid JSON: {exc.msg} (line {exc.lineno})") from None
    if not isinstance(config, dict):  # a list was an AttributeError in whatever read it first
        raise ValueError(f"{path} must hold a JSON object (the training config), got {type(config).__name__}")
    return config


class ModelRef:
    """A resolved model: its folder, weights file, config and padded layout."""

    def __init__(self, folder: Path, weights: Path):
        self.folder = folder
        self.weights = weights
        self.config = load_config(folder)
        name = self.config.get("name")
        self.name = name if isinstance(name, str) and name else folder.name
        from .envs import PADDING, padding_for

        padding = self.config.get("padding")
        if isinstance(padding, dict):
            sizes = [padding.get(k) for k in PADDING["large"]]
            if not all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in sizes):
                raise ValueError(f"model {self.name}: 'padding' in {folder / CONFIG_FILE} must give the integer sizes "
                                 f"{', '.join(PADDING['large'])}, got {json.dumps(padding)[:120]}")
        elif padding in (None, "auto") or not isinstance(padding, str):  # a model's layout is fixed when trained
            raise ValueError(f"model {self.name}: {folder / CONFIG_FILE} must name its padded layout ('padding': "
                             f"a profile such as {', '.join(PADDING)} or a dict of sizes), got {padding!r}")
        try:
            self.padding = padding_for(padding, [])
        except ValueError as exc:
            raise ValueError(f"model {self.name}: {exc}") from None
        from fms_sim.full_shop import DECISIONS

        #: the net the model was trained on (configs before the full net existed: the paper's)
        self.decisions = self.config.get("decisions", "paper")
        if not isinstance(self.decisions, str) or self.decisions not in DECISIONS:
            raise ValueError(f"model {self.name}: unknown decisions {self.decisions!r} in its config "
                             f"(choose from {', '.join(DECISIONS)})")
        #: the observation's plan guide (None: none; :mod:`fms_dispatch.rl.envs`)
        self.guide = self.config.get("guide")
        from .envs import check_guide

        try:
            check_guide(self.guide, self.decisions)
        except ValueError as exc:
            raise ValueError(f"model {self.name}: {exc}") from None
        #: whether the model takes its plan's assignments without running its network (:func:`checked_assignments`):
        #: only with the folder's solving weights, which the card's check was made on (another weights file of the
        #: folder, such as ``guided``'s ``model.zip``, was never checked)
        self.plan_assigns = (self.guide is not None and weights.name == _solving_weights_name(folder)
                             and checked_assignments(folder))

    def __repr__(self) -> str:
        return f"ModelRef({self.name!r}, {self.weights})"


def resolve_model(spec: str) -> ModelRef:
    """A model by shipped name (``bu``), folder (``models/bu``) or weights file (``models/bu/model.zip``). A bare
    name is looked up in :func:`model_dirs` first, then as a folder here: a folder named ``guided-dagger`` in the
    working directory took the place of the default model (``ppo``) without a word. A folder solves with its
    ``best_model.zip``, else its ``model.zip``; one that lacks the file its ``metrics.json`` names as its weights
    is refused (:func:`_recorded_weights`)."""
    p = Path(spec)
    if p.is_file() and p.suffix == ".zip":
        return ModelRef(p.parent, p)
    known = None if len(p.parts) != 1 or spec.startswith(".") else next(
        (d / spec for d in model_dirs() if (d / spec).is_dir()), None)
    if known is not None:
        folder = known
    elif p.is_dir():
        folder = p
    else:
        folder = p
        if not folder.is_dir():
            names = ", ".join(SHIPPED)
            raise ModelNotFoundError(f"no model named {spec!r} (shipped models: {names}; or give a model folder or "
                                     f".zip); {_searched()}")
    recorded = _recorded_weights(folder)
    if recorded is not None and not (folder / recorded).is_file():
        raise ValueError(f"model folder {folder} has no {recorded}, the weights its {METRICS_FILE} says it solves "
                         f"with (a copy that lost it?): restore it, or name another weights file (ppo:{folder}/"
                         "model.zip)")
    for fname in ("best_model.zip", "model.zip"):
        if (folder / fname).is_file():
            return ModelRef(folder, folder / fname)
    raise ValueError(f"model folder {folder} has no best_model.zip or model.zip")


def _recorded_weights(folder: Path) -> str | None:
    """The weights file that ``folder``'s metrics say the model solves with (``training.weights``: what training
    selected and evaluated), or None where they do not say. A folder that lost its ``best_model.zip`` solved with
    ``model.zip`` without a word: for ``guided``, the PPO weights its card says it does not solve with."""
    try:
        metrics = json.loads((folder / METRICS_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    training = metrics.get("training") if isinstance(metrics, dict) else None
    weights = training.get("weights") if isinstance(training, dict) else None
    return weights if weights in ("best_model.zip", "model.zip") else None


def _solving_weights_name(folder: Path) -> str:
    """The weights file ``folder`` solves with when named as a folder (:func:`resolve_model`): the one its metrics
    record, else ``best_model.zip`` where it is there, else ``model.zip``."""
    recorded = _recorded_weights(folder)
    if recorded is not None:
        return recorded
    return "best_model.zip" if (folder / "best_model.zip").is_file() else "model.zip"


#: the key of a model card (``metrics.json``) that records the check of its plan's assignments
ASSIGNMENTS_KEY = "plan_assignments"


def checked_assignments(folder: Path) -> bool:
    """Whether ``folder``'s model card records that its network chose the plan's assignment at every one checked
    (``metrics.json``'s ``plan_assignments``: ``assignments`` > 0 and ``network_otherwise`` 0, as
    ``bench/plan_assignments.py --record`` writes it): then its runs take those assignments without running the
    network (:attr:`fms_dispatch.rl.agent.Agent.plan_assigns`). A model without that record decides every choice
    with its network: a model just trained, or one whose network was seen to choose otherwise."""
    try:
        metrics = json.loads((folder / METRICS_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    record = metrics.get(ASSIGNMENTS_KEY) if isinstance(metrics, dict) else None
    if not isinstance(record, dict):
        return False
    n, other = record.get("assignments"), record.get("network_otherwise")
    if not isinstance(n, int) or not isinstance(other, int) or isinstance(n, bool) or isinstance(other, bool):
        return False
    return n > 0 and other == 0


def default_model_name(inst: Instance) -> str:
    """The shipped model for an instance: ``guided-dagger`` (the full net with a list-schedule plan's guide,
    searched with the solver's default effort) on every shop, Bilge-Ulusoy-size ones included, where the guided
    models beat ``bu``. Chosen on generated validation shops that no model trains on and no reported figure comes
    from (``bench/validation.py``, ``bench/disrupted.py``, docs/benchmarks.md §9): it decides as ``guided`` in
    every nominal run there and is below it in a quarter of the disrupted ones, above in none. ``inst`` stays a
    parameter: the choice is per shop."""
    del inst
    return "guided-dagger"


@functools.lru_cache(maxsize=8)
def _cached_agent(weights: str, mtime: float, padding: tuple, name: str, decisions: str = "paper",
                  guide: str | None = None, plan_assigns: bool = False) -> Any:
    from .agent import Agent

    agent = Agent(weights, dict(padding), name=name, decisions=decisions, guide=guide, plan_assigns=plan_assigns)
    _settle_heap()
    return agent


_settled = False

#: whether the first model load freezes the heap (:func:`_settle_heap`). A program that holds data in reference
#: cycles when it first loads a model, and frees them later (a notebook), sets it False before: frozen objects are
#: never collected by the cyclic collector, so such data would stay in memory (decisions then pause for the
#: collector's full scans, 15-25 ms each). Objects without reference cycles are freed either way.
FREEZE_HEAP = True


def _settle_heap() -> None:
    """Once per process, after the first model load: collect, then freeze what is alive (``gc.freeze``) unless
    :data:`FREEZE_HEAP` is False. The modules, the model and the instance tables stay for the process's life;
    without this every full collection of the cyclic garbage collector scans them all (15-25 ms with the solvers
    imported), a pause that lands on whichever decision or plan search triggers it (docs/benchmarks.md §9).
    Objects created later are collected as usual; objects alive then, in reference cycles, are not."""
    global _settled
    if not _settled and FREEZE_HEAP:
        _settled = True
        gc.collect()
        gc.freeze()


def load_agent(spec: str) -> Any:
    """A loaded :class:`~fms_dispatch.rl.agent.Agent` for ``spec`` (cached per weights file). The first load
    freezes the process's heap as it is then (see :func:`_settle_heap`; :data:`FREEZE_HEAP` False: not), so that
    later full garbage collections do not pause decisions to scan the modules and the model."""
    ref = resolve_model(spec)
    return _cached_agent(str(ref.weights), ref.weights.stat().st_mtime, tuple(sorted(ref.padding.items())),
                         ref.name, ref.decisions, ref.guide, ref.plan_assigns)
