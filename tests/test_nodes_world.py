"""world_simulator_node in-process: lock-step replies, rejected and stale actions, reset_world."""
import json
import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from sensor_msgs.msg import Image
from std_msgs.msg import Header, String
from std_srvs.srv import Trigger

from gscan_ros import interface
from gscan_ros.data.bag import write_bag
from gscan_ros.data.sources import sample_episode
from gscan_ros.errors import DatasetFormatError
from gscan_ros.interface import GRID_FRAME
from gscan_ros.nodes.common import EVENT_QOS, LATCHED_LOG_QOS, qos_profile
from gscan_ros.nodes.world_simulator_node import WorldSimulatorNode
from gscan_ros.world import World
from gscan_ros.world.types import Action
from msg_adapters import cdr_to_observation, cdr_to_reset, cdr_to_text, image_header, text_to_cdr, time_ns

from ros_helpers import parameters, source_info


@pytest.fixture
def world(probe):
    """(node, observations, status) with the node serving random seed 3, no images."""
    observations = probe.record("observation", Image, LATCHED_LOG_QOS, raw=True)
    status = probe.record("status", String, EVENT_QOS)
    node = WorldSimulatorNode(context=probe.context, parameter_overrides=parameters(seed=3, publish_images=False))
    probe.executor.add_node(node)
    probe.spin_until(lambda: len(observations) == 1, what="the initial observation")
    return node, observations, status


def encoding_after(situation, *actions):
    world = World(situation)
    for action in actions:
        world.step(action)
    return world.encode()


def test_initial_state_is_the_seeds_situation(world):
    node, observations, _ = world
    np.testing.assert_array_equal(cdr_to_observation(observations[0]), encoding_after(sample_episode(3).situation))


def test_each_action_gets_one_observation_of_the_new_state(probe, world):
    node, observations, _ = world
    for replies, token in enumerate(("turn left", "walk"), start=2):  # lock-step: one at a time
        node.on_action(text_to_cdr(token), source_info())
        probe.spin_until(lambda replies=replies: len(observations) == replies, what=f"the reply to {token!r}")
    expected = encoding_after(sample_episode(3).situation, Action.TURN_LEFT, Action.WALK)
    np.testing.assert_array_equal(cdr_to_observation(observations[-1]), expected)


def test_invalid_action_is_reported_and_the_unchanged_state_resent(probe, world):
    node, observations, status = world
    before = node.world.encode()
    node.on_action(text_to_cdr("fly away"), source_info())
    probe.spin_until(lambda: len(observations) == 2, what="the reply to a rejected action")
    probe.spin_until(lambda: any("rejected action" in s.data for s in status), what="a status line")
    np.testing.assert_array_equal(node.world.encode(), before)
    np.testing.assert_array_equal(cdr_to_observation(observations[-1]), before)
    assert any("'fly away'" in s.data for s in status)


def test_a_status_line_quotes_a_rejected_input_as_it_was_sent(probe, world):
    """'turn  left' (two spaces) is unknown; folding the line must not make the quote read 'turn left'."""
    node, observations, status = world
    node.on_action(text_to_cdr("turn  left\nnow"), source_info())
    probe.spin_until(lambda: any("rejected action" in s.data for s in status), what="a status line")
    [line] = [s.data for s in status if "rejected action" in s.data]
    assert "'turn  left\\nnow'" in line and "\n" not in line, line


def test_bytes_that_are_no_string_are_one_rejection_and_the_node_serves_on(probe, world):
    node, observations, status = world
    node.on_action(b"\x00\x01\x00\x00\xff\xff", source_info())
    probe.spin_until(lambda: any("serialized std_msgs/String needs at least 8 bytes" in s.data for s in status),
                     what="the rejection")
    node.on_action(text_to_cdr("stay"), source_info())
    probe.spin_until(lambda: len(observations) == 2, what="the reply to the next action")


def test_action_sent_before_a_reset_is_ignored_without_reply(probe, world):
    node, observations, status = world
    node.on_action(text_to_cdr("walk"), source_info(t_ns=1))  # predates the node's (re)set
    node.on_action(text_to_cdr("turn right"), source_info())
    expected = encoding_after(sample_episode(3).situation, Action.TURN_RIGHT)
    probe.spin_until(lambda: np.array_equal(cdr_to_observation(observations[-1]), expected),
                     what="the reply to the current action")
    assert len(observations) == 2  # the initial state and one reply: none for the stale walk
    probe.spin_until(lambda: any("before the world was reset" in s.data for s in status), what="a stale notice")


