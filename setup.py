"""maglev_ros: an ament_python package that also installs with plain pip.

colcon builds it from package.xml + this file in a ROS 2 workspace; ``scripts/install`` installs
it with pip into a venv that holds the ROS 2 wheels from PyPI (see README).
"""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "maglev_ros"

# Nodes (console scripts, also the executables `ros2 run maglev_ros <node>` finds).
NODES = {
    "replay": "maglev_ros.nodes.replay:main",
    "echo": "maglev_ros.nodes.echo:main",
    "summary": "maglev_ros.nodes.summary:main",
    "irregularity": "maglev_ros.nodes.irregularity:main",
    "twin": "maglev_ros.nodes.twin:main",
    "modal_id": "maglev_ros.nodes.modal_id:main",
    "updater": "maglev_ros.nodes.updater:main",
    "discrepancy": "maglev_ros.nodes.discrepancy:main",
}

setup(
    name=PACKAGE,
    version="0.1.0",
    description="ROS 2 node suite for high-speed maglev test lines",
    packages=find_packages(include=[PACKAGE, f"{PACKAGE}.*"]),
    package_data={PACKAGE: ["config/*.yaml", "report/*.html"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
        (f"share/{PACKAGE}/config", glob(f"{PACKAGE}/config/*.yaml")),
    ],
    python_requires=">=3.10",
    install_requires=[
        "numpy>=1.26",
        "scipy>=1.11",
        "pyyaml>=6",
        "matplotlib>=3.8",
        "rosbags>=0.10",
        "mcap>=1.1",
        "numba>=0.60",
        "threadpoolctl>=3",
        "torch==2.13.0",
        "pymoo>=0.6.1",
    ],
    extras_require={"test": ["pytest>=8", "pytest-timeout>=2.3"]},
    zip_safe=True,
    entry_points={
        "console_scripts": [f"maglev-ros = {PACKAGE}.cli:main"]
        + [f"{name} = {target}" for name, target in NODES.items()],
    },
)
