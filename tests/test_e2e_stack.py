"""The stack as separate processes over Fast DDS: command -> graph -> lock-step episode -> bag.

One stack per module (starting five Python processes costs seconds): world simulator,
parser, policy (a tiny random checkpoint: the protocol is under test, not the model)
and two recorders, one stopped with SIGINT and one SIGKILLed. Commands go through a
GscanCommander, the way a script drives the stack; a probe records the topics.
"""
import signal
import time

import numpy as np
import pytest
from std_msgs.msg import String

from gscan_ros.data.bag import BagEpisodeReader, read_bag_info
from gscan_ros.data.sources import sample_episode
from gscan_ros.nodes.commander import GscanCommander, Outcome
from gscan_ros.nodes.common import EVENT_QOS, LATCHED_LOG_QOS
from gscan_ros.nodes.episode_recorder_node import READY_LOG
from gscan_ros.world import World
from gscan_ros.world.types import Action
from msg_adapters import cdr_to_graph

from model_support import tiny_checkpoint
from ros_helpers import STARTUP_TIMEOUT, NodeProcess, Probe, fresh_domain_id, ros_env

pytestmark = pytest.mark.e2e  # the nodes as separate processes

SEED = 0
MAX_STEPS = 10
RECORDERS = ("episode_recorder_node", "recorder_killed")


class Stack:
    def __init__(self, tmp):
        checkpoint = tiny_checkpoint(tmp / "tiny.pt", weight_scale=8.0)
        self.tmp = tmp
        self.env = ros_env(fresh_domain_id(), tmp)
        self.processes = {}
        self._start("world_simulator_node", seed=SEED)
        self._start("parser_node", checkpoint=checkpoint)
        self._start("policy_node", checkpoint=checkpoint, max_steps=MAX_STEPS)
        for name in RECORDERS:
            self._start("episode_recorder_node", name=name, bag_dir=tmp / name, include_images=True)
        self.probe = Probe(int(self.env["ROS_DOMAIN_ID"]))
        self.actions = self.probe.record("action", String, EVENT_QOS)
        self.status = self.probe.record("status", String, EVENT_QOS)
        self.graphs = self.probe.record("command_graph", String, LATCHED_LOG_QOS, raw=True)
        self.commands = self.probe.node.create_publisher(String, "command", EVENT_QOS)
        self.action_pub = self.probe.node.create_publisher(String, "action", EVENT_QOS)
        self.commander = GscanCommander(context=self.probe.context)

    def _start(self, executable, name=None, **params):
        remaps = {"__node": name} if name else None
        self.processes[name or executable] = NodeProcess(executable, self.env, self.tmp, params, remaps, name)

    def wait_until_up(self):
        try:
            self.probe.wait_for_endpoints({
                "/command": {"parser_node"},
                "/command_graph": {"policy_node", *RECORDERS},
                "/observation": {"policy_node", *RECORDERS},
                "/action": {"world_simulator_node", *RECORDERS},
            })
            self.commander.wait_until_ready(STARTUP_TIMEOUT)
            for name in RECORDERS:
                self.probe.spin_until(lambda name=name: READY_LOG in self.processes[name].output(), STARTUP_TIMEOUT,
                                      what=f"{name} to receive the world state")
        except AssertionError as exc:
            logs = "\n".join(f"--- {n}\n{p.output()[-1500:]}" for n, p in self.processes.items())
            raise AssertionError(f"{exc}\n{logs}") from None

    def lines(self, prefix):
        return [m.data for m in self.status if m.data.startswith(prefix)]

    def run_command(self, command):
        """Run `command` to its end; the actions up to and including <eos>."""
        result = self.commander.run_episode(command, timeout=30)
        assert result.finished, (result.outcome, result.status[-5:])
        return result.actions

    def close(self):
        codes = {name: p.stop() for name, p in self.processes.items()}
        self.commander.shutdown()
        self.probe.close()
        return codes


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    s = Stack(tmp_path_factory.mktemp("stack"))
    try:
        s.wait_until_up()
        yield s
    finally:
        codes = s.close()
        for name, p in s.processes.items():
            print(f"--- {name} (exit {codes[name]})\n{p.output()[-3000:]}")


