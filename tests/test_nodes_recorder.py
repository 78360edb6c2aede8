"""episode_recorder_node in-process: stray actions pair with no episode, a reset records an aborted one."""
import json
import time

import pytest
import yaml
from std_msgs.msg import String

from gscan_ros.data.bag import BagEpisodeReader, BagWriter, iter_bag_episodes, read_bag_info
from gscan_ros.data.sources import sample_episode
from gscan_ros.language import get_parser
from gscan_ros.nodes.common import EVENT_QOS
from gscan_ros.nodes.episode_recorder_node import EpisodeRecorderNode
from gscan_ros.world import World
from gscan_ros.world.types import Action
from msg_adapters import action_to_msg, graph_to_msg, observation_to_msg, reset_to_msg

from ros_helpers import parameters

EPISODE = sample_episode(0)
WALK, TURN, EOS = Action.WALK, Action.TURN_LEFT, Action.EOS


class LiveStack:
    """Plays the world and the policy into a recorder's callbacks, with increasing stamps
    and the policy's publication sequence numbers."""

    def __init__(self, recorder):
        self.recorder = recorder
        self.world = World(EPISODE.situation)
        self.t = time.time_ns()
        self.policy_seq = 0

    def info(self, seq=None):
        self.t += 1000
        return {"source_timestamp": self.t, "publication_sequence_number": seq}

    def publish_state(self):
        self.recorder.on_situation(String(data=json.dumps(self.world.snapshot().to_json())), self.info())
        self.recorder.on_observation(observation_to_msg(self.world.encode()), self.info())

    def command(self):
        graph = get_parser("semantic").parse(EPISODE.command)
        self.recorder.on_graph(graph_to_msg(graph), self.info())

    def policy_acts(self, action):
        """The policy's action and, unless it is <eos>, the world's reply."""
        self.policy_seq += 1
        self.recorder.on_action(action_to_msg(action), self.info(self.policy_seq))
        if action is not EOS:
            self.world.step(action)
            self.publish_state()

    def policy_acts_reply_held(self, action):
        """The policy's action; the world's reply is stamped now but returned, to deliver later."""
        self.policy_seq += 1
        self.recorder.on_action(action_to_msg(action), self.info(self.policy_seq))
        self.world.step(action)
        return observation_to_msg(self.world.encode()), self.info()

    def reset(self):
        self.world = World(EPISODE.situation)
        self.recorder.on_world_reset(reset_to_msg(self.info()["source_timestamp"]), self.info())
        self.publish_state()


@pytest.fixture
def live(probe, tmp_path):
    node = EpisodeRecorderNode(context=probe.context, parameter_overrides=parameters(bag_dir=str(tmp_path / "bag")))
    probe.executor.add_node(node)
    stack = LiveStack(node)
    stack.publish_state()
    yield stack
    node.destroy_node()


def read(bag_dir, include_aborted=False):
    reader = BagEpisodeReader(bag_dir, include_aborted=include_aborted)
    return list(reader.records()), reader.report


def test_a_stray_eos_from_another_publisher_neither_closes_nor_loses_the_episode(probe, live):
    status = probe.record("status", String, EVENT_QOS)
    live.command()
    for action in (WALK, WALK, TURN):
        live.policy_acts(action)
    live.recorder.on_action(action_to_msg(EOS), live.info(seq=1))  # `ros2 topic pub --once /action '<eos>'`
    live.policy_acts(WALK)
    live.policy_acts(EOS)
    records, report = read(live.recorder.bag_dir)
    assert [r.episode.actions for r in records] == [(WALK, WALK, TURN, WALK)]
    assert report.aborted_episodes == 0
    probe.spin_until(lambda: any("ignored action '<eos>'" in s.data and "not the next message" in s.data
                                 for s in status), what="the stray's status line")


def test_a_reset_mid_episode_is_recorded_as_aborted_and_the_next_episode_starts_clean(live):
    live.command()
    live.policy_acts(WALK)
    live.policy_acts(TURN)
    live.reset()
    live.policy_acts(EOS)  # the old command's <eos>, too late: it ends nothing
    live.command()
    live.policy_acts(TURN)
    live.policy_acts(EOS)
    records, report = read(live.recorder.bag_dir)
    assert [r.episode.actions for r in records] == [(TURN,)]  # readers skip the aborted one ...
    assert report.aborted_episodes == 1 and report.lost_episodes == 0  # ... and count it
    assert records[0].episode.situation == EPISODE.situation  # the new world's, replay agrees
    [aborted, complete] = read(live.recorder.bag_dir, include_aborted=True)[0]
    assert aborted.header["outcome"] == "aborted" and aborted.episode.actions == (WALK, TURN)
    assert aborted.episode.meta["aborted_because"] == "the world was reset"
    assert "outcome" not in complete.header


def test_a_reset_notice_that_overtakes_the_last_reply_waits_for_it(live):
    """Topics arrive independently: the world's reply to TURN, published before the reset,
    is delivered after the reset notice; the aborted episode still has both actions."""
    live.command()
    live.policy_acts(WALK)
    reply = live.policy_acts_reply_held(TURN)
    reset = (reset_to_msg(live.info()["source_timestamp"]), live.info())
    live.recorder.on_world_reset(*reset)
    assert read(live.recorder.bag_dir, include_aborted=True)[0] == []  # not cut yet: a reply may be missing
    live.recorder.on_observation(*reply)
    live.world = World(EPISODE.situation)
    live.publish_state()  # the new state: everything sent before the reset is in
    [aborted] = read(live.recorder.bag_dir, include_aborted=True)[0]
    assert aborted.episode.actions == (WALK, TURN) and aborted.header["outcome"] == "aborted"


