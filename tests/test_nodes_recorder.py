"""episode_recorder_node in an in-process stack: every episode is in the bag with its outcome,
only complete ones are demonstrations, and a preempted episode keeps exactly its own actions."""
import random
import re
import time

import pytest
import rclpy
import yaml
from actionlib_msgs.msg import GoalStatus
from mcap.reader import make_reader
from std_msgs.msg import String

from gscan_ros import episode_status as es
from gscan_ros import interface
from gscan_ros.data.bag import BagEpisodeReader, BagWriter, read_bag_info
from gscan_ros.data.sources import sample_episode
from gscan_ros.language import get_parser
from gscan_ros.nodes.commander import Outcome
from gscan_ros.nodes.common import EVENT_QOS
from gscan_ros.nodes.episode_recorder_node import EpisodeRecorderNode
from gscan_ros.world.types import Action
from gscan_ros.world.world import World
from msg_adapters import (
    action_to_cdr,
    cdr_to_episode_status,
    episode_status_to_cdr,
    graph_to_cdr,
    grid_header,
    observation_to_cdr,
    reset_to_cdr,
    situation_to_cdr,
    text_to_cdr,
)

from ros_helpers import fresh_domain_id, in_process_stack, parameters

WALK, TURN, EOS = Action.WALK, Action.TURN_LEFT, Action.EOS
TIMEOUT = 30.0
COMMAND = "walk to a red circle"


