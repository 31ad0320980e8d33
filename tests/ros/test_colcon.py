"""The ROS 2 workspace as a ROS user builds it: the repository copied into ``ws/src``, ``colcon build``
(plain and ``--symlink-install``), ``source install/setup.bash``; ros2run's lookup (``ament_index_python``)
finds ``fms_sim`` and ``fms_dispatch`` as colcon packages, and the three nodes start from the paths found and
run EX12 with the shipped PPO model, which the plain build installed in ``share/fms_dispatch/models``."""

from __future__ import annotations

import importlib.metadata
import os
import shutil
import sqlite3
import subprocess
import sys
import time
from pathlib import Path
from unittest import mock

import pytest

pytest.importorskip("rclpy")
ament = pytest.importorskip("ament_index_python")
pytest.importorskip("colcon_core")

from fms_sim import validate  # noqa: E402
from fms_sim.benchmarks import builtin  # noqa: E402
from fms_sim.recorder_store import gantt_path  # noqa: E402
from fms_sim.schedule import Schedule  # noqa: E402

from .conftest import RUN_S, STARTUP_S, NodeProcs, ros_distro, wait_file  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
PACKAGES = {"fms_sim": {"shop", "recorder"}, "fms_dispatch": {"agent"}}
MODEL_FILES = {"config.json", "metrics.json", "best_model.zip", "best_model.actor.npz"}


def test_rclpy_is_jazzys() -> None:
    """The ros extra installs ROS 2 Jazzy (the LTS; Kilted's rclpy was 9.x)."""
    from std_msgs.msg import String

    assert ros_distro() == "jazzy" and String(data="x").data == "x"
    try:
        version = importlib.metadata.version("ros-rclpy")
    except importlib.metadata.PackageNotFoundError:   # a sourced ROS installation: $ROS_DISTRO said jazzy
        return
    assert version.startswith("7.1.")


