"""Where models are looked up (fms_dispatch.rl.models.model_dirs): one list of places for fms solve, fms up and
the agent node; a model found nowhere is an error naming every place searched. The installed cases (pip
prefix, colcon install space) run in tests/ros/test_install.py and test_colcon.py."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from fms_dispatch.rl.models import SHARE_SUBDIR, ModelNotFoundError, model_dirs, models_dir, resolve_model
from fms_dispatch.up import UpError, best_rule, best_solver
from fms_sim.benchmarks import builtin

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(autouse=True)
def _no_override(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("FMS_MODELS_DIR", raising=False)
    monkeypatch.delenv("AMENT_PREFIX_PATH", raising=False)


def test_a_checkout_uses_its_models_folder() -> None:
    assert model_dirs()[0] == REPO / "models" == models_dir()
    assert resolve_model("bu").folder == REPO / "models" / "bu"


def test_a_folder_here_named_like_a_model_does_not_replace_it(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # a folder guided-dagger in the working directory took the place of the default model: `ppo` ran another
    # model's weights (or failed for want of best_model.zip); a path names the folder here
    shutil.copytree(REPO / "models" / "full", tmp_path / "guided-dagger")
    (tmp_path / "mine").mkdir()
    for name in ("best_model.zip", "config.json"):
        shutil.copy(REPO / "models" / "bu" / name, tmp_path / "mine" / name)
    monkeypatch.chdir(tmp_path)
    assert resolve_model("guided-dagger").folder == REPO / "models" / "guided-dagger"
    assert resolve_model("./guided-dagger").folder == Path("./guided-dagger")
    assert resolve_model(str(tmp_path / "guided-dagger")).folder == tmp_path / "guided-dagger"
    assert resolve_model("mine").folder == Path("mine")  # a name no search place holds: the folder here


def test_ament_prefixes_are_searched(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    shutil.copytree(REPO / "models" / "bu", tmp_path / SHARE_SUBDIR / "mine")
    with pytest.raises(ModelNotFoundError):
        resolve_model("mine")
    monkeypatch.setenv("AMENT_PREFIX_PATH", f"{tmp_path / 'other'}:{tmp_path}")
    ref = resolve_model("mine")
    assert ref.folder == tmp_path / SHARE_SUBDIR / "mine" and ref.weights.name == "best_model.zip"
    assert model_dirs() == [REPO / "models", tmp_path / SHARE_SUBDIR]     # only the places that exist


def test_a_missing_model_names_every_place_searched(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(tmp_path / "ros"))
    with pytest.raises(ModelNotFoundError) as err:
        resolve_model("nope")
    text = str(err.value)
    assert text.startswith("no model named 'nope' (shipped models: bu, large, large-agv")
    for place in (REPO / "models", tmp_path / "ros" / SHARE_SUBDIR):
        assert str(place) in text
    assert "\n" not in text


def test_fms_models_dir_replaces_the_search(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("FMS_MODELS_DIR", str(tmp_path))
    assert model_dirs() == [tmp_path]
    with pytest.raises(ModelNotFoundError, match=f"searched {tmp_path} "):
        resolve_model("bu")
    with pytest.raises(ModelNotFoundError, match="the shipped models .* are not installed"):
        models_dir()
    shutil.copytree(REPO / "models" / "bu", tmp_path / "bu")
    assert resolve_model("bu").folder == tmp_path / "bu"


def test_best_refuses_to_fall_back_when_the_models_are_missing(tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    inst = builtin("EX12")
    name, span, _ = best_solver(inst)
    assert span <= best_rule(inst)[1] and (name.startswith("ppo:guided") or name == best_rule(inst)[0])
    monkeypatch.setenv("FMS_MODELS_DIR", str(tmp_path))
    with pytest.raises(UpError, match=f"--solver best needs the shipped PPO models: no model named 'guided-dagger'.*{tmp_path}"):
        best_solver(inst)


@pytest.mark.parametrize("config, needle", [
    ([1, 2], "must hold a JSON object (the training config), got list"),
    ({"decisions": "full"}, "must name its padded layout"),
    ({"decisions": "full", "padding": 5}, "must name its padded layout"),
    ({"decisions": "full", "padding": {"max_jobs": 10}}, "'padding' in .* must give the integer sizes"),
    ({"decisions": ["full"], "padding": "large"}, "unknown decisions"),
])
def test_a_broken_model_config_is_named(tmp_path: Path, config: object, needle: str) -> None:
    # a list was an AttributeError, a missing or partial padding a KeyError, and fms solve printed a traceback
    import json
    import re

    folder = tmp_path / "broken"
    folder.mkdir()
    shutil.copy(resolve_model("full").weights, folder / "best_model.zip")
    (folder / "config.json").write_text(json.dumps(config))
    with pytest.raises(ValueError, match=needle if "*" in needle else re.escape(needle)):
        resolve_model(str(folder))


@pytest.mark.parametrize("content, needle", [
    (b"garbage\n", "the file wasn't a zip-file"),
    (b"PK\x03\x04cut short", "the file wasn't a zip-file"),
    (None, "No data found in the saved file"),  # a zip, but not a model's
])
def test_broken_weights_are_named_as_a_model_error(tmp_path: Path, content: bytes | None, needle: str) -> None:
    # sb3's own message ("Error: the file ... wasn't a zip-file") escaped as a bare ValueError of the library
    import zipfile

    from fms_dispatch.cli import main
    from fms_dispatch.rl.agent import load_torch_policy

    folder = tmp_path / "broken"
    folder.mkdir()
    shutil.copy(resolve_model("guided-dagger").folder / "config.json", folder / "config.json")
    weights = folder / "best_model.zip"
    if content is None:
        with zipfile.ZipFile(weights, "w") as z:
            z.writestr("notes.txt", "hello")
    else:
        weights.write_bytes(content)
    with pytest.raises(ValueError, match=f"the weights {weights} are not a readable MaskablePPO model") as info:
        load_torch_policy(weights)
    assert needle in str(info.value)
    assert main(["solve", "EX12", "--solver", f"ppo:{folder}", "-q"]) == 2


_FREEZE_SCRIPT = """
import gc, sys, weakref
from fms_dispatch.rl import models
from fms_dispatch.solvers import solve
from fms_sim.benchmarks import builtin
models.FREEZE_HEAP = sys.argv[1] == "1"
class Node: pass
data = Node(); data.me = data  # a reference cycle alive at the first model load
alive = weakref.ref(data)
solve(builtin("EX12"), "ppo:bu")
del data
gc.collect()
print("kept" if alive() is not None else "freed")
"""


@pytest.mark.parametrize("freeze, outcome", [("1", "kept"), ("0", "freed")])
def test_a_program_can_keep_the_first_model_load_from_freezing_its_heap(freeze, outcome):
    # the first load freezes the heap (decisions do not pause for the collector's scans): data alive then in
    # reference cycles stays in memory; FREEZE_HEAP = False (a notebook that frees such data later) does not freeze
    import subprocess
    import sys

    res = subprocess.run([sys.executable, "-c", _FREEZE_SCRIPT, freeze], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == outcome


def test_a_model_folder_that_lost_its_solving_weights_is_refused(tmp_path):
    """A copy of a model folder without its best_model.zip solved with model.zip without a word (for guided, the
    PPO weights its card says it does not solve with). Its metrics.json records the weights that training chose."""
    folder = tmp_path / "guided"
    shutil.copytree(resolve_model("guided").folder, folder)
    assert resolve_model(str(folder)).weights == folder / "best_model.zip"
    (folder / "best_model.zip").unlink()
    with pytest.raises(ValueError, match=f"model folder {folder} has no best_model.zip, the weights its metrics.json "
                                         "says it solves with"):
        resolve_model(str(folder))
    assert resolve_model(str(folder / "model.zip")).weights == folder / "model.zip"  # named: taken as asked


def test_a_model_takes_its_plans_assignments_only_where_its_card_records_the_check(tmp_path):
    """A guided model's runs take its plan's assignments without its network only where its metrics.json records
    assignments checked and none chosen otherwise (bench/plan_assignments.py --record); a card without that record,
    one that records the network choosing otherwise, a malformed record, or a model without a guide: the network
    decides."""
    import json

    from fms_dispatch.rl.models import ASSIGNMENTS_KEY, checked_assignments, load_agent

    for name in ("guided-dagger", "guided", "guided-ppo"):  # the shipped guided models were checked
        assert resolve_model(name).plan_assigns and load_agent(name).plan_assigns
    assert not resolve_model("full").plan_assigns and not load_agent("full").plan_assigns
    folder = tmp_path / "mine"
    src = resolve_model("guided-dagger").folder
    folder.mkdir()
    for f in ("config.json", "best_model.zip", "best_model.actor.npz"):
        shutil.copy(src / f, folder / f)
    card = json.loads((src / "metrics.json").read_text())
    card.pop(ASSIGNMENTS_KEY, None)
    for record, taken in ((None, False), ({"assignments": 5, "network_otherwise": 0}, True),
                          ({"assignments": 5, "network_otherwise": 1}, False),
                          ({"assignments": 0, "network_otherwise": 0}, False),
                          ({"assignments": True, "network_otherwise": 0}, False),
                          ({"assignments": "5", "network_otherwise": 0}, False), ([], False)):
        (folder / "metrics.json").write_text(json.dumps({**card, **({} if record is None
                                                                   else {ASSIGNMENTS_KEY: record})}))
        assert checked_assignments(folder) is taken and resolve_model(str(folder)).plan_assigns is taken
    (folder / "metrics.json").write_text("{not json")
    assert not checked_assignments(folder)
    (folder / "metrics.json").unlink()
    assert not checked_assignments(folder) and not resolve_model(str(folder)).plan_assigns


def test_only_the_weights_the_card_checked_take_the_plans_assignments():
    """The card's check (bench/plan_assignments.py --record) was made on the folder's solving weights: another
    weights file of the same folder (guided's model.zip, its PPO weights, or warm_start.zip) was never checked and
    decides every choice with its network; the solving weights named as a file still take the assignments."""
    from fms_dispatch.rl.models import load_agent

    folder = resolve_model("guided").folder
    assert resolve_model(str(folder / "best_model.zip")).plan_assigns
    for other in ("model.zip", "warm_start.zip"):
        assert (folder / other).is_file()
        assert not resolve_model(str(folder / other)).plan_assigns
        assert not load_agent(str(folder / other)).plan_assigns
