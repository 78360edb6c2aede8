"""ament_python package: works with `colcon build`, `pip install .` and `pip install -e .`.

Node executables are console scripts; `setup.cfg` puts them under lib/gscan_ros for
colcon, and small launchers in `scripts/` go there via data_files so `ros2 run` also
finds them after a plain `pip install .` into a ROS-wheel venv.
"""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "gscan_ros"
NODES = ("world_simulator_node", "parser_node", "policy_node", "episode_recorder_node")

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=["gscan_ros", "gscan_ros.*", "msg_adapters", "msg_adapters.*"]),
    package_data={PACKAGE: ["assets/*"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/launch", glob("launch/*.py")),
        (f"share/{PACKAGE}/config", glob("config/*.yaml") + glob("config/*.xml") + glob("config/*.json")),
        (f"lib/{PACKAGE}", glob("scripts/*")),
    ],
    python_requires=">=3.11",
    # What the package imports at run time, loosely (requirements.txt pins exact versions). rclpy and
    # the message packages come from ROS (package.xml), not from an index.
    install_requires=["torch", "numpy", "nltk", "mcap", "zstandard", "lz4", "rosbags", "pyyaml", "tqdm", "matplotlib",
                      "pillow"],
    zip_safe=True,
    maintainer="gscan_ros maintainers",
    description="gSCAN command following with compositional networks on ROS 2 Jazzy",
    license="MIT",
    # Imported only by tests/ (`pip install .[test]`); `tests_require` is gone from setuptools >= 72.
    extras_require={"test": ["pytest", "hypothesis", "mcap-ros2-support"]},
    entry_points={
        "console_scripts": [
            "gscan-ros = gscan_ros.cli:main",
            *(f"{node} = {PACKAGE}.nodes.{node}:main" for node in NODES),
        ],
    },
)
