"""Suite-wide settings: deterministic hypothesis runs sized for a 2-core CI machine."""
import os

import pytest
from hypothesis import HealthCheck, settings

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



@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory):
    """A 300-candidate generated compositional dataset (seed 0), shared by the training tests."""
    from gscan_ros.cli import main

    out = tmp_path_factory.mktemp("tiny_data")
    assert main(["generate", "--out", str(out), "--examples", "300", "--seed", "0", "--workers", "1", "--quiet"]) == 0
    return out
