"""SIGINT/SIGTERM stop a node between callbacks, never inside one (`common.run`).

rclpy's own handler raises KeyboardInterrupt wherever the main thread is: inside a
recorder's write it leaves an MCAP chunk half indexed, and the closed bag reads back
with its last episodes missing. A node here sleeps in a callback while it is signalled.
"""
import os
import signal
import sys
import textwrap
import time

import pytest

from ros_helpers import TIMEOUT, NodeProcess, fresh_domain_id, ros_env

pytestmark = pytest.mark.e2e

NODE = textwrap.dedent("""
    import sys, time
    from rclpy.node import Node
    from gscan_ros.nodes.common import run

    class Busy(Node):
        def __init__(self):
            super().__init__("busy")
            self.timer = self.create_timer(0.05, self.work)

        def work(self):
            self.timer.cancel()
            print("callback started", flush=True)
            time.sleep(float(sys.argv[1]))
            print("callback finished", flush=True)

        def destroy_node(self):
            print("destroyed", flush=True)
            super().destroy_node()

    sys.exit(run(Busy))
""")


def start(tmp_path, seconds: float) -> NodeProcess:
    node = NodeProcess([sys.executable, "-c", NODE, str(seconds)], ros_env(fresh_domain_id(), tmp_path), tmp_path,
                       name="busy")
    deadline = time.monotonic() + TIMEOUT
    while "callback started" not in node.output():
        assert node.alive() and time.monotonic() < deadline, node.output()
        time.sleep(0.02)
    return node


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_lets_the_running_callback_finish_then_destroys_the_node(tmp_path, sig):
    node = start(tmp_path, seconds=1.0)
    assert node.stop(sig) == 0
    out = node.output()
    assert "callback finished" in out and "destroyed" in out, out
    assert out.index("callback finished") < out.index("destroyed")
    assert "Traceback" not in out, out


def test_a_second_signal_ends_a_stuck_callback(tmp_path):
    node = start(tmp_path, seconds=60.0)
    started = time.monotonic()
    os.killpg(node.process.pid, signal.SIGINT)
    # Two signals that arrive before Python handles the first count as one; the sleeping
    # callback takes it within milliseconds.
    time.sleep(0.5)
    assert node.alive(), node.output()  # the first one only asked
    assert node.stop(signal.SIGINT) == 0
    assert time.monotonic() - started < 15
    out = node.output()
    assert "callback finished" not in out and "destroyed" in out, out