def test_eos_ends_the_episode_with_a_status_line(probe, world):
    node, observations, status = world
    for replies in (2, 3):
        node.on_action(text_to_cdr("stay"), source_info())
        probe.spin_until(lambda replies=replies: len(observations) == replies, what="a reply")
    node.on_action(text_to_cdr("<eos>"), source_info())
    probe.spin_until(lambda: any("episode ended after 2 actions" in s.data for s in status), what="episode end")
    node.on_action(text_to_cdr("stay"), source_info())
    probe.spin_until(lambda: len(observations) == 4, what="the next reply")
    assert not any(m.data.endswith("after 3 actions") for m in status)


def test_reset_world_serves_the_next_seed(probe, world):
    node, observations, _ = world
    client = probe.node.create_client(Trigger, "reset_world")
    probe.spin_until(client.service_is_ready, what="reset_world")
    future = client.call_async(Trigger.Request())
    probe.spin_until(future.done, what="the reset response")
    assert future.result().success
    assert "seed 4" in future.result().message
    expected = encoding_after(sample_episode(4).situation)
    # Any number of re-deliveries of the latched first observation may come before it.
    probe.spin_until(lambda: len(observations) >= 2 and np.array_equal(cdr_to_observation(observations[-1]), expected),
                     what="the new situation")


def test_dataset_split_is_served_in_order_and_wraps_around(probe, tmp_path):
    episodes = [sample_episode(seed) for seed in range(3)]
    write_bag(tmp_path / "bag", episodes)
    node = WorldSimulatorNode(
        context=probe.context,
        parameter_overrides=parameters(dataset=str(tmp_path / "bag"), split="random", index=1, publish_images=False),
    )
    served = [node.world.encode()]
    for _ in range(2):
        node.on_reset_world(Trigger.Request(), Trigger.Response())
        served.append(node.world.encode())
    for got, episode in zip(served, (episodes[1], episodes[2], episodes[0])):
        np.testing.assert_array_equal(got, encoding_after(episode.situation))
    node.destroy_node()


def test_an_index_past_the_end_of_the_split_is_a_start_up_error(probe, tmp_path):
    """Not a silent start at example 0: the split has no example of that index."""
    write_bag(tmp_path / "bag", [sample_episode(seed) for seed in range(3)])
    with pytest.raises(DatasetFormatError, match=r"split 'random' has no example 3 \(the index is past its end\)"):
        WorldSimulatorNode(context=probe.context, parameter_overrides=parameters(
            dataset=str(tmp_path / "bag"), split="random", index=3, publish_images=False))


def test_missing_dataset_is_a_start_up_error(probe):
    with pytest.raises(DatasetFormatError):
        WorldSimulatorNode(context=probe.context, parameter_overrides=parameters(dataset="/no/such/dataset.txt"))


def dataset_with_a_bad_second_example(tmp_path, then=(), **bad):
    """dataset.txt whose 'test' split has a good example, then one with `bad` situation fields,
    then the examples of the seeds `then`."""
    from gscan_ros.data.dataset import DatasetHeader, Example, example_line, write_dataset_json
    from gscan_ros.language import tokenize

    def example(seed):
        episode = sample_episode(seed)
        return Example(tokenize(episode.command), episode.situation, episode.actions)

    broken = example(0).to_json()
    broken["situation"].update(bad)
    return write_dataset_json(tmp_path / "dataset.txt", DatasetHeader(),
                              {"test": [example_line(example(0)), json.dumps(broken),
                                        *(example_line(example(seed)) for seed in then)]})


def call_reset(probe):
    client = probe.node.create_client(Trigger, "reset_world")
    probe.spin_until(client.service_is_ready, what="reset_world")
    future = client.call_async(Trigger.Request())
    probe.spin_until(future.done, what="the reset response")
    return future.result()