def _topic_metadata(bag_dir):
    """Topic -> (type, offered QoS, type hash) as metadata.yaml records them."""
    info = yaml.safe_load((bag_dir / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    return {t["topic_metadata"]["name"]: (t["topic_metadata"]["type"], t["topic_metadata"]["offered_qos_profiles"],
                                          t["topic_metadata"].get("type_description_hash"))
            for t in info["topics_with_message_count"]}


def read(bag_dir, include_incomplete=False):
    reader = BagEpisodeReader(bag_dir, include_incomplete=include_incomplete)
    return list(reader.records()), reader.report


def close(stack, probe):
    """Take the recorder off the executor spinning in the background, then close its bag."""
    probe.executor.remove_node(stack.recorder)
    time.sleep(0.5)  # a callback already running finishes
    stack.recorder.destroy_node()
    return stack.recorder.bag_dir


def test_a_cut_episode_is_recorded_with_its_outcome_and_is_no_demonstration(probe, commander, checkpoint, tmp_path):
    stack = in_process_stack(probe, checkpoint, [WALK, TURN, EOS], bag_dir=tmp_path / "bag")
    commander.wait_until_ready(TIMEOUT)
    commander.spin_until(lambda: stack.recorder.ready, TIMEOUT, "the recorder")
    done = commander.run_episode(COMMAND, timeout=TIMEOUT)
    stack.policy_node.set_parameters(parameters(max_steps=1))
    cut = commander.run_episode("walk to a small circle", timeout=TIMEOUT)
    assert (done.outcome, cut.outcome, cut.actions) == (Outcome.SUCCEEDED, Outcome.MAX_STEPS, [WALK, EOS])
    commander.spin_until(lambda: stack.recorder.episodes == 2, TIMEOUT, "both episodes recorded")
    bag = close(stack, probe)
    [demo], report = read(bag)
    assert demo.episode.actions == (WALK, TURN) and demo.episode.command == COMMAND and demo.episode.split == "live"
    assert report.outcomes == {es.CUT: 1} and report.lost_episodes == 0 and report.complete
    both, _ = read(bag, include_incomplete=True)
    assert [(r.outcome, r.episode.actions) for r in both] == [(es.COMPLETE, (WALK, TURN)), (es.CUT, (WALK,))]
    assert both[1].header["outcome"] == es.CUT and both[1].episode.meta["episode_id"] == cut.episode_id
    info = read_bag_info(bag)
    assert (info.episodes, info.splits, info.topics["/command"].message_count) == (2, {"live": 1}, 2)


def test_a_preempted_episode_keeps_exactly_its_own_actions(probe, commander, checkpoint, tmp_path):
    """Command B mid-episode and C 1-6 ms later, ten rounds: every recorded episode holds the
    actions the policy reported for it, and no preempted one counts as complete."""
    stack = in_process_stack(probe, checkpoint, [WALK, TURN], max_steps=100_000, bag_dir=tmp_path / "bag")
    commander.wait_until_ready(TIMEOUT)
    commander.spin_until(lambda: stack.recorder.ready, TIMEOUT, "the recorder")
    # The stack spins in the probe's executor: this test listens and publishes through the commander's.
    reports, actions = [], []
    commander.create_subscription(GoalStatus, "episode_status", reports.append, EVENT_QOS, raw=True)
    commander.create_subscription(String, "action", actions.append, EVENT_QOS)
    commands = commander.create_publisher(String, "command", EVENT_QOS)
    commander.spin_until(lambda: commands.get_subscription_count() >= 1, TIMEOUT, "the parser")
    def started(text, after_ns):
        """The policy reported an ACTIVE episode of `text` that it took after `after_ns`."""
        return any((r := cdr_to_episode_status(m)).outcome == es.ACTIVE and r.text == text and r.start_ns > after_ns
                   for m in reports)

    rng = random.Random(5)
    for round_ in range(10):
        sent = time.time_ns()
        commands.publish(String(data="walk to a red circle"))
        commander.spin_until(lambda sent=sent: started("walk to a red circle", sent), TIMEOUT, f"round {round_}'s A")
        wanted = len(actions) + rng.randint(3, 15)
        commander.spin_until(lambda wanted=wanted: len(actions) >= wanted, TIMEOUT, f"round {round_}'s actions")
        sent = time.time_ns()
        commands.publish(String(data="walk to a blue circle"))
        time.sleep(rng.uniform(0.001, 0.006))
        commands.publish(String(data="walk to a green circle"))
        # The policy takes every graph in order: a B that C follows closely is started and preempted at once.
        commander.spin_until(lambda sent=sent: started("walk to a green circle", sent), TIMEOUT,
                             f"round {round_}'s C")
    # Each round's A and B are preempted, and so is each C: by the next round's A, the last
    # one by the commander's command (sent once the last C runs: it comes through another writer).
    stack.policy_node.set_parameters(parameters(max_steps=2))
    final = commander.run_episode("walk to a circle", timeout=TIMEOUT)
    assert final.outcome is Outcome.MAX_STEPS, [(r.episode_id, r.outcome, r.text) for r in map(
        cdr_to_episode_status, reports)][-6:]

    def ended():
        return sum(cdr_to_episode_status(r).ended for r in reports)

    deadline = time.monotonic() + TIMEOUT
    while time.monotonic() < deadline and not (ended() >= 31 and stack.recorder.episodes == ended()):
        commander.spin_for(0.05)
    assert ended() >= 31 and stack.recorder.episodes == ended(), (ended(), stack.recorder.episodes)
    bag = close(stack, probe)
    told = {}
    for msg in reports:
        report = cdr_to_episode_status(msg)
        if report.ended:
            told[report.episode_id] = (report.outcome, int(re.search(r"after (\d+) actions", report.text)[1])
                                       if report.outcome == es.PREEMPTED else None)
    records, report = read(bag, include_incomplete=True)
    preempted = {r.episode.meta["episode_id"]: len(r.episode.actions) for r in records if r.outcome == es.PREEMPTED}
    assert len(preempted) >= 30
    assert preempted == {i: n for i, (outcome, n) in told.items() if outcome == es.PREEMPTED}
    assert read(bag)[0] == [] and report.lost_episodes == 0  # nothing here was a complete demonstration


def test_the_typed_command_is_kept_beside_the_canonical_one(probe, commander, checkpoint, tmp_path):
    stack = in_process_stack(probe, checkpoint, [EOS], bag_dir=tmp_path / "bag")
    commander.wait_until_ready(TIMEOUT)
    commander.spin_until(lambda: stack.recorder.ready, TIMEOUT, "the recorder")
    commander.run_episode("walk to a large circle", timeout=TIMEOUT)
    commander.run_episode("walk to a big circle", timeout=TIMEOUT)
    commander.spin_until(lambda: stack.recorder.episodes == 2, TIMEOUT, "both episodes")
    [paraphrased, canonical], _ = read(close(stack, probe))
    assert paraphrased.episode.command == canonical.episode.command == "walk to a big circle"
    assert paraphrased.episode.meta["typed_command"] == "walk to a large circle"
    assert "typed_command" not in canonical.episode.meta
    assert paraphrased.episode.meta["recorded_by"] == "/episode_recorder_node"


def test_a_live_bag_has_the_layout_of_the_same_episode_written_by_bag_writer(probe, commander, checkpoint,
                                                                             tmp_path):
    """The same topics and types, offered QoS and type hashes, and the same episode back."""
    stack = in_process_stack(probe, checkpoint, [WALK, TURN, EOS], bag_dir=tmp_path / "bag")
    commander.wait_until_ready(TIMEOUT)
    commander.spin_until(lambda: stack.recorder.ready, TIMEOUT, "the recorder")
    commander.run_episode(COMMAND, timeout=TIMEOUT)
    commander.spin_until(lambda: stack.recorder.episodes == 1, TIMEOUT, "the episode")
    recorded = close(stack, probe)
    [record], _ = read(recorded)
    with BagWriter(tmp_path / "written") as writer:
        writer.write_episode(record.episode, graph=record.episode.meta["command_graph"])
    live, written = _topic_metadata(recorded), _topic_metadata(tmp_path / "written")
    assert set(written) <= set(live)
    assert {t: live[t] for t in written} == written
    [again], _ = read(tmp_path / "written")
    assert (again.episode.command, again.episode.actions, again.episode.situation) == (
        record.episode.command, record.episode.actions, record.episode.situation)


def test_memory_does_not_grow_with_what_is_published(probe, tmp_path):
    """Every message goes to the bag as it arrives: 40 situations of 2 MB cost what one
    does (the recorder once held up to 2,000 messages per topic: 100 x 5 MB took 560 MB)."""
    import tracemalloc

    from gscan_ros import interface
    from gscan_ros.nodes.episode_recorder_node import EpisodeRecorderNode
    from msg_adapters import text_to_cdr

    node = EpisodeRecorderNode(context=probe.context, parameter_overrides=parameters(bag_dir=str(tmp_path / "bag")))
    big = text_to_cdr("x" * 2_000_000)
    tracemalloc.start()
    try:
        for i in range(40):
            node._record(interface.SITUATION, big, {"source_timestamp": i, "received_timestamp": i})
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
        node.destroy_node()
    assert peak < 12_000_000, peak
    assert read_bag_info(tmp_path / "bag").topics["/situation"].message_count == 40


class Feed:
    """The stack's messages handed to a recorder as its subscriptions would (no spinning),
    published 1 µs apart: the world's state, the policy's reports and actions."""

    def __init__(self, recorder: EpisodeRecorderNode, seed: int = 3):
        self.recorder = recorder
        self.episode = sample_episode(seed)
        self.world = World(self.episode.situation)
        self.graph = get_parser("semantic").parse(self.episode.command)
        self.now = time.time_ns()

    def __call__(self, endpoint: interface.Endpoint, data: bytes) -> None:
        self.now += 1000
        self.recorder._record(endpoint, data, {"source_timestamp": self.now, "received_timestamp": self.now + 1})

    def state(self) -> None:
        self(interface.SITUATION, situation_to_cdr(self.world.snapshot()))
        self(interface.OBSERVATION, observation_to_cdr(self.world.encode(), header=grid_header(self.now)))

    def joined(self) -> None:
        """The latched samples a subscriber gets on joining."""
        self(interface.WORLD_RESET, reset_to_cdr(self.now))
        self.state()
        self(interface.COMMAND_GRAPH, graph_to_cdr(self.graph))

    def report(self, n: int, outcome: str, start_ns: int | None = None) -> None:
        """Episode `n`'s report; `start_ns` (default `n`) tells apart two policies' episodes of one id."""
        self(interface.EPISODE_STATUS, episode_status_to_cdr(
            es.EpisodeStatus(f"/policy_node/{n}", n if start_ns is None else start_ns, outcome, self.episode.command)))

    def act(self, *actions: Action) -> None:
        for action in actions:
            self(interface.ACTION, action_to_cdr(action))
            if action is not Action.EOS:
                self.world.step(action)
                self.state()

    def whole_episode(self, n: int) -> None:
        """The planner's demonstration of the command, from where the world is now."""
        from gscan_ros.world import demonstrate

        actions = demonstrate(self.world.snapshot(), self.episode.command)
        self(interface.COMMAND, text_to_cdr(self.episode.command))
        self(interface.COMMAND_GRAPH, graph_to_cdr(self.graph))
        self.report(n, es.ACTIVE)
        self.act(*actions, Action.EOS)
        self.report(n, es.COMPLETE)


@pytest.fixture
def recorder(probe, tmp_path):
    """A recorder of `tmp_path/bag` (with `overwrite`); the test destroys it, which closes the bag."""
    return EpisodeRecorderNode(context=probe.context, parameter_overrides=parameters(
        bag_dir=str(tmp_path / "bag"), overwrite=True))


def test_a_policy_restarted_mid_episode_leaves_both_episodes_of_its_reused_id_apart(recorder, tmp_path):
    """A policy killed mid-episode sends no end; restarted, it numbers its episodes from 1
    again. The recorder ends the dead one PREEMPTED just before the new one starts."""
    from gscan_ros.world import demonstrate

    feed = Feed(recorder)
    feed.joined()
    feed.report(1, es.ACTIVE, start_ns=10)
    feed.act(Action.TURN_LEFT)  # killed here
    actions = demonstrate(feed.world.snapshot(), feed.episode.command)
    feed.report(1, es.ACTIVE, start_ns=20)  # the restarted policy's first episode
    feed.act(*actions, Action.EOS)
    feed.report(1, es.COMPLETE, start_ns=20)
    recorder.destroy_node()
    records, report = read(tmp_path / "bag", include_incomplete=True)
    assert [(r.outcome, r.episode.actions) for r in records] == [(es.PREEMPTED, (Action.TURN_LEFT,)),
                                                                 (es.COMPLETE, tuple(actions))]
    assert report.complete and read_bag_info(tmp_path / "bag").episodes == 2


def test_a_recorder_that_joins_mid_episode_writes_a_whole_bag(recorder, tmp_path):
    """The end of the episode that ran when it joined is recorded but not counted; the bag reads complete."""
    feed = Feed(recorder)
    feed.joined()
    feed.act(Action.TURN_LEFT)
    feed.report(1, es.PREEMPTED)
    feed.whole_episode(2)
    recorder.destroy_node()
    records, report = read(tmp_path / "bag", include_incomplete=True)
    assert [(r.outcome, r.episode.meta["episode_id"]) for r in records] == [(es.COMPLETE, "/policy_node/2")]
    assert report.complete and report.drop_reasons == {} and read_bag_info(tmp_path / "bag").episodes == 1


def test_a_new_bag_dir_mid_episode_ends_it_in_the_old_bag_and_leaves_both_bags_whole(recorder, tmp_path):
    feed = Feed(recorder)
    feed.joined()
    feed.report(1, es.ACTIVE)
    feed.act(Action.TURN_LEFT, Action.WALK)
    lines, info = [], recorder.status.info
    recorder.status.info = lambda text: (lines.append(text), info(text))
    [result] = recorder.set_parameters(parameters(bag_dir=str(tmp_path / "second")))
    assert result.successful
    assert lines[0] == f"recorded episode 0 (/policy_node/1: {es.PREEMPTED}, the recording moved to {tmp_path}/second)"
    feed.act(Action.TURN_RIGHT, Action.EOS)
    feed.report(1, es.COMPLETE)
    feed.whole_episode(2)
    recorder.destroy_node()
    [first], first_report = read(tmp_path / "bag", include_incomplete=True)
    assert (first.outcome, first.episode.actions) == (es.PREEMPTED, (Action.TURN_LEFT, Action.WALK))
    assert first.header["outcome"] == es.PREEMPTED and first_report.complete
    assert read_bag_info(tmp_path / "bag").episodes == 1
    [second], second_report = read(tmp_path / "second", include_incomplete=True)
    assert (second.outcome, second.episode.meta["episode_id"]) == (es.COMPLETE, "/policy_node/2")
    assert second_report.complete and read_bag_info(tmp_path / "second").episodes == 1


def test_a_new_bag_starts_with_the_current_state_received_at_the_switch(recorder, tmp_path):
    """The latched samples are written into the new bag as a subscriber joining then gets
    them: received at the switch, in publish order, not at the times they first came."""
    feed = Feed(recorder)
    feed.now -= 600 * 10**9  # the world's state was published ten minutes ago
    feed.joined()
    switched = time.time_ns()
    [result] = recorder.set_parameters(parameters(bag_dir=str(tmp_path / "second")))
    assert result.successful
    recorder.destroy_node()
    with open(next((tmp_path / "second").glob("*.mcap")), "rb") as f:
        messages = [(c.topic, m.log_time, m.publish_time) for _, c, m in make_reader(f).iter_messages()]
    assert {topic for topic, _, _ in messages} == {"/world_reset", "/situation", "/observation", "/command_graph"}
    assert all(log >= switched for _, log, _ in messages)
    assert [publish for _, _, publish in messages] == sorted(publish for _, _, publish in messages)
    assert read_bag_info(tmp_path / "second").start_ns >= switched


def test_the_bag_being_recorded_is_refused_as_a_new_bag_dir(recorder, tmp_path):
    """With `overwrite` too: opening it again would wipe it under its own writer."""
    feed = Feed(recorder)
    feed.joined()
    feed.whole_episode(1)
    for same in (tmp_path / "bag", tmp_path / "bag" / ".." / "bag"):
        [refused] = recorder.set_parameters(parameters(bag_dir=str(same)))
        assert not refused.successful and "is the bag being recorded" in refused.reason
    feed.whole_episode(2)
    recorder.destroy_node()
    records, report = read(tmp_path / "bag")
    assert len(records) == 2 and report.complete and read_bag_info(tmp_path / "bag").episodes == 2


def test_ctrl_c_mid_episode_closes_the_bag_with_the_episode_preempted(tmp_path):
    """A context shut down before the node is destroyed (rclpy's own SIGINT handler does
    that; `run` does not): the recorder cannot publish its last status lines then, and
    still closes a whole bag."""
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=fresh_domain_id())
    recorder = EpisodeRecorderNode(context=context, parameter_overrides=parameters(bag_dir=str(tmp_path / "bag")))
    feed = Feed(recorder)
    feed.joined()
    feed.report(1, es.ACTIVE)
    feed.act(Action.TURN_LEFT)
    context.shutdown()
    recorder.destroy_node()
    [record], report = read(tmp_path / "bag", include_incomplete=True)
    assert (record.outcome, record.episode.actions) == (es.PREEMPTED, (Action.TURN_LEFT,))
    assert report.complete and read_bag_info(tmp_path / "bag").closed


def test_a_disk_that_refuses_writes_stops_the_bag_with_one_error_until_bag_dir_changes(recorder, tmp_path,
                                                                                      monkeypatch):
    """A full disk: the bag stops where it is (its ended episodes read back), the error is
    reported once, not again for every message after it (the recorder's own error line is
    one of them), and a new bag_dir records again from the current state."""
    import errno

    feed = Feed(recorder)
    feed.joined()
    feed.whole_episode(1)
    errors, error = [], recorder.status.error
    recorder.status.error = lambda text: (errors.append(text), error(text))

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(recorder._writer, "add_record", full)
    feed.report(2, es.ACTIVE)
    for _ in range(5):  # what follows, its own status line among it, is not written and not reported
        feed(interface.STATUS, text_to_cdr(errors[-1]))
        feed.act(Action.WALK)
    assert len(errors) == 1 and errors[0].startswith(f"recording stopped: {tmp_path}/bag cannot be written "
                                                      "(No space left on device)")
    [first], _ = read(tmp_path / "bag")
    assert first.episode.meta["episode_id"] == "/policy_node/1"
    [result] = recorder.set_parameters(parameters(bag_dir=str(tmp_path / "second")))
    assert result.successful
    feed.whole_episode(3)
    recorder.destroy_node()
    [second], report = read(tmp_path / "second")
    assert second.episode.meta["episode_id"] == "/policy_node/3" and report.complete
