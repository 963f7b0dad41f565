"""Build hooks that pyproject.toml cannot express; the metadata lives there.

- The message definitions (``msg_defs/msg/*.msg``, the recording contract's SensorBlock among
  them) are copied into the package as ``maglev_ros/msg/``, so a plain ``pip install .`` reads
  and writes contract bags without the ROS message package built.
- Console scripts: a pip build installs ``maglev-ros`` and the nodes as ``maglev_<node>`` (no
  ``replay`` or ``echo`` shadowing a system command on PATH); colcon's ament_python build
  (``setup.py install``/``develop``) installs them under their short names in
  ``lib/maglev_ros/`` (setup.cfg), where ``ros2 run maglev_ros <node>`` looks.
- ``data_files``: the ament index entry, package.xml and the launch file under ``share/``.
"""
import shutil
import sys
from glob import glob
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

PACKAGE = "maglev_ros"
HERE = Path(__file__).resolve().parent
# every node module is a console script (maglev_ros/nodes/__init__.py makes their entry functions)
NODES = sorted(p.stem for p in (HERE / PACKAGE / "nodes").glob("*.py") if not p.stem.startswith("_"))
# a legacy command on the command line means colcon (or a ROS user) is installing into a ROS prefix
ROS_LAYOUT = bool({"install", "develop"} & set(sys.argv[1:]))


class BuildPyWithMsgs(build_py):
    """build_py that also places the .msg texts inside the package (package data)."""

    def run(self):
        super().run()
        src = HERE / "msg_defs" / "msg"
        dst = Path(self.build_lib) / PACKAGE / "msg"
        if src.is_dir():
            dst.mkdir(parents=True, exist_ok=True)
            for f in sorted(src.glob("*.msg")):
                shutil.copyfile(f, dst / f.name)


def console_scripts():
    prefix = "" if ROS_LAYOUT else "maglev_"
    return [f"maglev-ros = {PACKAGE}.cli:main"] + [
        f"{prefix}{name} = {PACKAGE}.nodes:{name}_main" for name in NODES]


setup(
    cmdclass={"build_py": BuildPyWithMsgs},
    python_requires=">=3.10",
    entry_points={"console_scripts": console_scripts()},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
        (f"share/{PACKAGE}/config", glob(f"{PACKAGE}/config/*.yaml")),
    ],
    zip_safe=False,
)