def test_reset_to_an_unsupported_grid_size_fails_cleanly_and_the_node_keeps_serving(probe, tmp_path):
    observations = probe.record("observation", Image, LATCHED_LOG_QOS, raw=True)
    status = probe.record("status", String, EVENT_QOS)
    dataset = dataset_with_a_bad_second_example(tmp_path, grid_size=100_000)
    node = WorldSimulatorNode(context=probe.context,
                              parameter_overrides=parameters(dataset=str(dataset), publish_images=False))
    probe.executor.add_node(node)
    before = node.world.encode()
    result = call_reset(probe)
    assert not result.success
    assert "reset failed, world unchanged" in result.message and "grid_size': 100000 is not supported" in result.message
    np.testing.assert_array_equal(node.world.encode(), before)
    probe.spin_until(lambda: any("100000 is not supported" in s.data for s in status), what="the failure on status")
    node.on_action(text_to_cdr("turn left"), source_info())  # still serving
    probe.spin_until(lambda: len(observations) == 2, what="the reply to an action after the failed reset")


def test_a_malformed_example_fails_its_reset_and_the_examples_after_it_are_served(probe, tmp_path):
    """The next reset serves the example after the bad one (not example 0), and a node
    started beyond it reaches its own example."""
    dataset = dataset_with_a_bad_second_example(tmp_path, then=(7,), grid_size=100_000)
    node = WorldSimulatorNode(context=probe.context,
                              parameter_overrides=parameters(dataset=str(dataset), publish_images=False))
    failed = node.on_reset_world(Trigger.Request(), Trigger.Response())
    assert not failed.success and "example 1 of split 'test'" in failed.message
    served = node.on_reset_world(Trigger.Request(), Trigger.Response())
    assert served.success and "example 2" in served.message
    np.testing.assert_array_equal(node.world.encode(), encoding_after(sample_episode(7).situation))
    node.destroy_node()
    beyond = WorldSimulatorNode(context=probe.context, parameter_overrides=parameters(
        dataset=str(dataset), index=2, publish_images=False))
    np.testing.assert_array_equal(beyond.world.encode(), encoding_after(sample_episode(7).situation))
    beyond.destroy_node()


def test_a_new_episode_counts_its_actions_from_zero(probe, world):
    """A preempted episode sends no <eos>: the policy's ACTIVE report starts the count again
    (with the new episode's first action when that overtook the report); garbage on
    episode_status is one rejection."""
    from gscan_ros import episode_status as es
    from msg_adapters import episode_status_to_cdr

    node, observations, status = world

    def active(n):
        return episode_status_to_cdr(es.EpisodeStatus(f"/policy_node/{n}", 1, es.ACTIVE, "walk to a circle"))

    def act(token, replies):
        node.on_action(text_to_cdr(token), source_info())
        probe.spin_until(lambda: len(observations) == replies, what=f"the reply to {token!r}")

    act("stay", 2)  # the episode that is preempted
    node.on_episode_status(active(2), source_info())
    act("stay", 3)
    node.on_action(text_to_cdr("<eos>"), source_info())
    probe.spin_until(lambda: any("episode ended after 1 actions" in s.data for s in status), what="the first end")
    act("stay", 4)  # preempted too
    started_ns = time.time_ns()
    act("stay", 5)  # the next episode's first action, before its report
    node.on_episode_status(active(3), source_info(t_ns=started_ns))
    node.on_action(text_to_cdr("<eos>"), source_info())
    probe.spin_until(lambda: sum("episode ended after 1 actions" in s.data for s in status) == 2, what="the end")
    node.on_episode_status(b"\x00\x01\x00\x00\xff", source_info())
    probe.spin_until(lambda: any("GoalStatus" in s.data for s in status), what="the rejection")


def test_any_exception_in_reset_world_is_a_failed_response_not_a_dead_node(probe, world):
    node, observations, status = world

    def exhausted():
        raise MemoryError("no room for the next situation")

    node._source.next = exhausted
    result = call_reset(probe)
    assert not result.success and "MemoryError: no room for the next situation" in result.message
    probe.spin_until(lambda: any("internal error in on_reset_world" in s.data for s in status), what="a status line")
    node.on_action(text_to_cdr("stay"), source_info())
    probe.spin_until(lambda: len(observations) == 2, what="a reply after the failed reset")


def test_a_bug_every_call_hits_logs_its_traceback_once_and_a_status_line_each_time(probe, world, monkeypatch):
    """A flood of messages that all hit one bug must not write a traceback per message."""
    node, _, status = world
    logged = []
    logger = node.get_logger()
    monkeypatch.setattr(logger, "error", lambda text, *a, **k: logged.append(text))

    def exhausted():
        raise MemoryError("no room for the next situation")

    node._source.next = exhausted
    for _ in range(5):
        assert not call_reset(probe).success
    assert sum("Traceback" in line for line in logged) == 1
    probe.spin_until(lambda: sum("internal error in on_reset_world" in s.data for s in status) == 5,
                     what="a status line per call")


