"""Recordings of the live stack read back by the episode rule (episode_assembly): the policy's
reports delimit episodes, messages count in publication order whatever order a recorder
logged them in, and what a recorder missed of the world's state is replayed."""
import random

import numpy as np
import pytest
from mcap.reader import make_reader

from gscan_ros import episode_status as es
from gscan_ros.data.bag import (
    LIVE_SPLIT,
    BagEpisodeReader,
    BagWriter,
    iter_bag_episodes,
    read_bag_info,
    repair_bag,
    write_bag,
)
from gscan_ros.data.bag_cache import load_episode_cache
from gscan_ros.data.episode import Episode
from gscan_ros.language import get_parser
from gscan_ros.world.types import Action
from gscan_ros.world.world import World
from msg_adapters import action_to_cdr, reset_to_cdr, text_to_cdr

from bag_support import BAD_MESSAGES, LiveStack, make_episodes, mcap_file, recording_with_a_bad_message, rosbag2_copy

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
            writer.add_record(writer.channel(topic, msg_type), data, publish_ns + latency[topic], publish_ns, 0)
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


def test_the_outcome_line_tells_taken_episodes_from_those_outside_the_selection(outcomes):
    """`verify`/`replay --include-incomplete --splits`: the cut and preempted episodes of
    another split are outside the selection, not "refused before any action"."""
    from gscan_ros.data.bag_report import incomplete_line

    bag, _ = outcomes
    everything = BagEpisodeReader(bag, include_incomplete=True)
    list(everything.records())
    assert everything.report.taken_outcomes == {"cut": 1, "preempted": 1}
    assert incomplete_line([everything], "checked", included=True) == (
        "episodes that did not end complete: 1 cut, 1 preempted (checked: 1 cut, 1 preempted)")
    other_split = BagEpisodeReader(bag, splits=["train"], include_incomplete=True)
    list(other_split.records())
    assert other_split.report.taken_outcomes == {}
    assert incomplete_line([other_split], "checked", included=True) == (
        "episodes that did not end complete: 1 cut, 1 preempted (checked: none; 2 outside the selection)")


def test_a_recording_begun_mid_episode_reads_complete(tmp_path):
    """`ros2 bag record -a` started while an episode runs: its tail and end report are the
    bag's prologue, not lost data; the next episode starts where that tail left the world."""
    rng = random.Random(4)
    stack = LiveStack(make_episodes(1, seed=4)[0].situation)
    stack.state()
    stack.command("walk to a red circle", PARSER.parse("walk to a red circle"))
    running = es.EpisodeStatus("/policy_node/1", stack.now, es.ACTIVE, "")  # published before the recording
    stack.episodes = 1
    for action in stack.route(rng, 3):
        stack.act(action)
    stack.end(running, es.PREEMPTED)
    situation, actions = stack.world.snapshot(), stack.route(rng, 4)
    stack.command("walk to a blue circle", PARSER.parse("walk to a blue circle"))
    stack.episode(actions)
    bag = tmp_path / "late"
    with BagWriter(bag) as writer:
        stack.record(writer, recorder=False)
    reader = BagEpisodeReader(bag, include_incomplete=True)
    assert [r.episode for r in reader.records()] == [_live("walk to a blue circle", situation, actions)]
    assert reader.report.complete and reader.report.drop_reasons == {} and reader.report.incomplete_episodes == 0


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


def _two_commands_sent_at_once(rng: random.Random, *, graphs: bool, first_len: int, second_len: int):
    """Two commands typed at once (with their graphs when `graphs`): the first is followed
    for `first_len` actions and preempted, the second completes. The stack, and the episodes
    a reader must return."""
    stack = LiveStack(make_episodes(1, seed=3)[0].situation)
    stack.state()
    first_command, second_command = "walk to a red circle", "walk to a blue circle"
    for command in (first_command, second_command):
        stack.command(command, PARSER.parse(command) if graphs else None)
    start, first = stack.world.snapshot(), stack.route(rng, first_len)
    preempted = stack.start(first_command)
    for action in first:
        stack.act(action)
    stack.end(preempted, es.PREEMPTED)
    middle, second = stack.world.snapshot(), stack.route(rng, second_len)
    following = stack.start(second_command)
    for action in [*second, Action.EOS]:
        stack.act(action)
    stack.end(following, es.COMPLETE)
    return stack, [(_live(first_command, start, first), es.PREEMPTED),
                   (_live(second_command, middle, second), es.COMPLETE)]


