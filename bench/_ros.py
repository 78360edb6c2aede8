"""Shared by the ROS benches: the test suite's node-process harness (tests/ros_helpers.py).

Node processes run in their own session and domain, on loopback, with the fast-discovery
profile; importing this sets the process environment for that (see tests/ros_helpers.py),
so import it before rclpy is initialised. The stack is then driven by a GscanCommander.
"""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from ros_helpers import NodeProcess, fresh_domain_id, ros_env  # noqa: E402

__all__ = ["NodeProcess", "fresh_domain_id", "ros_env"]