def test_an_eos_sent_before_a_reset_completes_its_episode_whatever_arrives_first(live):
    """The policy's <eos> comes before the reset, but the reply it waits for comes after the
    reset notice: the episode is complete, not aborted."""
    live.command()
    live.policy_acts(WALK)
    reply = live.policy_acts_reply_held(TURN)
    live.policy_seq += 1
    live.recorder.on_action(action_to_msg(EOS), live.info(live.policy_seq))
    live.recorder.on_world_reset(reset_to_msg(live.info()["source_timestamp"]), live.info())
    live.recorder.on_observation(*reply)
    live.world = World(EPISODE.situation)
    live.publish_state()
    records, report = read(live.recorder.bag_dir, include_aborted=True)
    assert [r.episode.actions for r in records] == [(WALK, TURN)] and report.aborted_episodes == 0


def test_over_dds_a_reset_service_call_ends_the_recorded_episode_as_aborted(probe, tmp_path):
    """The world's world_reset notice and the actions' sequence numbers reach the recorder."""
    from std_msgs.msg import UInt8MultiArray
    from std_srvs.srv import Trigger

    from gscan_ros.nodes.common import LATCHED_LOG_QOS, LATCHED_QOS
    from gscan_ros.nodes.world_simulator_node import WorldSimulatorNode

    status = probe.record("status", String, EVENT_QOS)
    observations = probe.record("observation", UInt8MultiArray, LATCHED_LOG_QOS)
    world = WorldSimulatorNode(context=probe.context, parameter_overrides=parameters(publish_images=False))
    recorder = EpisodeRecorderNode(context=probe.context, parameter_overrides=parameters(bag_dir=str(tmp_path / "bag")))
    for node in (world, recorder):
        probe.executor.add_node(node)
    probe.spin_until(lambda: recorder.ready and observations, what="the world state")
    graphs = probe.node.create_publisher(String, "command_graph", LATCHED_QOS)
    probe.publish_when_matched(graphs, graph_to_msg(get_parser("semantic").parse(EPISODE.command)))
    actions = probe.node.create_publisher(String, "action", EVENT_QOS)
    # At least: in the shared domain an earlier test's participant, still being disposed of
    # on a loaded machine, can count as a third match for a while (it no longer receives).
    probe.spin_until(lambda: actions.get_subscription_count() >= 2, what="the world and the recorder")
    for replies, action in enumerate((WALK, TURN), start=2):
        actions.publish(action_to_msg(action))
        probe.spin_until(lambda replies=replies: len(observations) == replies, what=f"the reply to {action.token}")
    client = probe.node.create_client(Trigger, "reset_world")
    probe.spin_until(client.service_is_ready, what="reset_world")
    future = client.call_async(Trigger.Request())
    probe.spin_until(future.done, what="the reset")
    probe.spin_until(lambda: any("recorded episode 0 as aborted (the world was reset) (2 actions)" in s.data
                                 for s in status), what="the aborted episode")
    world.destroy_node()
    recorder.destroy_node()
    records, report = read(tmp_path / "bag", include_aborted=True)
    assert [r.episode.actions for r in records] == [(WALK, TURN)]
    assert report.aborted_episodes == 1 and report.lost_episodes == 0 and report.lost_messages == 0


def _channel_metadata(bag_dir):
    from mcap.reader import make_reader

    (path,) = bag_dir.glob("*.mcap")
    with open(path, "rb") as f:
        return {c.topic: c.metadata for c in make_reader(f).get_summary().channels.values()}


def _topic_metadata(bag_dir):
    info = yaml.safe_load((bag_dir / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    return {t["topic_metadata"]["name"]: (t["topic_metadata"], t["message_count"])
            for t in info["topics_with_message_count"]}


def test_a_live_bag_has_the_metadata_of_the_same_episode_written_by_bag_writer(live, tmp_path):
    """The recorder writes through BagWriter: same custom data (episodes per split), topics,
    types, counts, offered QoS and type hashes as a generated bag of the same episode."""
    live.command()
    for action in (WALK, TURN, EOS):
        live.policy_acts(action)
    live.recorder.destroy_node()  # closes the bag
    recorded = live.recorder.bag_dir
    [record] = read(recorded)[0]
    with BagWriter(tmp_path / "written") as writer:
        writer.write_episode(record.episode, graph=record.episode.meta["command_graph"])
    live_info, written_info = read_bag_info(recorded), read_bag_info(tmp_path / "written")
    assert live_info.custom == written_info.custom
    assert live_info.splits == {"live": 1} and live_info.closed
    assert _topic_metadata(recorded) == _topic_metadata(tmp_path / "written")
    assert _channel_metadata(recorded) == _channel_metadata(tmp_path / "written")
    assert list(iter_bag_episodes(recorded)) == list(iter_bag_episodes(tmp_path / "written"))
