"""Packaging facts that need no build: the ROS 2 extra is Jazzy, the colcon packages under ``ros/`` declare
every dependency their code imports, agree with the pip project on the version, and pip and colcon install
the same shipped models. (Building and running them: tests/ros/test_colcon.py and test_install.py.)"""

from __future__ import annotations

import ast
import configparser
import re
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from fms_dispatch.rl.models import SHIPPED

REPO = Path(__file__).resolve().parents[1]
ROS = REPO / "ros"
#: colcon package -> the Python packages it installs (symbolic links to src/)
COLCON_PACKAGES = {"fms_sim": ("fms_sim", "fms_msgs_json"), "fms_dispatch": ("fms_dispatch",)}
#: third-party module -> the package.xml key that provides it (rosdep: python3-X from Debian, python3-X-pip)
KEYS = {"numpy": "python3-numpy", "gymnasium": "python3-gymnasium-pip", "matplotlib": "python3-matplotlib",
        "ortools": "python3-ortools-pip", "rclpy": "rclpy", "std_msgs": "std_msgs",
        "rcl_interfaces": "rcl_interfaces"}
#: modules of the pip extra fms[rl] (training, the torch policy): optional, not in package.xml
OPTIONAL = {"torch", "stable_baselines3", "sb3_contrib", "tqdm", "tensorboard", "rich"}


def config(path: Path) -> configparser.ConfigParser:
    cfg = configparser.ConfigParser(interpolation=None)
    cfg.read(path)
    return cfg


def requirement_names(text: str) -> list[str]:
    return [re.split(r"[\[<>=!~ ;]", line.strip())[0].lower() for line in text.splitlines() if line.strip()]


def imported_modules(folder: Path) -> set[str]:
    """Top-level names of the absolute imports in every .py file below ``folder``."""
    mods: set[str] = set()
    for f in folder.rglob("*.py"):
        for node in ast.walk(ast.parse(f.read_text(), str(f))):
            if isinstance(node, ast.Import):
                mods |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                mods.add(node.module.split(".")[0])
    return mods


def test_the_ros_extra_is_jazzy() -> None:
    extras = config(REPO / "setup.cfg")["options.extras_require"]
    ros = requirement_names(extras["ros"])
    assert ros == ["ros-jazzy-rclpy", "ros-jazzy-common-interfaces", "ros-jazzy-ament-index-python"]
    assert "[fastrtps]" in extras["ros"]                      # without it `import rclpy` fails
    assert "colcon-common-extensions" in requirement_names(extras["dev"])


def test_the_repository_root_is_no_colcon_package() -> None:
    """colcon stops crawling at a package: the root must not be one, or it would hide ros/fms_sim and
    ros/fms_dispatch (and it was one package, ``fms``, that no ``<exec_depend>`` could name)."""
    assert not (REPO / "package.xml").exists() and not (REPO / "setup.py").exists()
    assert sorted(p.parent.name for p in ROS.glob("*/package.xml")) == sorted(COLCON_PACKAGES)


@pytest.mark.parametrize("pkg", sorted(COLCON_PACKAGES))
def test_colcon_package_is_complete(pkg: str) -> None:
    root = ROS / pkg
    xml = ET.parse(root / "package.xml").getroot()
    assert xml.get("format") == "3" and xml.findtext("name") == pkg
    assert xml.findtext("export/build_type") == "ament_python"
    cfg = config(root / "setup.cfg")
    version = config(REPO / "setup.cfg")["metadata"]["version"]
    assert xml.findtext("version") == cfg["metadata"]["version"] == version
    assert cfg["metadata"]["name"] == pkg
    assert (root / "setup.py").read_text().startswith("from setuptools import setup\n\nsetup()")
    # its own marker and manifest (colcon warns, and will stop installing them itself, otherwise)
    data = {k: v.split() for k, v in cfg["options.data_files"].items()}
    assert data["share/ament_index/resource_index/packages"] == [f"resource/{pkg}"]
    assert (root / "resource" / pkg).read_bytes() == b""
    assert data[f"share/{pkg}"] == ["package.xml"]
    assert cfg["install"]["install_scripts"] == cfg["develop"]["script_dir"] == f"$base/lib/{pkg}"
    # its Python packages are the repository's sources, not copies
    for py in COLCON_PACKAGES[pkg]:
        assert (root / py).is_symlink() and (root / py).resolve() == REPO / "src" / py
    # every dependency its code imports is declared
    deps = {e.text for e in xml.iter() if e.tag in ("depend", "exec_depend")}
    mods = set().union(*(imported_modules(REPO / "src" / py) for py in COLCON_PACKAGES[pkg]))
    third_party = mods - set(sys.stdlib_module_names) - {"__future__"} - set(COLCON_PACKAGES[pkg]) - OPTIONAL
    workspace = {m for m in third_party if m in {p for ps in COLCON_PACKAGES.values() for p in ps}}
    for mod in workspace:                                     # another colcon package of this workspace
        assert next(k for k, v in COLCON_PACKAGES.items() if mod in v) in deps, mod
    unknown = third_party - workspace - set(KEYS)
    assert not unknown, f"{pkg} imports {unknown}: add them to KEYS and to its package.xml"
    assert {KEYS[m] for m in third_party - workspace} <= deps


def test_package_xml_covers_the_pip_requirements() -> None:
    """Every install_requires of the pip project is declared by the colcon package(s) that import it."""
    required = requirement_names(config(REPO / "setup.cfg")["options"]["install_requires"])
    declared = set()
    for pkg in COLCON_PACKAGES:
        declared |= {e.text for e in ET.parse(ROS / pkg / "package.xml").getroot().iter("exec_depend")}
    assert {KEYS[r] for r in required} <= declared


def test_pip_and_colcon_install_the_same_shipped_models() -> None:
    pip_data = config(REPO / "setup.cfg")["options.data_files"]
    colcon_data = config(ROS / "fms_dispatch" / "setup.cfg")["options.data_files"]
    assert (ROS / "fms_dispatch" / "models").resolve() == REPO / "models"
    for data in (pip_data, colcon_data):
        shipped = {k.rsplit("/", 1)[1]: v for k, v in data.items() if k.startswith("share/fms_dispatch/models/")}
        assert set(shipped) == set(SHIPPED)
        for name, patterns in shipped.items():
            assert patterns.replace(",", " ").split() == [f"models/{name}/*.json", f"models/{name}/best_model.*"]
    for name in SHIPPED:   # what the patterns take: the files solving needs, not model.zip (resuming training)
        taken = {p.name for p in (REPO / "models" / name).glob("*.json")} | \
            {p.name for p in (REPO / "models" / name).glob("best_model.*")}
        assert taken == {"config.json", "metrics.json", "best_model.zip", "best_model.actor.npz"}
