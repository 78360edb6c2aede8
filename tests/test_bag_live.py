"""Recordings of the live stack read back by the episode rule (episode_assembly): the policy's
reports delimit episodes, messages count in publication order whatever order a recorder
logged them in, and what a recorder missed of the world's state is replayed."""
import random

import numpy as np
import pytest
from mcap.reader import make_reader

from gscan_ros import episode_status as es
from gscan_ros.data.bag import LIVE_SPLIT, BagEpisodeReader, BagWriter, iter_bag_episodes, read_bag_info, write_bag
from gscan_ros.data.episode import Episode
from gscan_ros.errors import DatasetFormatError
from gscan_ros.language import get_parser
from gscan_ros.world.types import Action
from msg_adapters import text_to_cdr

from bag_support import LiveStack, make_episodes, mcap_file

PARSER = get_parser("semantic")


def _typed(command: str) -> str:
    """How a person types a command: the parser's graph names the canonical one."""
    return command.replace(" a ", " the ", 1).capitalize()


def _record(stack: LiveStack, bag, **kwargs):
    with BagWriter(bag) as writer:
        stack.record(writer, **kwargs)
    return bag


def _live(command: str, situation, actions) -> Episode:
    return Episode(command, situation, tuple(actions), split=LIVE_SPLIT, example_id=None)


def _file_order(bag) -> list[tuple[str, int]]:
    """(topic, publish time) of every message, in the order the recorder logged them."""
    with open(mcap_file(bag), "rb") as f:
        return [(c.topic, m.publish_time) for _, c, m in make_reader(f).iter_messages(log_time_order=False)]


def test_live_recording_with_real_times(tmp_path):
    """A recorder writes message by message as they arrive: the typed command is plain
    text, the policy follows its graph, and a command it refused is no episode."""
    episode = make_episodes(5, seed=2)[4]
    assert episode.actions
    graph = PARSER.parse(_typed(episode.command))
    stack = LiveStack(episode.situation)
    stack.state()
    stack.command("walk to a red circle", PARSER.parse("walk to a red circle"))
    stack.reject()
    stack.command(_typed(episode.command), graph)
    report = stack.start()
    for action in episode.actions:
        stack.act(action)
        stack.publish("status", text_to_cdr("stepping"))
    stack.act(Action.EOS)
    stack.end(report, es.COMPLETE)
    bag = _record(stack, tmp_path / "live")

    reader = BagEpisodeReader(bag, decode_states=True)
    [record] = list(reader.records())
    assert record.outcome == es.COMPLETE and "outcome" not in record.header
    assert record.episode == _live(graph.command, episode.situation, episode.actions)
    assert graph.command == episode.command != _typed(episode.command)
    assert record.episode.meta == {"recorded_by": "/episode_recorder_node", "parser": "semantic",
                                   "typed_command": _typed(episode.command), "episode_id": "/policy_node/2",
                                   "command_graph": graph}
    assert np.array_equal(record.states, episode.states())
    assert reader.report.outcomes == {"rejected": 1} and reader.report.episodes_read == 1
    assert reader.report.complete and reader.report.drop_reasons == {}
    info = read_bag_info(bag)
    assert info.start_ns == stack.messages[0][3] and info.episodes == 2 and info.splits == {LIVE_SPLIT: 1}
    assert info.topics["/status"].msg_type == "std_msgs/msg/String"


