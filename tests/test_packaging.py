"""Packaging: what a pip user and a ROS user get from this tree.

- a wheel built from the tree, installed into a bare venv (no ROS 2, no maglev_msgs), runs the
  offline verbs on the bundled bags (the contract's .msg texts ship as package data);
- no console script shadows a system command (pip gets ``maglev_<node>``);
- package.xml declares what the code imports, with rosdep keys that exist.
"""
from __future__ import annotations

import ast
import json
import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from importlib import metadata
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BAGS = ROOT / "bags"

# rosdep keys for what the code imports, as listed in ros/rosdistro (rosdep/python.yaml and
# base.yaml) on 2026-11-27; ROS packages are their own keys. A module missing here fails the
# test below: find its key (or declare why it has none) before importing it.
ROSDEP_KEY = {
    "numpy": "python3-numpy", "scipy": "python3-scipy", "yaml": "python3-yaml",
    "matplotlib": "python3-matplotlib", "rosbags": "python3-rosbags-pip",
    "numba": "python3-numba", "torch": "python3-torch", "tqdm": "python3-tqdm",
    "rich": "python3-rich",
    # no key for mcap alone: the pip key mcap-ros2-support installs it (its dependency)
    "mcap": "mcap-ros2-support",
    "rclpy": "rclpy", "std_msgs": "std_msgs", "std_srvs": "std_srvs",
    "rosgraph_msgs": "rosgraph_msgs", "builtin_interfaces": "builtin_interfaces",
    "launch": "launch", "launch_ros": "launch_ros", "maglev_msgs": "maglev_msgs",
    "diagnostic_msgs": "diagnostic_msgs",
    "rcl_interfaces": "rcl_interfaces",
    "h5py": "python3-h5py",
    "sensor_msgs": "sensor_msgs", "nav_msgs": "nav_msgs",
}
# declared without an import of their own: the field types of messages the nodes use
# (sensor_msgs/Imu and nav_msgs/Odometry are made of geometry_msgs types)
MESSAGE_DEPENDENCIES = {"geometry_msgs"}
# imported only when installed (guarded import) and without a rosdep key: pip brings it
# (foxglove: foxglove-sdk, the live view's server, from requirements.txt; the node says so in one
# line when it is missing)
# npTDMS, asammdf: the import's TDMS and MDF4 readers, imported when such a file is read, with one
# line saying how to get them when missing; no rosdep key in rosdistro (2026-08), pip brings them
OPTIONAL_WITHOUT_KEY = {"threadpoolctl", "foxglove", "nptdms", "asammdf"}
# imported only by a verb that needs them (batch: Dask and Parquet) and without a rosdep key in
# ros/rosdistro (checked 2026-11-27); pip installs them with pyproject.toml's dependencies and the
# verb says so in one line when they are missing
PIP_ONLY_WITHOUT_KEY = {"dask", "distributed", "pyarrow"}
# what pip installs for the science core; the ROS side comes from requirements.txt
PIP_NAME = {"yaml": "pyyaml"}
# cloudpickle: diagnose/update --workers (maglev_ros/parallel.py), imported when asked for, with one
# line saying how to get it when missing; no rosdep key found
PIP_ONLY_WITHOUT_KEY = PIP_ONLY_WITHOUT_KEY | {"cloudpickle"}


def _third_party_imports(paths) -> set[str]:
    stdlib = set(sys.stdlib_module_names)
    found = set()
    for path in paths:
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                top = name.split(".")[0]
                if top not in stdlib and top not in ("maglev_ros", "__future__"):
                    found.add(top)
    return found


def _sources(*dirs):
    return [p for d in dirs for p in (ROOT / d).rglob("*.py")]


def test_package_xml_declares_every_import_with_a_rosdep_key():
    root = ET.parse(ROOT / "package.xml").getroot()
    declared = {e.text.strip() for tag in ("depend", "exec_depend") for e in root.iter(tag)}
    imports = _third_party_imports(_sources("maglev_ros", "launch"))
    unknown = imports - set(ROSDEP_KEY) - OPTIONAL_WITHOUT_KEY - PIP_ONLY_WITHOUT_KEY
    assert not unknown, f"no rosdep key known for {sorted(unknown)}"
    missing = {ROSDEP_KEY[m] for m in imports if m in ROSDEP_KEY} - declared
    assert not missing, f"package.xml lacks {sorted(missing)}"
    unused = declared - {ROSDEP_KEY[m] for m in imports if m in ROSDEP_KEY} - MESSAGE_DEPENDENCIES
    assert not unused, f"package.xml declares {sorted(unused)}, which nothing imports"