@pytest.fixture(scope="module")
def episode(stack):
    """The situation's own command, run once: (command, actions with <eos>)."""
    command = sample_episode(SEED).command
    actions = stack.run_command(command)
    for name in RECORDERS:
        try:
            stack.probe.spin_until(lambda name=name: stack.lines(f"{name}: recorded episode 0"),
                                   what=f"{name} to record")
        except AssertionError as exc:
            logs = "\n".join(f"--- {n}\n{p.output()[-2000:]}" for n, p in stack.processes.items())
            raise AssertionError(f"{exc}\n{logs}") from None
    return command, actions


def test_episode_runs_in_lock_step_until_eos(stack, episode):
    command, actions = episode
    assert actions[-1] is Action.EOS and Action.EOS not in actions[:-1]
    assert 1 <= len(actions) <= MAX_STEPS + 1
    assert stack.graphs and cdr_to_graph(stack.graphs[-1]).command == command
    stack.probe.spin_until(lambda: stack.lines(f"world_simulator_node: episode ended after {len(actions) - 1} actions"),
                           what="the world's episode end")


def test_the_commander_reports_a_refused_command_with_its_reason(stack, episode):
    result = stack.commander.run_episode("walk to a purple circle", timeout=30)
    assert result.outcome is Outcome.REJECTED and result.actions == []
    assert result.reason.startswith("rejected command 'walk to a purple circle'")
    assert result.episode_id == "/parser_node/1"


def check_recorded(bag_dir, command, actions):
    """The one episode with its outcome: cut when the policy stopped it at max_steps."""
    reader = BagEpisodeReader(bag_dir, decode_states=True, include_incomplete=True)
    records = list(reader.records())
    assert len(records) == 1, reader.report.summary()
    assert records[0].outcome == ("cut" if len(actions) - 1 == MAX_STEPS else "complete")
    recorded = records[0].episode
    assert recorded.command == command
    assert recorded.actions == tuple(actions[:-1])
    # The recorded observations are exactly the states the actions lead through.
    np.testing.assert_array_equal(records[0].states, recorded.states())
    np.testing.assert_array_equal(World(recorded.situation).encode(), World(sample_episode(SEED).situation).encode())
    return reader


def test_recorder_stopped_with_sigint_closes_a_complete_bag(stack, episode):
    assert stack.processes["episode_recorder_node"].stop(signal.SIGINT) == 0
    bag = stack.tmp / "episode_recorder_node"
    assert read_bag_info(bag).closed
    reader = check_recorded(bag, *episode)
    assert not reader.report.truncated and reader.report.lost_messages == 0


def test_killed_recorder_leaves_a_bag_readable_up_to_its_last_episode(stack, episode):
    stack.processes["recorder_killed"].kill()
    bag = stack.tmp / "recorder_killed"
    assert not read_bag_info(bag).closed
    check_recorded(bag, *episode)


def test_bad_inputs_are_reported_one_status_line_each(stack, episode):
    bad = ["walk to a purple circle", "", "x" * 10_000, "circle a to walk"]
    before = len(stack.lines("parser_node: rejected command"))
    for text in bad:
        stack.probe.publish_when_matched(stack.commands, String(data=text))
    stack.probe.spin_until(lambda: len(stack.lines("parser_node: rejected command")) == before + len(bad),
                           what="a rejection per bad command")
    stack.probe.publish_when_matched(stack.action_pub, String(data="fly"), subscribers=2)
    stack.probe.spin_until(lambda: stack.lines("world_simulator_node: rejected action 'fly'"), what="the rejection")


def test_a_command_flood_is_answered_in_full_and_the_stack_survives(stack, episode):
    flood = 300
    before = len(stack.lines("parser_node: rejected command"))
    stack.probe.spin_until(lambda: stack.commands.get_subscription_count() > 0, what="the parser")
    for i in range(flood):
        stack.commands.publish(String(data=f"walk to a circle number {i}"))
    stack.probe.spin_until(lambda: len(stack.lines("parser_node: rejected command")) == before + flood,
                           what=f"{flood} rejections")
    assert all(p.alive() for name, p in stack.processes.items() if name not in RECORDERS)
    actions = stack.run_command("walk to a small circle")  # still serving
    assert actions[-1] is Action.EOS


def test_nodes_exit_cleanly_on_sigint(stack, episode):
    for name in ("world_simulator_node", "parser_node", "policy_node"):
        started = time.monotonic()
        assert stack.processes[name].stop(signal.SIGINT) == 0, stack.processes[name].output()[-2000:]
        assert time.monotonic() - started < 15
