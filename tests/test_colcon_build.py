"""The tree builds as a ROS 2 workspace with colcon (msg_defs as maglev_msgs, top level as maglev_ros)."""
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.skipif(shutil.which("colcon", path=str(Path(sys.executable).parent)) is None,
                    reason="colcon is installed by `scripts/install --test`")
def test_colcon_builds_both_packages(tmp_path):
    src = tmp_path / "src"
    shutil.copytree(ROOT / "msg_defs", src / "maglev_msgs")
    ignore = shutil.ignore_patterns(".venv", ".git", "msg_defs", "build", "install", "log",
                                    "__pycache__", "*.egg-info", "out")
    shutil.copytree(ROOT, src / "maglev_ros", ignore=ignore)
    prefix = str(Path(sys.prefix))
    env = dict(os.environ, AMENT_PREFIX_PATH=prefix, CMAKE_PREFIX_PATH=prefix,
               PATH=str(Path(sys.executable).parent) + os.pathsep + os.environ["PATH"])
    res = subprocess.run(
        [str(Path(sys.executable).parent / "colcon"), "build", "--cmake-args",
         f"-DPython3_EXECUTABLE={sys.executable}", "-DBUILD_TESTING=OFF"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    inst = tmp_path / "install"
    assert (inst / "maglev_msgs" / "share" / "maglev_msgs" / "msg" / "SensorBlock.msg").exists()
    assert list((inst / "maglev_msgs").rglob("maglev_msgs/msg/_sensor_block.py"))
    assert (inst / "maglev_ros" / "share" / "maglev_ros" / "package.xml").exists()
    assert (inst / "maglev_ros" / "share" / "maglev_ros" / "launch" / "monitor.launch.py").exists()
    assert (inst / "maglev_ros" / "share" / "ament_index" / "resource_index" / "packages"
            / "maglev_ros").exists()
    # `ros2 run maglev_ros <node>` looks in lib/<package>/
    for exe in ("replay", "twin", "modal_id", "irregularity", "updater", "discrepancy", "maglev-ros"):
        assert (inst / "maglev_ros" / "lib" / "maglev_ros" / exe).exists(), exe
