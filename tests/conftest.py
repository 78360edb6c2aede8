"""Suite-wide settings and shared fixtures: deterministic hypothesis runs sized for a 2-core
CI machine, and the markers that keep the quick loop quick (markers in setup.cfg)."""
import json
import os
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

FIXTURES = Path(__file__).parent / "fixtures"

settings.register_profile(
    "ci",
    max_examples=int(os.environ.get("HYPOTHESIS_MAX_EXAMPLES", "100")),
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.load_profile("ci")

# DDS must stay on loopback for every test that touches ROS (machine rule).
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

# Markers of whole modules that do not set `pytestmark` themselves: ROS stacks in
# subprocesses (e2e) and installs of the package (packaging).
MODULE_MARKERS = {
    "test_e2e_bringup.py": "e2e",
    "test_e2e_stack.py": "e2e",
    "test_nodes_launch.py": "e2e",
    "test_nodes_demo.py": "e2e",
    "test_nodes_wheel.py": "packaging",
}


def pytest_collection_modifyitems(items):
    for item in items:
        marker = MODULE_MARKERS.get(item.path.name)
        if marker is not None:
            item.add_marker(marker)


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory):
    """A 300-candidate generated compositional dataset (seed 0), shared by the training tests."""
    from gscan_ros.cli import main

    out = tmp_path_factory.mktemp("tiny_data")
    assert main(["generate", "--out", str(out), "--examples", "300", "--seed", "0", "--workers", "1", "--quiet"]) == 0
    return out


@pytest.fixture
def real_situation() -> dict:
    """A fresh copy of the situation of the real compositional example in gSCAN's
    `example_prediction.json` ("push a green small square cautiously")."""
    return json.loads((FIXTURES / "real_situation.json").read_text())