def colcon(ws: Path, *args: str) -> str:
    """Run the environment's colcon in ``ws`` (no underlay, its own COLCON_HOME); returns its output."""
    exe = Path(sys.executable).with_name("colcon")
    env = {k: v for k, v in os.environ.items()
           if k not in ("AMENT_PREFIX_PATH", "COLCON_PREFIX_PATH", "CMAKE_PREFIX_PATH", "PYTHONPATH")}
    env["COLCON_HOME"] = str(ws / ".colcon")
    res = subprocess.run([str(exe), *args], cwd=ws, env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr
    return res.stdout + res.stderr


def sourced(ws: Path, install: str, env: dict[str, str]) -> dict[str, str]:
    """The environment after ``source <install>/setup.bash`` in ``ws``."""
    res = subprocess.run(["bash", "-c", f'source "{install}/setup.bash" && env -0'], cwd=ws, env=env,
                         capture_output=True, timeout=60)
    assert res.returncode == 0, res.stderr
    return dict(line.split("=", 1) for line in res.stdout.decode().split("\0") if "=" in line)


@pytest.fixture(scope="module")
def ws(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A workspace with the repository (its tracked layout: ros/, src/, models/ and the top-level files) in
    ``src/fms``, built plain (``install``) and with ``--symlink-install`` (``install-sym``)."""
    ws = tmp_path_factory.mktemp("ws")
    src = ws / "src" / "fms"
    ignore = shutil.ignore_patterns("__pycache__", "*.egg-info", "*.pyc")
    for name in ("ros", "src", "models"):
        shutil.copytree(REPO / name, src / name, symlinks=True, ignore=ignore)
    for name in ("setup.cfg", "pyproject.toml", "README.md"):
        shutil.copy2(REPO / name, src / name)
    listed = colcon(ws, "list", "--names-only").split()
    assert sorted(listed) == sorted(PACKAGES)
    # one package alone, as --packages-select does it (fms_dispatch depends on it, not the other way round)
    out = colcon(ws, "build", "--packages-select", "fms_sim")
    assert (ws / "install" / "fms_sim").is_dir() and not (ws / "install" / "fms_dispatch").exists()
    out += colcon(ws, "build")
    out += colcon(ws, "build", "--symlink-install", "--build-base", "build-sym", "--install-base", "install-sym")
    assert "doesn't explicitly install" not in out   # each package installs its own marker and package.xml
    return ws


@pytest.mark.parametrize("install", ["install", "install-sym"])
def test_ament_index_finds_the_colcon_packages(ws: Path, install: str, ros_env: dict[str, str],
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    env = sourced(ws, install, ros_env)
    monkeypatch.setenv("AMENT_PREFIX_PATH", env["AMENT_PREFIX_PATH"])
    for pkg, exes in PACKAGES.items():
        prefix = Path(ament.get_package_prefix(pkg))          # ros2run's lookup
        assert prefix == ws / install / pkg
        assert (prefix / "share" / "ament_index" / "resource_index" / "packages" / pkg).is_file()
        assert (prefix / "share" / pkg / "package.xml").is_file()
        lib = prefix / "lib" / pkg                            # what ros2run lists: executables in lib/<pkg>
        assert {p.name for p in lib.iterdir() if p.is_file() and os.access(p, os.X_OK)} == exes
    models = ws / install / "fms_dispatch" / "share" / "fms_dispatch" / "models"
    for name in ("bu", "large", "large-agv", "guided", "guided-dagger"):
        assert {p.name for p in (models / name).iterdir()} == MODEL_FILES


def node_cmd(ws: Path, install: str, pkg: str, exe: str, env: dict[str, str], **params: object) -> list[str]:
    """The command ``ros2 run pkg exe --ros-args -p k:=v ...`` starts: the executable the ament index gives."""
    with mock.patch.dict(os.environ, {"AMENT_PREFIX_PATH": env["AMENT_PREFIX_PATH"]}):
        path = Path(ament.get_package_prefix(pkg)) / "lib" / pkg / exe
    assert path.is_relative_to(ws / install)
    cmd = [str(path), "--ros-args"]
    for k, v in params.items():
        cmd += ["-p", f"{k}:={str(v).lower() if isinstance(v, bool) else v}"]
    return cmd


def test_nodes_from_the_plain_build_run_ex12_with_the_installed_model(ws: Path, ros_env: dict[str, str],
                                                                      tmp_path: Path) -> None:
    env = sourced(ws, "install", {k: v for k, v in ros_env.items() if k != "FMS_MODELS_DIR"})
    where = subprocess.run([sys.executable, "-c", "import fms_sim, fms_dispatch; print(fms_sim.__file__); "
                            "print(fms_dispatch.__file__)"], env=env, capture_output=True, text=True, timeout=60)
    sim_file, dispatch_file = where.stdout.split()
    assert Path(sim_file).is_relative_to(ws / "install" / "fms_sim")          # not the environment's own fms
    assert Path(dispatch_file).is_relative_to(ws / "install" / "fms_dispatch")
    out, db = tmp_path / "EX12.schedule.json", tmp_path / "rec.sqlite"
    procs = NodeProcs(env, tmp_path)
    try:
        procs.start("recorder", node_cmd(ws, "install", "fms_sim", "recorder", env, db=db))
        # the default model (guided-dagger) decides through the full net
        procs.start("shop", node_cmd(ws, "install", "fms_sim", "shop", env, instance="EX12", run_id="colcon",
                                     history=True, features=False, schedule_out=out, decisions="full"))
        procs.start("agent", node_cmd(ws, "install", "fms_dispatch", "agent", env, solver="ppo",
                                      instance="EX12"))
        wait_file(out, STARTUP_S + RUN_S, procs)
        wait_file(gantt_path(tmp_path, "colcon"), RUN_S, procs)
        model = ws / "install" / "fms_dispatch" / "share" / "fms_dispatch" / "models" / "guided-dagger" / "best_model.zip"
        assert f"deciding with ppo:guided-dagger (model {model})" in procs.log("agent")
        codes = procs.stop_all()
    finally:
        procs.stop_all()
    assert codes == {"recorder": 0, "shop": 0, "agent": 0}, procs.report(codes)
    from fms_dispatch.rl import ppo_solver

    sched, inst = Schedule.load(out), builtin("EX12")
    assert validate(inst, sched) == [] and sched.meta["solver"] == "ppo:guided-dagger"
    assert sched.makespan == ppo_solver("ppo")(inst).makespan
    (stored,) = sqlite3.connect(db).execute("SELECT makespan FROM schedules WHERE run_id = 'colcon'").fetchone()
    assert stored == sched.makespan


def test_symlink_install_finds_the_models_of_the_source(ws: Path, ros_env: dict[str, str], tmp_path: Path) -> None:
    """With --symlink-install the Python packages are the sources', so the models come from the sources'
    models/ (an edit there is seen without a rebuild)."""
    env = sourced(ws, "install-sym", {k: v for k, v in ros_env.items() if k != "FMS_MODELS_DIR"})
    procs = NodeProcs(env, tmp_path)
    try:
        agent = procs.start("agent", node_cmd(ws, "install-sym", "fms_dispatch", "agent", env, solver="ppo",
                                              instance="EX12"))
        model = ws / "src" / "fms" / "models" / "guided-dagger" / "best_model.zip"
        line = f"deciding with ppo:guided-dagger (model {model})"
        deadline = time.monotonic() + STARTUP_S
        while line not in procs.log("agent") and time.monotonic() < deadline and agent.poll() is None:
            time.sleep(0.1)
        assert line in procs.log("agent"), procs.log("agent")
    finally:
        codes = procs.stop_all()
    assert codes == {"agent": 0}, procs.report(codes)
