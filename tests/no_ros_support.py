"""Run a Python snippet in a process where every ROS package is unimportable: what a training
machine without ROS (a GPU box, a cluster node) sees."""
from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

# Client library, message, build and tooling packages of ROS 2; any `*_msgs` package too.
ROS_PACKAGES = ("rclpy", "rosidl", "rpyutils", "rcl_interfaces", "builtin_interfaces", "std_srvs",
                "ament_index_python", "launch", "rosbag2_py", "unique_identifier_msgs")

PRELUDE = textwrap.dedent(f"""
    import importlib.abc, sys
    sys.path.insert(0, {str(Path(__file__).parent)!r})

    class NoRos(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            top = name.split(".")[0]
            if top.startswith({ROS_PACKAGES!r}) or top.endswith("_msgs"):
                raise ModuleNotFoundError(f"{{name}}: this process has no ROS")

    sys.meta_path.insert(0, NoRos())
""")


def is_ros(module: str) -> bool:
    top = module.split(".")[0]
    return top.startswith(ROS_PACKAGES) or top.endswith("_msgs")


def run_without_ros(script: str, timeout: float = 300) -> subprocess.CompletedProcess:
    """`script` (dedented) after the prelude, in a fresh interpreter; stdout and stderr as text."""
    return subprocess.run([sys.executable, "-c", PRELUDE + textwrap.dedent(script)], capture_output=True,
                          text=True, timeout=timeout, cwd=Path(__file__).resolve().parents[1])