def test_two_commands_sent_at_once_each_keep_their_own_episode(tmp_path):
    """Both graphs reach the recorder before the first one's ACTIVE report: the episode
    takes the graph of the command its report names, not the newest (which preempts it)."""
    stack, expected = _two_commands_sent_at_once(random.Random(4), graphs=True, first_len=1, second_len=3)
    records = list(BagEpisodeReader(_record(stack, tmp_path / "both"), include_incomplete=True).records())
    assert [(r.episode, r.outcome) for r in records] == expected
    assert "typed_command" not in records[0].episode.meta  # the newest typed command is the second's


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


def test_every_stack_of_a_recording_reads_on_its_own(tmp_path):
    """`ros2 bag record -a` of a fleet: stacks in namespaces /robot1 and /robot2 (no `/episode`
    records), their messages interleaved. Each is read on its own: neither's messages go
    into the other's episodes, and neither hides the other."""
    rng = random.Random(9)
    first, other = make_episodes(2, seed=9)
    robot1 = LiveStack(first.situation, namespace="/robot1", policy="/robot1/policy_node")
    robot2 = LiveStack(other.situation, namespace="/robot2", policy="/robot2/policy_node", t0_ns=robot1.now + 500)
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
    back = sorted(reader, key=lambda e: e.command)
    assert back == sorted(expected, key=lambda e: e.command)
    assert [e.meta["episode_id"] for e in back] == ["/robot2/policy_node/1", "/robot1/policy_node/1"]
    assert reader.report.complete and reader.report.episodes_read == 2


def test_another_nodes_topic_of_a_stack_topics_name_is_context(tmp_path):
    """A battery node's `/battery/status` (a std_msgs/String, as the stack's `/status`) is the
    bag's first message, and `/camera/observation` has a stack topic's name but another
    type: neither is taken for a stack, and the stack at the root reads whole."""
    rng = random.Random(2)
    stack = LiveStack(make_episodes(1, seed=2)[0].situation)
    start = stack.now
    stack.state()
    expected = []
    for command in ("walk to a red circle", "walk to a blue circle"):
        situation, actions = stack.world.snapshot(), stack.route(rng, 5)
        stack.command(command, PARSER.parse(command))
        stack.episode(actions)
        expected.append(_live(command, situation, actions))
    stack.messages += [("/battery/status", "std_msgs/msg/String", text_to_cdr("battery ok"), start - 1000, 0),
                       ("/camera/observation", "std_msgs/msg/Header", reset_to_cdr(start), start + 1, 0)]
    bag = _record(stack, tmp_path / "battery", recorder=False)
    assert _file_order(bag)[0] == ("/battery/status", start - 1000)

    reader = iter_bag_episodes(bag)
    assert list(reader) == expected
    assert reader.report.complete


@pytest.mark.parametrize("topic", sorted(BAD_MESSAGES))
def test_a_bad_message_costs_its_episode_not_the_bag(tmp_path, topic):
    """A bad `/action` token, a `/situation` or `/episode` that is not JSON, an `/episode_status`
    code the policy never sends, an `/observation` that is no image: the episode it belongs
    to is dropped and the report names the reason and the message; the episodes around it read."""
    bag = tmp_path / "bad"
    expected, bad_ns = recording_with_a_bad_message(bag, topic)
    reader = iter_bag_episodes(bag)
    assert list(reader) == expected and len(expected) == 2
    report = reader.report
    assert report.drop_reasons == {f"a bad /{topic} message": 1} and report.incomplete_episodes == 1
    assert report.bad_messages == 1
    assert report.first_bad_message.startswith(f"/{topic} at {bad_ns} ns: {BAD_MESSAGES[topic][1]}")
    assert not report.complete and f"a bad /{topic} message" in report.summary()


@pytest.mark.parametrize("topic", ["action", "episode_status", "observation"])
def test_a_stray_bad_message_between_episodes_is_lost_alone(tmp_path, topic):
    bag = tmp_path / "stray"
    expected, _ = recording_with_a_bad_message(bag, topic, stray=True)
    reader = iter_bag_episodes(bag)
    assert list(reader) == expected and len(expected) == 3
    report = reader.report
    assert report.bad_messages == 1 and report.incomplete_episodes == 0
    assert report.lost_episodes == 0 and report.lost_messages == 1 and not report.complete
    # Training's read agrees: a state it could not read is the world's, replayed.
    records = list(BagEpisodeReader(bag, decode_states=True).records())
    assert [r.episode for r in records] == expected
    assert all(np.array_equal(r.states, np.stack(r.episode.states())) for r in records)