def test_messages_logged_out_of_publication_order_read_back(tmp_path):
    """A recorder logs each topic as it arrives, with its own latency: the log order differs
    from the publication order across topics; the reader restores the latter."""
    episodes = make_episodes(12, seed=4)
    graphs = {e.command: PARSER.parse(e.command) for e in episodes}
    write_bag(tmp_path / "published", episodes, graphs=graphs)
    latency = {"/episode": 3_000_000, "/situation": 2_000_000, "/command_graph": 2_500_000,
               "/episode_status": 1_200_000, "/observation": 900_000, "/action": 10_000, "/command": 0}
    with open(mcap_file(tmp_path / "published"), "rb") as f:
        published = [(c.topic, s.name, m.publish_time, m.data) for s, c, m in make_reader(f).iter_messages()]
    with BagWriter(tmp_path / "logged") as writer:
        for topic, msg_type, publish_ns, data in sorted(published, key=lambda m: m[2] + latency[m[0]]):
            channel = writer.channel_id(topic) or writer.register_channel(topic, msg_type)
            writer.add_record(topic, channel, data, publish_ns + latency[topic], publish_ns, 0)
        for episode in episodes:
            writer.count_episode(episode.split)
    logged = _file_order(tmp_path / "logged")
    assert sorted(logged, key=lambda m: m[1]) == [(t, p) for t, _, p, _ in published] != logged
    # Each episode's ACTIVE report is logged after its first action, its record after both.
    for i in range(len(episodes)):
        mine = [topic for topic, p in logged if p // 1_000_000_000 == i]
        assert mine.index("/episode") > mine.index("/episode_status") > mine.index("/action")

    reader = BagEpisodeReader(tmp_path / "logged", decode_states=True)
    records = list(reader.records())
    assert [r.episode for r in records] == episodes
    assert [r.episode.meta["command_graph"] for r in records] == [graphs[e.command] for e in episodes]
    for record, episode in zip(records, episodes):
        assert np.array_equal(record.states, episode.states())
    assert reader.report.complete


@pytest.fixture
def outcomes(tmp_path):
    """Four episodes on one world: complete, cut at max_steps, preempted, complete."""
    rng = random.Random(8)
    stack = LiveStack(make_episodes(1, seed=8)[0].situation)
    stack.state()
    expected = []
    for outcome in (es.COMPLETE, es.CUT, es.PREEMPTED, es.COMPLETE):
        command = f"walk to a {rng.choice(['red', 'blue'])} circle"
        situation, actions = stack.world.snapshot(), stack.route(rng, 5)
        stack.command(command, PARSER.parse(command))
        stack.episode(actions, outcome)
        expected.append((_live(command, situation, actions), outcome))
    return _record(stack, tmp_path / "outcomes"), expected


def test_cut_and_preempted_episodes_are_skipped_and_counted(outcomes):
    bag, expected = outcomes
    reader = iter_bag_episodes(bag)
    assert list(reader) == [expected[0][0], expected[3][0]]
    assert reader.report.outcomes == {"cut": 1, "preempted": 1}
    assert reader.report.episodes_read == 2 and reader.report.complete
    records = list(BagEpisodeReader(bag, include_incomplete=True).records())
    assert [(r.episode, r.outcome) for r in records] == expected
    assert [r.header.get("outcome") for r in records] == [None, "cut", "preempted", None]
    assert list(BagEpisodeReader(bag, splits=["train"], include_incomplete=True).records()) == []


def test_preempted_episodes_last_action_logged_late_stays_in_it(tmp_path):
    """The policy publishes its last action, then PREEMPTED when a new command comes, then
    ACTIVE; the recorder gets that action only after the next ACTIVE."""
    rng = random.Random(3)
    stack = LiveStack(make_episodes(1, seed=3)[0].situation)
    stack.state()
    start, first = stack.world.snapshot(), stack.route(rng, 4)
    stack.command("walk to a red circle", PARSER.parse("walk to a red circle"))
    preempted = stack.start()
    for action in first[:-1]:
        stack.act(action)
    late = stack.now + stack.step_ns
    stack.act(first[-1], late_ns=20 * stack.step_ns)  # the world replies, then the next command comes
    stack.command("walk to a blue circle", PARSER.parse("walk to a blue circle"))
    stack.end(preempted, es.PREEMPTED)
    middle, second = stack.world.snapshot(), stack.route(rng, 3)
    following = stack.episode(second)
    bag = _record(stack, tmp_path / "late")
    logged = _file_order(bag)
    assert logged.index(("/action", late)) > logged.index(("/episode_status", following.start_ns))

    records = list(BagEpisodeReader(bag, include_incomplete=True).records())
    assert [(r.episode, r.outcome) for r in records] == [
        (_live("walk to a red circle", start, first), es.PREEMPTED),
        (_live("walk to a blue circle", middle, second), es.COMPLETE)]


def test_missed_situations_and_observations_are_replayed(tmp_path):
    """The world publishes its situation after every step on a depth-1 latched topic: a busy
    recorder may keep only the first. Each episode starts where the actions since led."""
    rng = random.Random(5)
    stack = LiveStack(make_episodes(1, seed=5)[0].situation)
    stack.state()
    expected = []
    for command in ("walk to a red circle", "walk to a blue circle", "walk to a red circle"):
        situation, actions = stack.world.snapshot(), stack.route(rng, 6)
        stack.command(command, PARSER.parse(command))
        stack.episode(actions, situations=False)
        expected.append(_live(command, situation, actions))
    assert expected[0].situation != expected[1].situation != expected[2].situation
    observations = [i for i, m in enumerate(stack.messages) if m[0] == "/observation"]
    del stack.messages[observations[10]]  # and it lost a state of the second episode
    bag = _record(stack, tmp_path / "missed")
    assert read_bag_info(bag).topics["/situation"].message_count == 1

    reader = BagEpisodeReader(bag, decode_states=True)
    records = list(reader.records())
    assert [r.episode for r in records] == expected
    for record in records:
        assert np.array_equal(record.states, record.episode.states())
    assert reader.report.complete


def test_a_namespaced_recording_reads(tmp_path):
    """`ros2 bag record -a` of a stack in namespace /robot1 (no `/episode` records); a second
    stack's topics in the bag are not read into its episodes."""
    rng = random.Random(9)
    first, other = make_episodes(2, seed=9)
    robot1 = LiveStack(first.situation, namespace="/robot1")
    robot2 = LiveStack(other.situation, namespace="/robot2", t0_ns=robot1.now + 500)
    expected = []
    for stack, command in ((robot1, "walk to a red circle"), (robot2, "walk to a blue circle")):
        stack.state()
        situation, actions = stack.world.snapshot(), stack.route(rng, 6)
        stack.command(command, PARSER.parse(command))
        stack.episode(actions)
        expected.append(_live(command, situation, actions))
    robot1.messages += robot2.messages
    bag = _record(robot1, tmp_path / "robots", recorder=False)
    assert {t.split("/")[1] for t in read_bag_info(bag).topics} == {"robot1", "robot2"}

    reader = iter_bag_episodes(bag)
    back = list(reader)
    assert back == expected[:1] and back[0].meta["episode_id"] == "/policy_node/1"
    assert reader.report.complete


def test_unknown_action_token_names_bag_topic_and_time(tmp_path):
    stack = LiveStack(make_episodes(1)[0].situation)
    stack.state()
    stack.command("walk to a red circle")
    stack.start()
    stack.publish("action", text_to_cdr("jump"))
    bag = _record(stack, tmp_path / "tok")
    with pytest.raises(DatasetFormatError, match=rf"^{bag}: action at {stack.now} ns: unknown action 'jump'"):
        list(iter_bag_episodes(bag))
