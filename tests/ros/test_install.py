"""``ros2 run`` support: a non-editable install puts the ament index markers and the node wrappers under its
prefix; ros2run's lookup (``ament_index_python``) finds them and a node starts from the found path."""

from __future__ import annotations

import importlib.metadata
import os
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
    for name in ("setup.cfg", "pyproject.toml", "README.md", "package.xml"):
        shutil.copy2(REPO / name, src / name)
    ignore = shutil.ignore_patterns("__pycache__", "*.egg-info", "*.pyc")
    shutil.copytree(REPO / "src", src / "src", ignore=ignore)
    shutil.copytree(REPO / "resource", src / "resource", ignore=ignore)
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
    res = subprocess.run([str(agent), "--ros-args", "-p", "solver:=ppo"], env=env, capture_output=True, text=True,
                         timeout=60)
    assert res.returncode == 2 and "fms-agent: error: solver 'ppo' is not available" in res.stderr
    procs = NodeProcs(env, tmp_path)
    try:
        proc = procs.start("shop", [str(shop), "--ros-args", "-p", "instance:=EX12", "-p", "run_id:=installed"])
        state = observer.wait_for(lambda g: next((s for s in g["state"] if s["run_id"] == "installed"), None),
                                  STARTUP_S, "the installed shop's first state")
        assert state["seq"] == 0 and state["instance"] == "EX12" and state["actions"][0] == "job:0"
        assert procs.stop(proc) == 0
    finally:
        procs.stop_all()