def test_an_episode_after_a_reset_whose_new_situation_was_missed_is_dropped(tmp_path):
    """The recorder lagged over the new world's latched `/situation`: the old world is no
    start for the episode, however many states of the new one were recorded."""
    old, new = (e.situation for e in make_episodes(2, seed=1))
    stack = LiveStack(old)
    stack.state()
    stack.publish("world_reset", reset_to_cdr(stack.now + stack.step_ns))
    stack.world = World(new)
    stack.state(situation=False)
    stack.command("walk to a red circle", PARSER.parse("walk to a red circle"))
    stack.episode(stack.route(random.Random(0), 4), situations=False)
    reader = BagEpisodeReader(_record(stack, tmp_path / "reset"), decode_states=True, include_incomplete=True)
    assert list(reader.records()) == []
    assert reader.report.drop_reasons == {"no situation before it started": 1}


def test_observations_are_matched_to_actions_by_the_lock_step_protocol(tmp_path):
    """A preempted episode's last reply comes after the next ACTIVE report (it is the state
    the next episode starts from), and the recorder misses a later reply: the count of
    states comes out right, and the states are still the world's, step by step."""
    rng = random.Random(2)
    stack = LiveStack(make_episodes(1, seed=5)[0].situation)
    stack.state()
    stack.command("walk to a red circle", PARSER.parse("walk to a red circle"))
    preempted = stack.start()
    [first] = stack.route(rng, 1)
    stack.publish("action", action_to_cdr(first))
    stack.command("walk to a blue circle", PARSER.parse("walk to a blue circle"))
    stack.end(preempted, es.PREEMPTED)
    following = stack.start()
    stack.world.step(first)
    stack.state()  # the reply to the preempted episode's action
    start, actions = stack.world.snapshot(), stack.route(rng, 5)
    for step, action in enumerate(actions):
        stack.publish("action", action_to_cdr(action))
        stack.world.step(action)
        if step != 2:  # the recorder missed this reply
            stack.state()
    stack.act(Action.EOS)
    stack.end(following, es.COMPLETE)
    bag = _record(stack, tmp_path / "lagged")

    [record] = list(BagEpisodeReader(bag, decode_states=True).records())
    assert record.episode == _live("walk to a blue circle", start, actions)
    assert np.array_equal(record.states, record.episode.states())
    cache = load_episode_cache(bag)
    assert cache.complete and np.array_equal(cache.states(0), record.episode.states())


def test_an_all_topics_recording_stopped_mid_episode_ends_it_preempted(tmp_path):
    """`ros2 bag record -a` stopped by Ctrl-C writes no end report for the running episode:
    like our recorder's bags, it reads PREEMPTED (no demonstration) and nothing is lost.
    In a bag whose writer died, the same tail is lost data."""
    rng = random.Random(1)
    stack = LiveStack(make_episodes(1, seed=3)[0].situation)
    stack.state()
    situation, actions = stack.world.snapshot(), stack.route(rng, 4)
    stack.command("walk to a red circle", PARSER.parse("walk to a red circle"))
    stack.episode(actions)
    middle, running = stack.world.snapshot(), stack.route(rng, 2)
    stack.command("walk to a blue circle", PARSER.parse("walk to a blue circle"))
    stack.start()
    for action in running:
        stack.act(action)
    bag = tmp_path / "rosbag2"
    rosbag2_copy(_record(stack, tmp_path / "recorded", recorder=False), bag, files=2)

    reader = BagEpisodeReader(bag, include_incomplete=True)
    assert [(r.episode, r.outcome) for r in reader.records()] == [
        (_live("walk to a red circle", situation, actions), es.COMPLETE),
        (_live("walk to a blue circle", middle, running), es.PREEMPTED)]
    assert reader.report.complete and reader.report.outcomes == {es.PREEMPTED: 1}
    assert [r.episode for r in BagEpisodeReader(bag).records()] == [_live("walk to a red circle", situation, actions)]

    (bag / "metadata.yaml").unlink()  # the recorder was killed: its last file may miss messages
    reader = BagEpisodeReader(bag, include_incomplete=True)
    assert [r.outcome for r in reader.records()] == [es.COMPLETE]
    assert reader.report.drop_reasons == {"no end report (the recording stopped first)": 1}


