"""`colcon build` lays gscan_ros out where `ros2 run` and `ros2 launch` look for it.

Runs only where colcon is installed: importable here, or a `colcon` on PATH (or $COLCON)
from a venv of the same Python version. The wheels venv must not get colcon, so it
lives in its own venv (docs/ros.md "Building with colcon"); it is run on *this*
interpreter, as on a ROS install where colcon and rclpy share /usr/bin/python3, because
colcon builds with its own interpreter and writes it into the node scripts' shebangs.
"""
from __future__ import annotations

import importlib.util
import os
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from packaging_support import (
    NODES,
    PACKAGE,
    SITE,
    copy_sources,
    imported_from,
    installed_env,
    ros2_run,
    run_until_logged,
)

pytestmark = pytest.mark.packaging

RUN_COLCON = "import sys; from colcon_core.command import main; sys.argv[0] = 'colcon'; sys.exit(main())"
INSTALL_HINT = ("python3.11 -m venv /tmp/colcon_venv && /tmp/colcon_venv/bin/pip install colcon-common-extensions, "
                "then put /tmp/colcon_venv/bin on PATH")


def colcon_pythonpath() -> str | None:
    """PYTHONPATH that makes colcon importable on this interpreter ("" if it already is); None: no colcon."""
    if importlib.util.find_spec("colcon_core") is not None:
        return ""
    executable = os.environ.get("COLCON") or shutil.which("colcon")
    if executable is None:
        return None
    shebang = Path(executable).read_text().splitlines()[0].removeprefix("#!")
    query = "import colcon_core, os, sys; print(sys.version_info[:2]); print(os.path.dirname(colcon_core.__path__[0]))"
    lines = subprocess.run([*shlex.split(shebang), "-c", query], capture_output=True, text=True, check=True,
                           timeout=60).stdout.splitlines()
    if lines[0] != str(sys.version_info[:2]):
        pytest.skip(f"colcon at {executable} runs on Python {lines[0]}, this is {sys.version_info[:2]}")
    return lines[1]


@pytest.fixture(scope="module")
def colcon_install(tmp_path_factory) -> Path:
    """`colcon build` of a copy of the repo in a fresh workspace: its install/gscan_ros."""
    pythonpath = colcon_pythonpath()
    if pythonpath is None:
        pytest.skip(f"colcon is not installed ({INSTALL_HINT})")
    workspace = tmp_path_factory.mktemp("colcon_ws")
    copy_sources(workspace / "src" / PACKAGE)
    env = {**os.environ, "PYTHONPATH": pythonpath} if pythonpath else dict(os.environ)
    build = subprocess.run([sys.executable, "-c", RUN_COLCON, "build", "--packages-select", PACKAGE],
                           cwd=workspace, env=env, capture_output=True, text=True, timeout=300)
    assert build.returncode == 0, build.stdout + build.stderr
    return workspace / "install" / PACKAGE


def test_colcon_install_has_node_executables_share_files_and_ament_index(colcon_install):
    for node in NODES:
        executable = colcon_install / "lib" / PACKAGE / node
        assert executable.is_file() and os.access(executable, os.X_OK), executable
        assert executable.read_text().startswith(f"#!{sys.executable}")
    share = colcon_install / "share"
    for path in ("package.xml", "launch/gscan.launch.py", "config/params.yaml", "config/fastdds_fast_discovery.xml"):
        assert (share / PACKAGE / path).is_file(), path
    assert (share / "ament_index/resource_index/packages" / PACKAGE).is_file()
    # colcon's own environment hook: sourcing install/setup.bash puts the prefix on AMENT_PREFIX_PATH.
    assert "AMENT_PREFIX_PATH" in (share / PACKAGE / "hook/ament_prefix_path.dsv").read_text()
    assert (colcon_install / SITE / "gscan_ros/nodes/parser_node.py").is_file()
    assert (colcon_install / SITE / "msg_adapters/__init__.py").is_file()


def test_colcon_install_ships_the_default_model_when_the_repo_has_one(colcon_install):
    shipped = Path(__file__).resolve().parents[1] / "gscan_ros/assets/default_model.pt"
    if not shipped.is_file():
        pytest.skip("no gscan_ros/assets/default_model.pt in this checkout")
    installed = colcon_install / SITE / "gscan_ros/assets/default_model.pt"  # the one copy the nodes load
    assert installed.read_bytes() == shipped.read_bytes()
    assert not (colcon_install / "share" / PACKAGE / "models").exists()


def test_ros2_run_parser_node_from_the_colcon_install_starts_and_stops_on_sigint(colcon_install, tmp_path):
    env = installed_env(colcon_install, tmp_path)
    executable = ros2_run("parser_node", env)
    assert executable == colcon_install / "lib" / PACKAGE / "parser_node"
    assert imported_from(env, tmp_path).startswith(str(colcon_install / SITE))  # the install, not the source tree
    output, status = run_until_logged(executable, env, tmp_path, "parsing commands with the semantic parser")
    assert "[parser_node]: parsing commands with the semantic parser" in output, output
    assert status == 0, output
