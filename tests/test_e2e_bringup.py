"""`gscan-ros bringup` (all nodes in one process) answers a command from another process."""
import signal

import pytest

from gscan_ros.nodes.commander import GscanCommander
from gscan_ros.world.types import Action

from model_support import tiny_checkpoint
from ros_helpers import STARTUP_TIMEOUT, VENV_BIN, NodeProcess, Probe, fresh_domain_id, ros_env

pytestmark = pytest.mark.e2e  # `gscan-ros bringup` in a subprocess


def test_bringup_follows_a_command_and_stops_on_sigint(tmp_path):
    checkpoint = tiny_checkpoint(tmp_path / "tiny.pt")
    env = ros_env(fresh_domain_id(), tmp_path)
    bringup = NodeProcess(
        [str(VENV_BIN / "gscan-ros"), "bringup", "--checkpoint", str(checkpoint), "--seed", "2", "--max-steps", "3"],
        env, tmp_path,
    )
    probe = Probe(int(env["ROS_DOMAIN_ID"]))
    commander = GscanCommander(context=probe.context)
    try:
        commander.wait_until_ready(STARTUP_TIMEOUT)
        result = commander.run_episode("pull a yellow cylinder hesitantly", timeout=60)
        assert result.finished and result.actions[-1] is Action.EOS
        assert result.steps <= 3  # max_steps 3, then <eos>
        commander.wait_for_status("world_simulator_node: episode ended", 30)
    finally:
        commander.shutdown()
        probe.close()
        code = bringup.stop(signal.SIGINT)
    assert code == 0, bringup.output()[-2000:]
    assert "gscan-ros bringup: running world_simulator_node, parser_node, policy_node" in bringup.output()


def test_a_node_with_a_bad_parameter_exits_1_with_one_line(tmp_path):
    env = ros_env(fresh_domain_id(), tmp_path)
    node = NodeProcess("policy_node", env, tmp_path, {"checkpoint": tmp_path / "missing.pt"})
    assert node.process.wait(timeout=120) == 1
    node.stop()
    lines = [line for line in node.output().splitlines() if not line.startswith("[")]  # ROS log lines aside
    assert lines == [f"error: checkpoint {str(tmp_path / 'missing.pt')!r} does not exist"]
