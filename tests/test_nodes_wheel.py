"""The wheel carries what `ros2 run` / `ros2 launch` need after a plain `pip install`."""
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

pytestmark = pytest.mark.packaging  # builds a wheel with pip

REPO = Path(__file__).resolve().parents[1]
NODES = ("world_simulator_node", "parser_node", "policy_node", "episode_recorder_node")
# What setup.py packages; copied so the in-tree build leaves no build/ behind in the repo.
SOURCES = ("setup.py", "setup.cfg", "package.xml", "resource", "launch", "config", "scripts", "gscan_ros",
           "msg_adapters")


def test_wheel_installs_ament_index_share_files_and_node_launchers(tmp_path):
    source = tmp_path / "src"
    source.mkdir()
    for name in SOURCES:
        if (REPO / name).is_dir():
            shutil.copytree(REPO / name, source / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(REPO / name, source / name)
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", str(source),
         "-w", str(tmp_path)],
        check=True, capture_output=True, timeout=300,
    )
    (wheel,) = tmp_path.glob("gscan_ros-*.whl")
    with zipfile.ZipFile(wheel) as archive:
        names = set(archive.namelist())
        entry_points = next(archive.read(n).decode() for n in names if n.endswith(".dist-info/entry_points.txt"))
    data = next(n.split("/data/")[0] for n in names if ".data/data/" in n) + "/data/"
    expected = {
        "share/ament_index/resource_index/packages/gscan_ros",
        "share/gscan_ros/package.xml",
        "share/gscan_ros/launch/gscan.launch.py",
        "share/gscan_ros/config/params.yaml",
        "share/gscan_ros/config/fastdds_fast_discovery.xml",
        *(f"lib/gscan_ros/{node}" for node in NODES),
    }
    assert {data + path for path in expected} <= names
    for node in NODES:
        assert f"{node} = gscan_ros.nodes.{node}:main" in entry_points
    assert "gscan-ros = gscan_ros.cli:main" in entry_points
    assert "gscan_ros/nodes/policy_node.py" in names and "msg_adapters/__init__.py" in names