def test_each_load_publishes_its_reset_time_before_the_new_state(probe, world):
    node, observations, _ = world
    resets = probe.record("world_reset", Header, LATCHED_LOG_QOS, raw=True)
    probe.spin_until(lambda: resets, what="the latched start-up reset")
    first = cdr_to_reset(resets[0])
    assert call_reset(probe).success
    probe.spin_until(lambda: len(resets) == 2 and len(observations) == 2, what="the reset and the new state")
    assert first < cdr_to_reset(resets[1]) == node._reset_ns


def test_a_late_subscriber_to_a_latched_topic_gets_only_the_current_world(probe, world):
    """What `ros2 topic echo --once /situation` shows after steps and a reset: the new world,
    one sample per latched topic, nothing stale (the writers keep depth 1)."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    node, observations, _ = world
    for action in (Action.WALK, Action.TURN_LEFT, Action.WALK):
        node.on_action(text_to_cdr(action.token), source_info())
    node.on_reset_world(Trigger.Request(), Trigger.Response())
    current = node.world.snapshot()
    echo_qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)  # what echo asks of a latched topic
    late = {"situation": [], "observation": [], "world_reset": []}

    def keep(topic):  # this test's world only (a participant of an earlier test may linger in the domain)
        return lambda msg, info: late[topic].append(msg) if info["source_timestamp"] >= probe.created_ns else None

    for topic, msg_type in (("situation", String), ("observation", Image), ("world_reset", Header)):
        probe.node.create_subscription(msg_type, topic, keep(topic), echo_qos, raw=True)
    probe.spin_until(lambda: all(late.values()), what="the latched samples")
    for _ in range(25):  # anything else the writers still hold would arrive now
        probe.executor.spin_once(timeout_sec=0.02)
    assert [len(v) for v in late.values()] == [1, 1, 1]
    assert json.loads(cdr_to_text(late["situation"][0])) == current.to_json()
    assert np.array_equal(cdr_to_observation(late["observation"][0]), World(current).encode())
    # Stamped with the time the world reached that state (here: the reset), in the grid frame.
    header = image_header(late["observation"][0])
    assert (time_ns(header.stamp), header.frame_id) == (node.state_ns, GRID_FRAME)
    assert node.state_ns == cdr_to_reset(late["world_reset"][0])


def test_diagnostics_carry_the_level_of_the_last_status_line(probe, world):
    """OK while serving, WARN after a rejected input, ERROR after an internal error (docs/ros.md "Health")."""
    node, _, _ = world
    diagnostics = probe.record("/diagnostics", DiagnosticArray, qos_profile(interface.DIAGNOSTICS, depth=100))

    def newest(level):
        def arrived():
            mine = [s for a in diagnostics for s in a.status if s.name == node.get_fully_qualified_name()]
            return mine and mine[-1].level == level and mine[-1]
        return arrived

    probe.spin_until(newest(DiagnosticStatus.OK), what="an OK status at 1 Hz")
    node.on_action(text_to_cdr("fly"), source_info())
    probe.spin_until(newest(DiagnosticStatus.WARN), what="WARN after a rejected action")
    status = newest(DiagnosticStatus.WARN)()
    assert "rejected action 'fly'" in status.message and status.hardware_id == "gscan_ros"
    assert {v.key: v.value for v in status.values}["rejected inputs"] == "1"
    assert call_reset(probe).success
    probe.spin_until(newest(DiagnosticStatus.OK), what="OK after the next event")
    node._source.next = lambda: 1 / 0
    assert not call_reset(probe).success
    probe.spin_until(newest(DiagnosticStatus.ERROR), what="ERROR after an internal error")


def test_a_huge_action_is_reported_in_one_short_line_without_copying_it(probe, world):
    """The node decodes the 20 MB of text once, and copies none of it."""
    import tracemalloc

    node, observations, status = world
    huge = text_to_cdr("walk" * 5_000_000)
    tracemalloc.start()
    try:
        node.on_action(huge, source_info())
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    probe.spin_until(lambda: any("20000000 chars" in s.data for s in status), what="the rejection")
    line = next(s.data for s in status if "20000000 chars" in s.data)
    assert len(line) <= len("world_simulator_node: ") + 300 and peak < 20_000_000 + 2_000_000, (len(line), peak)