def test_a_bad_observation_costs_its_episode_whether_states_are_decoded_or_not(tmp_path):
    """One rule for every reader: an observation cut short drops its episode with the
    reason, like any bad message, in the training cache's read (`decode_states`), in
    `verify`'s and in `bag repair`, whose copy then holds nothing bad."""
    rng = random.Random(6)
    stack = LiveStack(make_episodes(1, seed=6)[0].situation)
    stack.state()
    expected, bad = [], None
    for i, command in enumerate(("walk to a red circle", "walk to a blue circle", "walk to a red circle")):
        situation, actions = stack.world.snapshot(), stack.route(rng, 4)
        stack.command(command)
        start = len(stack.messages)
        stack.episode(actions)
        if i == 1:  # the second episode's state after its first action (not the third's start), 5 bytes short
            bad = next(k for k, m in enumerate(stack.messages) if k > start and m[0] == "/observation")
        else:
            expected.append(Episode(command, situation, actions, split=LIVE_SPLIT, example_id=None))
    topic, msg_type, data, publish_ns, late_ns = stack.messages[bad]
    stack.messages[bad] = (topic, msg_type, data[:-5], publish_ns, late_ns)
    with BagWriter(tmp_path / "bag") as writer:
        stack.record(writer, recorder=False)
    for decode_states in (False, True):
        reader = BagEpisodeReader(tmp_path / "bag", decode_states=decode_states)
        records = list(reader.records())
        assert [r.episode for r in records] == expected
        assert reader.report.drop_reasons == {"a bad /observation message": 1} and not reader.report.complete
        assert reader.report.bad_messages == 1 and reader.report.first_bad_message.startswith("/observation")
    assert all(len(r.states) == len(r.episode.actions) + 1 for r in records)
    result = repair_bag(tmp_path / "bag", tmp_path / "repaired")
    assert result.episodes == 2
    repaired = BagEpisodeReader(tmp_path / "repaired", decode_states=True)
    assert [r.episode for r in repaired.records()] == expected and repaired.report.complete


def test_without_command_graphs_an_episode_takes_the_command_its_report_names(tmp_path):
    """An all-topics bag of /command but no /command_graph: the newest typed command may be
    the one that preempted the episode, so the ACTIVE report's command labels it."""
    stack, expected = _two_commands_sent_at_once(random.Random(5), graphs=False, first_len=2, second_len=2)
    bag = _record(stack, tmp_path / "no_graphs", recorder=False)
    records = list(BagEpisodeReader(bag, include_incomplete=True).records())
    assert [(r.episode, r.outcome) for r in records] == expected
    assert all("typed_command" not in r.episode.meta for r in records)


@pytest.mark.parametrize("topic", ["action", "episode_status", "situation", "observation"])
def test_a_message_the_bag_holds_twice_is_read_once(tmp_path, topic):
    """A bag merged with itself, or a sample logged twice: same topic, publish time and
    bytes is one DDS sample, so a demonstration gains no action and a report counts once."""
    rng = random.Random(6)
    stack = LiveStack(make_episodes(1, seed=3)[0].situation)
    stack.state()
    for command in ("walk to a red circle", "walk to a blue circle"):
        stack.command(command, PARSER.parse(command))
        stack.episode(stack.route(rng, 3))
    clean = list(BagEpisodeReader(_record(stack, tmp_path / "clean", recorder=False)).records())
    copied = next(i for i, m in enumerate(stack.messages) if m[0] == f"/{topic}")
    stack.messages.insert(copied + 1, stack.messages[copied])
    reader = BagEpisodeReader(_record(stack, tmp_path / "twice", recorder=False))
    assert [r.episode for r in reader.records()] == [r.episode for r in clean] and len(clean) == 2
    assert reader.report.duplicate_messages == 1 and reader.report.lost_episodes == 0
    assert "1 duplicate message(s) left out" in reader.report.summary()


def test_a_bag_without_an_episode_topic_names_it(tmp_path):
    stack = LiveStack(make_episodes(1, seed=3)[0].situation)
    stack.state()
    stack.command("walk to a red circle", PARSER.parse("walk to a red circle"))
    stack.episode(stack.route(random.Random(7), 2))
    stack.messages = [m for m in stack.messages if m[0] != "/situation"]
    reader = BagEpisodeReader(_record(stack, tmp_path / "no_situation", recorder=False))
    assert list(reader.records()) == []
    assert "no gSCAN stack: it lacks /situation (std_msgs/msg/String)" in reader.report.summary()


def test_a_message_logged_beyond_the_reorder_window_is_lost_not_misplaced():
    """Put back in order within the window; one logged further away would join whatever
    episode is open where it was logged, so it becomes a loss there instead."""
    from gscan_ros.data.episode_assembly import LOSS, Message, publication_order

    def message(t):
        return Message(t, t, "", "action", b"")

    logged = [message(t) for t in (2, 1, 3, 4, 5, 6)] + [message(0)] + [message(7)]  # 0 comes 6 places late
    late = []
    out = list(publication_order(logged, window=2, on_late=late.append))
    assert [m if m is LOSS else m.publish_ns for m in out] == [1, 2, 3, 4, LOSS, 5, 6, 7]
    assert [m.publish_ns for m in late] == [0]