def test_pyproject_dependencies_cover_the_core_imports():
    import tomllib
    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    names = {d.split(";")[0].split("=")[0].split(">")[0].split("<")[0].strip().lower() for d in deps}
    core = [p for p in _sources("maglev_ros") if "nodes" not in p.relative_to(ROOT / "maglev_ros").parts]
    for mod in _third_party_imports(core):
        assert PIP_NAME.get(mod, mod).lower() in names, f"pyproject.toml lacks {mod}"


def test_no_console_script_shadows_a_system_command():
    eps = [ep for ep in metadata.entry_points(group="console_scripts")
           if ep.value.startswith("maglev_ros.")]
    assert {ep.name for ep in eps} >= {"maglev-ros", "maglev_replay", "maglev_twin", "maglev_echo"}
    assert all(ep.name.startswith("maglev") for ep in eps), [ep.name for ep in eps]
    bindir = Path(sys.executable).parent
    for name in ("echo", "replay", "summary", "twin"):
        assert not (bindir / name).exists(), name


def _run(cmd, cwd, env, timeout=600):
    res = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    return res.returncode, res.stdout + res.stderr


@pytest.fixture(scope="module")
def bare_venv(tmp_path_factory):
    """A venv made by the base interpreter, with only the wheel built from this tree installed."""
    tmp = tmp_path_factory.mktemp("wheel")
    env = {k: v for k, v in os.environ.items()
           if k not in ("PYTHONPATH", "AMENT_PREFIX_PATH", "MAGLEV_MSG_DIR", "VIRTUAL_ENV")}
    code, out = _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp / "dist"),
                      str(ROOT)], tmp, env)
    assert code == 0, out[-3000:]
    wheel = next((tmp / "dist").glob("maglev_ros-*.whl"))
    base = getattr(sys, "_base_executable", None) or shutil.which("python3")
    code, out = _run([base, "-m", "venv", str(tmp / "venv")], tmp, env)
    assert code == 0, out
    py = tmp / "venv" / "bin" / "python"
    code, out = _run([str(py), "-m", "pip", "install", "-q", "--disable-pip-version-check", str(wheel)],
                     tmp, env, timeout=900)
    assert code == 0, out[-3000:]
    return py, env, tmp


def test_wheel_runs_the_offline_verbs_without_ros(bare_venv):
    py, env, tmp = bare_venv
    exe = str(py.parent / "maglev-ros")
    code, out = _run([str(py), "-c", "import importlib.util as u; print(u.find_spec('rclpy'), "
                      "u.find_spec('maglev_msgs'))"], tmp, env)
    assert out.split() == ["None", "None"], out
    code, out = _run([exe, "info", str(BAGS / "paper_pass"), "--json"], tmp, env)
    assert code == 0, out[-2000:]
    info = json.loads(out[out.index("{"):])
    assert "/testline/vehicle/gap" in {t["topic"] for t in info["topics"]}
    code, out = _run([exe, "modes", str(BAGS / "paper_ambient"), "--json", str(tmp / "m.json")], tmp, env)
    assert code == 0, out[-2000:]
    truth = json.loads((BAGS / "paper_ambient.truth.json").read_text())
    f_true = truth["instrumented_span"]["freq_hz"][0]
    f = [m["frequency_hz"] for m in json.loads((tmp / "m.json").read_text())["modes"]]
    assert min(abs(x - f_true) for x in f) / f_true < 0.01, (f, f_true)
    code, out = _run([exe, "irregularity", str(BAGS / "paper_pass"), "--out", str(tmp / "irr.csv")],
                     tmp, env)
    assert code == 0, out[-2000:]
    assert (tmp / "irr.csv").stat().st_size > 0
    code, out = _run([exe, "simulate", "paper", "--out", str(tmp / "sim"), "--quiet",
                      "--set", "speed_mps=40", "--set", "lead_in_s=0.2", "--set", "free_decay_s=0.5"],
                     tmp, env)
    assert code == 0, out[-2000:]
    code, out = _run([exe, "info", str(tmp / "sim")], tmp, env)
    assert code == 0 and "OK" in out, out[-2000:]


def test_wheel_node_without_ros_says_how_to_get_it(bare_venv):
    py, env, tmp = bare_venv
    code, out = _run([str(py.parent / "maglev_twin")], tmp, env)
    assert code == 1
    lines = out.strip().splitlines()
    assert len(lines) == 1 and "rclpy" in lines[0] and "scripts/install" in lines[0], out
