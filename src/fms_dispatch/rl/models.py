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

Shipped models (in the repository's ``models/`` folder, or ``$FMS_MODELS_DIR``): ``bu`` (Bilge-Ulusoy, layout
2, 2 AGVs, no tools), ``large`` (large benchmark with AGVs and tools) and ``large-agv`` (AGVs only).
"""

from __future__ import annotations

import functools
import json
import os
from pathlib import Path
from typing import Any

from fms_sim.instance import Instance

__all__ = ["ModelRef", "models_dir", "resolve_model", "default_model_name", "load_config", "SHIPPED",
           "load_agent"]

SHIPPED = ("bu", "large", "large-agv")
CONFIG_FILE = "config.json"
METRICS_FILE = "metrics.json"


def models_dir() -> Path:
    """``$FMS_MODELS_DIR``, else the ``models`` folder of the source checkout, else ``./models``."""
    env = os.environ.get("FMS_MODELS_DIR")
    if env:
        return Path(env)
    repo = Path(__file__).resolve().parents[3] / "models"
    return repo if repo.is_dir() else Path("models")


def load_config(folder: str | Path) -> dict[str, Any]:
    path = Path(folder) / CONFIG_FILE
    try:
        return json.loads(path.read_text())
    except OSError:
        raise ValueError(f"model folder {folder} has no readable {CONFIG_FILE}") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path} is not valid JSON: {exc.msg} (line {exc.lineno})") from None


class ModelRef:
    """A resolved model: its folder, weights file, config and padded layout."""

    def __init__(self, folder: Path, weights: Path):
        self.folder = folder
        self.weights = weights
        self.config = load_config(folder)
        self.name = self.config.get("name") or folder.name
        from .envs import padding_for

        self.padding = padding_for(self.config["padding"], [])

    def __repr__(self) -> str:
        return f"ModelRef({self.name!r}, {self.weights})"


def resolve_model(spec: str) -> ModelRef:
    """A model by shipped name (``bu``), folder (``models/bu``) or weights file (``models/bu/model.zip``)."""
    p = Path(spec)
    if p.is_file() and p.suffix == ".zip":
        return ModelRef(p.parent, p)
    folder = p if p.is_dir() else models_dir() / spec
    if not folder.is_dir():
        names = ", ".join(SHIPPED)
        raise ValueError(f"no model named {spec!r} (shipped models: {names}; or give a model folder or .zip)")
    for fname in ("best_model.zip", "model.zip"):
        if (folder / fname).is_file():
            return ModelRef(folder, folder / fname)
    raise ValueError(f"model folder {folder} has no best_model.zip or model.zip")


def default_model_name(inst: Instance) -> str:
    """The shipped model for an instance: tools -> ``large``; small 2-AGV shops -> ``bu``; else ``large-agv``."""
    if inst.has_tools:
        return "large"
    if inst.n_jobs <= 8 and inst.n_machines <= 4 and (not inst.has_agvs or inst.n_agvs <= 2):
        return "bu"
    return "large-agv"


@functools.lru_cache(maxsize=8)
def _cached_agent(weights: str, mtime: float, padding: tuple, name: str) -> Any:
    from .agent import Agent

    return Agent(weights, dict(padding), name=name)


def load_agent(spec: str) -> Any:
    """A loaded :class:`~fms_dispatch.rl.agent.Agent` for ``spec`` (cached per weights file)."""
    ref = resolve_model(spec)
    return _cached_agent(str(ref.weights), ref.weights.stat().st_mtime, tuple(sorted(ref.padding.items())),
                         ref.name)
