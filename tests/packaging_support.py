"""Shared by the packaging tests: a clean source copy, and `ros2 run` without the ros2 CLI.

`ros2 run PKG EXE` finds PKG's prefix in the ament index (AMENT_PREFIX_PATH) and executes
`<prefix>/lib/PKG/EXE` directly, so its shebang picks the interpreter. `ros2_run` does the
same with `ament_index_python`, in the environment a sourced workspace or an activated
wheels venv gives: the install prefix first on AMENT_PREFIX_PATH and PYTHONPATH, and the
wheels venv (its ament index holds rclpy & co.) behind it.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from unittest import mock

from ament_index_python.packages import get_package_prefix

from ros_helpers import STARTUP_TIMEOUT, VENV_BIN, NodeProcess, fresh_domain_id, ros_env

REPO = Path(__file__).resolve().parents[1]
PACKAGE = "gscan_ros"
NODES = ("world_simulator_node", "parser_node", "policy_node", "episode_recorder_node")
WHEELS_VENV = Path(sys.prefix)
SITE = f"lib/python{sys.version_info.major}.{sys.version_info.minor}/site-packages"
# What setup.py reads; building a copy leaves no build/, install/ or egg-info in the repo.
SOURCES = ("setup.py", "setup.cfg", "package.xml", "resource", "launch", "config", "scripts", "gscan_ros",
           "msg_adapters")


def copy_sources(dest: Path) -> Path:
    dest.mkdir(parents=True)
    for name in SOURCES:
        if (REPO / name).is_dir():
            shutil.copytree(REPO / name, dest / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(REPO / name, dest / name)
    return dest


def installed_env(prefix: Path, log_dir: Path) -> dict[str, str]:
    """Node environment for an install `prefix`: loopback DDS, own domain, prefix before the venv."""
    env = ros_env(fresh_domain_id(), log_dir)
    env.update(
        AMENT_PREFIX_PATH=os.pathsep.join((str(prefix), str(WHEELS_VENV))),
        PYTHONPATH=str(prefix / SITE),
        PATH=os.pathsep.join((str(VENV_BIN), env.get("PATH", ""))),  # an activated venv
    )
    return env


def ros2_run(executable: str, env: dict[str, str]) -> Path:
    """The file `ros2 run gscan_ros <executable>` would execute in `env`."""
    with mock.patch.dict(os.environ, AMENT_PREFIX_PATH=env["AMENT_PREFIX_PATH"]):
        return Path(get_package_prefix(PACKAGE)) / "lib" / PACKAGE / executable


def run_until_logged(executable: Path, env: dict[str, str], log_dir: Path, ready: str) -> tuple[str, int]:
    """Start the node, wait for its `ready` log line, SIGINT it: (output, exit status)."""
    node = NodeProcess([str(executable)], env, log_dir, name=executable.name)
    try:
        deadline = time.monotonic() + STARTUP_TIMEOUT
        while ready not in node.output() and node.alive() and time.monotonic() < deadline:
            time.sleep(0.1)
    finally:
        status = node.stop()
    return node.output(), status


def imported_from(env: dict[str, str], cwd: Path) -> str:
    """Where `import gscan_ros` resolves in `env` (run from `cwd`: `-c` puts the cwd first on sys.path)."""
    return subprocess.run([sys.executable, "-c", "import gscan_ros; print(gscan_ros.__file__)"], env=env, cwd=cwd,
                          capture_output=True, text=True, check=True, timeout=60).stdout.strip()
