"""Suite-wide settings and shared fixtures: deterministic hypothesis runs sized for a 2-core
CI machine, DDS on loopback, and fixtures. Markers (setup.cfg) are set by each module itself
(`pytestmark = pytest.mark.e2e`); non-ROS tests import no ROS support (ros_helpers)."""
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

@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory):
    """A generated compositional dataset of at most 300 examples (seed 0), shared by the training tests."""
    from gscan_ros.cli import main

    out = tmp_path_factory.mktemp("tiny_data")
    assert main(["generate", "--out", str(out), "--examples", "300", "--seed", "0", "--workers", "1", "--quiet"]) == 0
    return out


@pytest.fixture
def real_situation() -> dict:
    """A fresh copy of the situation of the real compositional example in gSCAN's
    `example_prediction.json` ("push a green small square cautiously")."""
    return json.loads((FIXTURES / "real_situation.json").read_text())


@pytest.fixture
def probe():
    """A ROS probe node in a fresh DDS domain (loopback), closed with every node it spun."""
    from ros_helpers import Probe, fresh_domain_id  # ROS support only for the tests that ask

    p = Probe(fresh_domain_id())
    yield p
    p.close()


@pytest.fixture
def commander(probe):
    """A GscanCommander in the probe's context (it spins itself)."""
    from gscan_ros.nodes.commander import GscanCommander

    c = GscanCommander(context=probe.context)
    yield c
    c.shutdown()


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    """A tiny trained-shape checkpoint on disk, one per test module."""
    from model_support import tiny_checkpoint

    return tiny_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny.pt")
