"""``ros2 run`` support and the shipped models in a non-editable install: pip puts the ament index markers, the
node wrappers and the models (``share/fms_dispatch/models``) under its prefix; ros2run's lookup
(``ament_index_python``) finds the wrappers, a node starts from the found path, ``fms up --solver best`` runs
the installed PPO model, and without the models every PPO solver is an error naming the places searched."""

from __future__ import annotations

import importlib.metadata
import json
import os
import re
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

pytest.importorskip("rclpy")
ament = pytest.importorskip("ament_index_python")

from .conftest import STARTUP_S, NodeProcs, Observer  # noqa: E402

REPO = Path(__file__).resolve().parents[2]


def _copy_sources(dest: Path) -> Path:
    """The files a build needs, copied so that the build never writes into the working tree."""
    src = dest / "fms-src"
    src.mkdir()
    for name in ("setup.cfg", "pyproject.toml", "README.md"):
        shutil.copy2(REPO / name, src / name)
    ignore = shutil.ignore_patterns("__pycache__", "*.egg-info", "*.pyc")
    for name in ("src", "resource", "models"):
        shutil.copytree(REPO / name, src / name, ignore=ignore)
    return src


@pytest.fixture(scope="module")
def prefix(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``pip install --prefix`` of the project (no network, no build isolation, no dependencies).

    ``--ignore-installed`` matters: without it pip would uninstall the editable ``fms`` of the running
    environment while installing the copy into the prefix.
    """
    root = tmp_path_factory.mktemp("install")
    src = _copy_sources(root)
    before = _installed_fms()
    res = subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--no-build-isolation", "--no-index",
                          "--ignore-installed", "--no-warn-script-location", "--disable-pip-version-check", "-q",
                          "--prefix", str(root / "prefix"), str(src)],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert _installed_fms() == before                 # the environment's own install is untouched
    return root / "prefix"


def _installed_fms() -> str | None:
    try:
        dist = importlib.metadata.distribution("fms")
    except importlib.metadata.PackageNotFoundError:
        return None
    return f"{dist.locate_file('')} {dist.version} {sorted(str(f) for f in dist.files or [])[:5]}"


def _site_packages(prefix: Path) -> Path:
    rel = Path(sysconfig.get_path("purelib")).relative_to(sys.prefix)
    return prefix / rel


def test_ament_index_finds_the_packages_and_executables(prefix: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(prefix))
    for pkg, exes in (("fms_sim", {"shop", "recorder"}), ("fms_dispatch", {"agent"})):
        found = Path(ament.get_package_prefix(pkg))
        assert found == prefix
        marker = prefix / "share" / "ament_index" / "resource_index" / "packages" / pkg
        assert marker.is_file() and marker.read_bytes() == b""
        lib = found / "lib" / pkg           # what ros2run lists: executable files in <prefix>/lib/<pkg>
        assert {p.name for p in lib.iterdir() if p.is_file() and os.access(p, os.X_OK)} == exes
        for exe in exes:
            text = (lib / exe).read_text()
            assert text.startswith("#!/bin/sh\n") and str(prefix) not in text and "-m fms_" in text
    for script in ("fms", "fms-shop", "fms-agent", "fms-recorder"):
        assert (prefix / "bin" / script).is_file()
    models = prefix / "share" / "fms_dispatch" / "models"   # what solving needs; model.zip stays in the repo
    for name in ("bu", "large", "large-agv", "guided", "guided-dagger"):
        assert {p.name for p in (models / name).iterdir()} == {"config.json", "metrics.json", "best_model.zip",
                                                               "best_model.actor.npz"}
    with pytest.raises(ament.PackageNotFoundError):
        ament.get_package_prefix("fms_nothing")


def test_node_starts_from_the_found_path(prefix: Path, ros_env: dict[str, str], monkeypatch: pytest.MonkeyPatch,
                                         tmp_path: Path, observer: Observer) -> None:
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(prefix))
    shop = Path(ament.get_package_prefix("fms_sim")) / "lib" / "fms_sim" / "shop"
    agent = Path(ament.get_package_prefix("fms_dispatch")) / "lib" / "fms_dispatch" / "agent"
    # the prefix is not a venv: the wrapper runs FMS_PYTHON, which finds the installed copy through PYTHONPATH
    env = dict(ros_env, FMS_PYTHON=sys.executable, PYTHONPATH=str(_site_packages(prefix)))
    where = subprocess.run([sys.executable, "-c", "import fms_sim.shop_node as m; print(m.__file__)"], env=env,
                           capture_output=True, text=True, timeout=60)
    assert where.stdout.strip().startswith(str(prefix)), where
    procs = NodeProcs(env, tmp_path)
    try:
        proc = procs.start("shop", [str(shop), "--ros-args", "-p", "instance:=EX12", "-p", "run_id:=installed",
                                    "-p", "history:=true"])  # the PPO agent replays the history
        state = observer.wait_for(lambda g: next((s for s in g["state"] if s["run_id"] == "installed"), None),
                                  STARTUP_S, "the installed shop's first state")
        assert state["seq"] == 0 and state["instance"] == "EX12" and state["actions"][0] == "job:0"
        # the agent finds the installed model (the prefix's share/fms_dispatch/models, not the repository's)
        ppo = procs.start("agent", [str(agent), "--ros-args", "-p", "solver:=ppo:bu", "-p", "instance:=EX12"])
        model = prefix / "share" / "fms_dispatch" / "models" / "bu" / "best_model.zip"
        observer.wait_for(lambda g: [s for s in g["state"] if s["run_id"] == "installed" and s["seq"] >= 3],
                          STARTUP_S, "the installed agent's commands")
        assert f"deciding with ppo:bu (model {model})" in procs.log("agent")
        codes = {"agent": procs.stop(ppo), "shop": procs.stop(proc)}
        assert codes == {"agent": 0, "shop": 0}, procs.report(codes)
    finally:
        procs.stop_all()


def _installed_env(prefix: Path, ros_env: dict[str, str]) -> dict[str, str]:
    """Python with the prefix's copy of fms first on its path, no model folder override."""
    env = {k: v for k, v in ros_env.items() if k not in ("FMS_MODELS_DIR", "AMENT_PREFIX_PATH")}
    return dict(env, FMS_PYTHON=sys.executable, PYTHONPATH=str(_site_packages(prefix)))


def test_fms_up_best_runs_the_installed_model(prefix: Path, ros_env: dict[str, str], tmp_path: Path) -> None:
    """The issue's case: after a non-editable install ``fms up EX62 --solver best`` runs the shipped PPO model
    (the default, guided-dagger), not silently a rule pair or the list schedule (110)."""
    out = tmp_path / "EX62.json"
    res = subprocess.run([sys.executable, "-m", "fms_dispatch.up", "EX62", "--solver", "best", "--out", str(out),
                          "--db", str(tmp_path / "fms.sqlite"), "--log-dir", str(tmp_path / "logs")],
                         env=_installed_env(prefix, ros_env), capture_output=True, text=True, timeout=180)
    assert res.returncode == 0, res.stderr
    found = re.search(r"best on EX62: (ppo:guided\S*) \(makespan (\d+) in simulation; list schedule "
                      r"plan:list: 110\)", res.stderr)
    assert found and int(found[2]) < 110, res.stderr
    assert str(prefix) in (tmp_path / "logs" / "agent.log").read_text()    # the installed model was used
    assert json.loads(out.read_text())["makespan"] == int(found[2])


def test_missing_models_are_an_error_naming_the_places(prefix: Path, ros_env: dict[str, str]) -> None:
    models = prefix / "share" / "fms_dispatch" / "models"
    hidden = models.with_name("models.hidden")
    models.rename(hidden)
    try:
        env = _installed_env(prefix, ros_env)
        best = subprocess.run([sys.executable, "-m", "fms_dispatch.up", "EX12", "--solver", "best"], env=env,
                              capture_output=True, text=True, timeout=120)
        agent = prefix / "lib" / "fms_dispatch" / "agent"
        ppo = subprocess.run([str(agent), "--ros-args", "-p", "solver:=ppo", "-p", "instance:=EX12"], env=env,
                             capture_output=True, text=True, timeout=60)
    finally:
        hidden.rename(models)
    assert best.returncode == 2 and best.stderr.startswith("fms up: error: --solver best needs the shipped PPO models")
    assert ppo.returncode == 2 and "fms-agent: error: solver 'ppo:guided-dagger': no model named 'guided-dagger'" in ppo.stderr
    for res in (best, ppo):
        assert f"searched {models}" in res.stderr and str(Path(sys.prefix, "share", "fms_dispatch", "models")) \
            in res.stderr
        assert res.stderr.count("\n") == 1                                  # one line
