"""After a plain (non-editable) `pip install .` into a venv, `ros2 run gscan_ros policy_node` works.

The wheel's contents are checked by test_nodes_wheel.py; this installs it into a fresh,
throwaway venv and runs a node the way `ros2 run` does: found through the ament index
registered under the venv, executed through its launcher's shebang (`/usr/bin/env
python3`, i.e. the activated venv's interpreter: here the wheels venv, which has rclpy).
pip targets the throwaway venv with `--python`: installing into a `--prefix` from this
venv would first uninstall this venv's own (editable) gscan_ros.
"""
from __future__ import annotations

import subprocess
import sys

import pytest

from packaging_support import (
    NODES,
    PACKAGE,
    SITE,
    WHEELS_VENV,
    copy_sources,
    imported_from,
    installed_env,
    ros2_run,
    run_until_logged,
)

pytestmark = pytest.mark.packaging


def pip(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "pip", *args, "-q", "--no-deps"], check=True, capture_output=True,
                   timeout=300)


def test_pip_install_registers_ament_index_and_ros2_run_starts_policy_node(tmp_path):
    own_install = sorted(WHEELS_VENV.glob(f"{SITE}/*gscan_ros*"))
    source = copy_sources(tmp_path / "src")
    pip("wheel", "--no-build-isolation", str(source), "-w", str(tmp_path))  # no index needed
    (wheel,) = tmp_path.glob("gscan_ros-*.whl")
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    pip("--python", str(venv / "bin/python"), "install", str(wheel))
    assert sorted(WHEELS_VENV.glob(f"{SITE}/*gscan_ros*")) == own_install  # this venv's install untouched
    assert (venv / "share/ament_index/resource_index/packages" / PACKAGE).is_file()
    assert (venv / "share" / PACKAGE / "package.xml").is_file()
    assert {path.name for path in (venv / "lib" / PACKAGE).iterdir()} == set(NODES)

    env = installed_env(venv, tmp_path)
    executable = ros2_run("policy_node", env)
    assert executable == venv / "lib" / PACKAGE / "policy_node"
    assert imported_from(env, tmp_path).startswith(str(venv / SITE))  # the install, not the source tree
    output, status = run_until_logged(executable, env, tmp_path, "policy ready")
    assert "[policy_node]: policy ready" in output, output
    assert status == 0, output
