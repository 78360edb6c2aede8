"""`gscan-ros bringup` (all nodes in one process) answers a command from another process."""
import signal

from std_msgs.msg import String

from gscan_ros.nodes.common import EVENT_QOS
from gscan_ros.nodes.harness import VENV_BIN, NodeProcess, Probe, fresh_domain_id, ros_env

from ros_helpers import tiny_checkpoint


def test_bringup_follows_a_command_and_stops_on_sigint(tmp_path):
    checkpoint = tiny_checkpoint(tmp_path / "tiny.pt")
    env = ros_env(fresh_domain_id(), tmp_path)
    bringup = NodeProcess(
        [str(VENV_BIN / "gscan-ros"), "bringup", "--checkpoint", str(checkpoint), "--seed", "2", "--max-steps", "3"],
        env, tmp_path,
    )
    probe = Probe(int(env["ROS_DOMAIN_ID"]))
    try:
        actions = probe.record("action", String, EVENT_QOS)
        status = probe.record("status", String, EVENT_QOS)
        commands = probe.node.create_publisher(String, "command", EVENT_QOS)
        probe.wait_for_endpoints({"/command_graph": {"policy_node"}, "/action": {"world_simulator_node"}})
        probe.publish_when_matched(commands, String(data="pull a yellow cylinder hesitantly"))
        probe.spin_until(lambda: actions and actions[-1].data == "<eos>", what="<eos>")
        assert len(actions) <= 4  # max_steps 3, then <eos>
        probe.spin_until(lambda: any(s.data.startswith("world_simulator_node: episode ended") for s in status),
                         what="the world's episode end")
    finally:
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
