"""`repair_bag` / `gscan-ros bag repair`: a damaged or unfinished bag becomes a complete, indexed
bag that third-party readers open, holding exactly what the recovering reader gets out of it."""
import json
import logging
import random
from collections import Counter
from pathlib import Path

import pytest
from actionlib_msgs.msg import GoalStatus
from mcap.reader import make_reader
from mcap.well_known import SchemaEncoding
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from gscan_ros import episode_status as es
from gscan_ros import interface
from gscan_ros.cli import main
from gscan_ros.data.bag import EPISODE_PERIOD_NS, STEP_NS, BagWriter, iter_bag_episodes, read_bag_info, repair_bag
from gscan_ros.data.bag_report import BagReadReport
from gscan_ros.data.bag_scan import LOSS, McapScan
from gscan_ros.errors import DatasetFormatError
from msg_adapters import message_class, message_definition, msg_to_cdr, text_to_cdr

from bag_support import (
    BAD_MESSAGES,
    LiveStack,
    copy_bag,
    damaged_copy,
    data_end,
    kill_writer,
    make_episodes,
    mcap_file,
    message_lost,
    messages_of,
    recording_with_a_bad_message,
    rosbag2_copy,
    truncated_copy,
    write_message_chunks,
)

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
S = EPISODE_PERIOD_NS


@pytest.fixture(scope="module")
def episodes():
    return make_episodes(50, seed=5)


@pytest.fixture(scope="module")
def intact(tmp_path_factory, episodes):
    """A closed bag of small chunks; a /status message (not an episode topic) after each episode."""
    bag = tmp_path_factory.mktemp("intact") / "bag"
    with BagWriter(bag, chunk_size=4096) as writer:
        for i, episode in enumerate(episodes):
            end = writer.write_episode(episode)
            writer.write_message("/status", interface.STATUS.type, text_to_cdr(f"episode {i} done"), end + 100)
    return bag


def _flipped(bag, dst):
    """A copy of `bag` with a byte flipped in the compressed data of the chunk a quarter into it."""
    with open(mcap_file(bag), "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    chunk = chunks[len(chunks) // 4]

    def flip(data: bytearray) -> None:
        data[chunk.chunk_start_offset + chunk.chunk_length // 2] ^= 0xFF

    return damaged_copy(bag, dst, flip)


def _damaged(kind, intact, tmp_path):
    if kind == "truncated":
        return truncated_copy(intact, tmp_path / "cut", int(data_end(intact) * 0.6))
    if kind == "flipped byte":
        return _flipped(intact, tmp_path / "flip")
    bag = tmp_path / "killed"
    kill_writer(bag)
    return bag


def _messages(bag):
    """(topic, log time, publish time, sequence, data) of every message, in file order."""
    with open(mcap_file(bag), "rb") as f:
        return [(c.topic, m.log_time, m.publish_time, m.sequence, m.data)
                for _, c, m in make_reader(f).iter_messages(log_time_order=False)]


def _readable(bag):
    """`_messages` of a damaged bag: those the recovering scanner gets out of it."""
    scan = McapScan(mcap_file(bag), BagReadReport(bag), read_bag_info(bag))
    return [(c.topic, log, publish, sequence, data)
            for c, sequence, log, publish, data in (i for i in scan.items() if i is not LOSS)]


def _reports(bag):
    """(episode id, GoalStatus code) of every `/episode_status` report, in file order (rosbags)."""
    with Reader(bag) as reader:
        connections = [c for c in reader.connections if c.topic == "/episode_status"]
        return [(msg.goal_id.id, msg.status) for msg in (
            TYPESTORE.deserialize_cdr(raw, c.msgtype) for c, _, raw in reader.messages(connections=connections))]


def _reports_of(episode):
    """Its ACTIVE and end reports, as a complete generated episode has them."""
    episode_id = str(episode.meta["episode_id"])
    return [(episode_id, GoalStatus.ACTIVE), (episode_id, GoalStatus.SUCCEEDED)]


@pytest.mark.parametrize("kind", ["truncated", "flipped byte", "killed writer"])
def test_repaired_bag_is_complete_and_opens_in_rosbags(kind, intact, episodes, tmp_path):
    source = _damaged(kind, intact, tmp_path)
    reader = iter_bag_episodes(source)
    recovered = list(reader)
    assert reader.report.damaged and recovered
    if kind != "flipped byte":
        with pytest.raises(Exception, match="magic"):  # no footer: rosbags cannot open it
            with Reader(source) as bag:
                list(bag.messages())

    result = repair_bag(source, tmp_path / "repaired")
    out = tmp_path / "repaired"
    assert result.episodes == len(recovered) and result.info.path == out

    # Our reader: the same episodes, nothing lost, a closed bag with the right counts.
    again = iter_bag_episodes(out)
    assert list(again) == recovered
    assert again.report.complete and again.report.lost_episodes == 0
    info = read_bag_info(out)
    assert info.closed and info.episodes == len(recovered)
    assert info.splits == dict(Counter(e.split for e in recovered))
    assert info.custom["gscan_ros.repaired_from"] == str(source)

    # A complete MCAP: summary with chunk indexes and statistics, footer, end magic.
    with open(mcap_file(out), "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary.chunk_indexes and summary.statistics.message_count == result.messages == info.message_count
    assert mcap_file(out).read_bytes().endswith(b"\x89MCAP0\r\n")

    # The third-party reader opens it and decodes every message: each recovered episode's
    # reports, record and situation are there (the prologues of episodes left out may be too).
    records, situations = {}, {}
    with Reader(out) as bag:
        assert bag.message_count == result.messages
        for connection, t, raw in bag.messages():
            msg = TYPESTORE.deserialize_cdr(raw, connection.msgtype)
            if connection.topic == "/episode":
                records[json.loads(msg.data)["id"]] = json.loads(msg.data)
            elif connection.topic == "/situation":
                situations[t // S] = json.loads(msg.data)
    assert _reports(out) == [r for e in recovered for r in _reports_of(e)]
    assert [records[str(e.meta["episode_id"])]["example_id"] for e in recovered] == [e.example_id for e in recovered]
    assert [situations[e.meta["episode_id"]] for e in recovered] == [e.situation.to_json() for e in recovered]


@pytest.mark.parametrize("kind", ["truncated", "flipped byte"])
def test_repair_keeps_channels_times_and_other_topics(kind, intact, tmp_path):
    source = _damaged(kind, intact, tmp_path)
    kept = {e.example_id for e in iter_bag_episodes(source)}
    result = repair_bag(source, tmp_path / "repaired")
    original = _messages(intact)
    # Every readable message, bytes and times unchanged, but the `/episode_status` reports of
    # the episodes the reader dropped: what is left of those is the world's history, never
    # an episode (no piece of one is joined to another across the damage).
    readable = _readable(source)
    expected = [m for m in readable if m[0] != "/episode_status" or m[1] // S in kept]
    assert _messages(tmp_path / "repaired") == expected
    assert result.dropped_messages == len(readable) - len(expected)
    if kind == "flipped byte":
        assert result.dropped_messages > 0  # the reports of the episode the damage cut
        assert expected[-1] == original[-1]  # other topics after the damage: the bag's last message
    with open(mcap_file(intact), "rb") as f:
        channels = {c.topic: (c.message_encoding, c.metadata) for c in make_reader(f).get_summary().channels.values()}
        schemas = {s.name: s.data for s in make_reader(f).get_summary().schemas.values()}
    with open(mcap_file(tmp_path / "repaired"), "rb") as f:
        summary = make_reader(f).get_summary()
    assert {c.topic: (c.message_encoding, c.metadata) for c in summary.channels.values()} == channels
    assert {s.name: s.data for s in summary.schemas.values()} == schemas


def test_repairing_an_intact_bag_copies_it(intact, episodes, tmp_path):
    result = repair_bag(intact, tmp_path / "copy")
    assert result.source.complete and result.dropped_messages == 0
    assert list(iter_bag_episodes(tmp_path / "copy")) == episodes
    assert _messages(tmp_path / "copy") == _messages(intact)


def test_repair_refuses_to_replace_what_it_should_not(intact, tmp_path):
    source = truncated_copy(intact, tmp_path / "cut", data_end(intact) // 2)
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(DatasetFormatError, match="exists"):
        repair_bag(source, out)
    with pytest.raises(DatasetFormatError, match="not a bag"):
        repair_bag(source, out, overwrite=True)
    assert (out / "notes.txt").read_text() == "mine"
    for target in (source, source / "inside", tmp_path):
        with pytest.raises(DatasetFormatError, match="overlaps"):
            repair_bag(source, target, overwrite=True)
    assert iter_bag_episodes(source).info.path == source  # still there
    # A previous bag is replaced with --overwrite (and nothing is left beside it).
    previous = tmp_path / "previous"
    repair_bag(intact, previous)
    repair_bag(source, previous, overwrite=True)
    assert len(list(iter_bag_episodes(previous))) == len(list(iter_bag_episodes(source)))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cut", "out", "previous"]


def test_cli_bag_repair(intact, tmp_path, capsys):
    source = _flipped(intact, tmp_path / "flip")
    assert main(["bag", "repair", str(source), "--out", str(tmp_path / "new")]) == 0
    out = capsys.readouterr().out
    assert "read" in out and "corrupt" in out
    assert "kept:" in out and "lost:" in out and "complete bag" in out
    assert main(["bag", "repair", str(source), "--out", str(tmp_path / "new")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--overwrite" in err[0] and err[0].startswith("gscan-ros bag repair: error:")
    assert main(["bag", "repair", str(source), "--out", str(tmp_path / "new"), "--overwrite"]) == 0
    # Bad arguments: one line, status 1, like every subcommand; nothing written.
    (tmp_path / "notes.txt").write_text("mine")
    for argv, name in (([str(tmp_path / "missing"), "--out", str(tmp_path / "x")], "BAG"),
                       ([str(source), "--out", str(tmp_path / "notes.txt")], "--out"),
                       ([str(tmp_path / "notes.txt"), "--out", str(tmp_path / "x")], "not a rosbag2 bag")):
        assert main(["bag", "repair", *argv]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and name in err[0] and err[0].startswith("gscan-ros bag repair: error:")
    assert not (tmp_path / "x").exists() and (tmp_path / "notes.txt").read_text() == "mine"


@pytest.mark.parametrize("keep", [0, 64], ids=["empty", "header only"])
def test_repair_of_a_bag_with_nothing_readable_fails_and_writes_nothing(intact, tmp_path, capsys, keep):
    """An empty repaired bag would read as intact and hide the loss: refused, no bag written."""
    (tmp_path / "dead").mkdir()
    (tmp_path / "dead" / "dead_0.mcap").write_bytes(mcap_file(intact).read_bytes()[:keep])
    assert main(["bag", "repair", str(tmp_path / "dead"), "--out", str(tmp_path / "new")]) == 1
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert "nothing to recover" in line and line.startswith("gscan-ros bag repair: error:")
    assert not (tmp_path / "new").exists()


@pytest.mark.parametrize("summary", [True, False], ids=["closed", "no summary"])
def test_random_damage_never_yields_a_wrong_episode(intact, episodes, tmp_path, summary):
    """Flipped bytes, zeroed or overwritten spans, cuts: whatever is recovered is exactly the
    original episodes (in order, none stitched), and its repair opens in rosbags."""
    rng = random.Random(12 + summary)
    source = mcap_file(intact).read_bytes()
    if not summary:
        source = source[: data_end(intact)]  # like a killed writer: chunks, no summary, no footer
    for trial in range(25):
        data = bytearray(source)
        for _ in range(rng.randint(1, 4)):
            start = rng.randrange(len(data))
            span = rng.choice([1, 1, 8, 300, 5000])
            data[start : start + span] = bytes(rng.randrange(256) for _ in range(len(data[start : start + span])))
        if rng.random() < 0.3:
            data = data[: rng.randrange(len(data) // 2, len(data))]
        bag = copy_bag(intact, tmp_path / f"t{trial}", bytes(data))
        reader = iter_bag_episodes(bag)
        try:
            recovered = list(reader)
        except DatasetFormatError as exc:  # only for a damaged magic or header
            assert "not an MCAP file" in str(exc)
            continue
        ids = [e.example_id for e in recovered]
        assert ids == sorted(set(ids)) and recovered == [episodes[i] for i in ids], trial
        if len(recovered) < len(episodes):
            assert not reader.report.complete
        result = repair_bag(bag, tmp_path / f"r{trial}")
        assert _reports(tmp_path / f"r{trial}") == [r for e in recovered for r in _reports_of(e)], trial
        again = iter_bag_episodes(result.info.path)
        assert list(again) == recovered and again.report.complete, trial


@pytest.fixture(scope="module")
def message_chunks(tmp_path_factory, episodes):
    return write_message_chunks(tmp_path_factory.mktemp("messages") / "bag", episodes[:5])


@pytest.mark.parametrize("lost", [2 * S, 2 * S + 2 * STEP_NS], ids=["record", "action"])
def test_repair_leaves_out_the_reports_of_the_episode_damage_cut(message_chunks, episodes, tmp_path, lost):
    """Damage takes episode 2's `/episode` record, or its second action: of that episode, all
    that is readable is copied but its two `/episode_status` reports, and the repaired bag
    reads whole, as the same episodes."""
    assert len(episodes[2].actions) >= 2
    source = message_lost(message_chunks, tmp_path / "damaged", lost)
    recovered = list(iter_bag_episodes(source))
    assert recovered == [e for i, e in enumerate(episodes[:5]) if i != 2]
    result = repair_bag(source, tmp_path / "repaired")
    topics = [m[0] for m in _messages(tmp_path / "repaired") if m[1] // S == 2]
    assert len(topics) == messages_of(episodes[2]) - 1 - 2 and "/episode_status" not in topics
    assert result.dropped_messages == 2
    again = iter_bag_episodes(tmp_path / "repaired")
    assert list(again) == recovered and again.report.complete
    assert result.source.lost_episodes == 1 and result.source.incomplete_episodes == 1


@pytest.mark.parametrize("topic", sorted(BAD_MESSAGES))
def test_repair_leaves_out_a_bad_message_and_its_episode(tmp_path, topic, capsys):
    """The bad message and the reports of the episode it belongs to are left out and
    reported lost, with the counts `verify` gives: the repaired bag verifies."""
    source = tmp_path / "bad"
    expected, _ = recording_with_a_bad_message(source, topic)
    reader = iter_bag_episodes(source)
    assert list(reader) == expected
    assert main(["verify", str(source), "--quiet"]) == 1
    assert f" episodes / {reader.report.lost_messages} messages" in capsys.readouterr().err

    result = repair_bag(source, tmp_path / "repaired")
    assert result.source.lost_messages == reader.report.lost_messages
    assert result.source.drop_reasons == reader.report.drop_reasons == {f"a bad /{topic} message": 1}
    assert result.dropped_messages == 3  # the bad message and the two reports
    again = iter_bag_episodes(tmp_path / "repaired")
    assert list(again) == expected and again.report.complete
    assert main(["verify", str(tmp_path / "repaired"), "--quiet"]) == 0


def test_cli_bag_repair_counts_each_outcome(tmp_path, capsys):
    """Cut and preempted episodes are kept, and counted as what they are."""
    rng = random.Random(4)
    stack = LiveStack(make_episodes(1, seed=4)[0].situation)
    stack.state()
    for outcome in (es.COMPLETE, es.CUT, es.PREEMPTED, es.COMPLETE):
        stack.command("walk to a red circle")
        stack.episode(stack.route(rng, 3), outcome)
    with BagWriter(tmp_path / "live") as writer:
        stack.record(writer)
    assert main(["bag", "repair", str(tmp_path / "live"), "--out", str(tmp_path / "new")]) == 0
    out = capsys.readouterr().out
    assert "kept: 2 complete episodes (and 1 cut, 1 preempted: no demonstrations)," in out
    info = read_bag_info(tmp_path / "new")
    assert info.episodes == 4 and info.splits == {"live": 2}


def test_repair_and_verify_agree_on_a_ros2_bag_record_bag(intact, tmp_path, capsys):
    """A bag of `ros2 bag record` (no episode count), its last file torn: both say the same
    loss, a lower bound for episodes; the repair's line ends without empty parentheses."""
    files = rosbag2_copy(intact, tmp_path / "rosbag2", 3)
    files[-1].write_bytes(files[-1].read_bytes()[:500])
    assert main(["verify", str(tmp_path / "rosbag2"), "--quiet"]) == 1
    err = capsys.readouterr().err
    lost = err[err.index("lost at least"):].split(" (")[0]
    assert lost.startswith("lost at least ") and " episodes / " in lost and "at least" not in lost.split("/")[1]
    assert main(["bag", "repair", str(tmp_path / "rosbag2"), "--out", str(tmp_path / "new")]) == 0
    line = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("lost:"))
    assert line.startswith(f"lost: {lost[len('lost '):]}") and not line.endswith("()")


def test_repair_of_a_folder_without_metadata_writes_one(intact, tmp_path, caplog):
    """A killed `ros2 bag record` leaves only its .mcap files: they are read in order (`_10`
    after `_9`), with a warning, and the repaired bag has a metadata.yaml."""
    files = rosbag2_copy(intact, tmp_path / "killed", 11)
    (tmp_path / "killed" / "metadata.yaml").unlink()
    with caplog.at_level(logging.WARNING, logger="gscan_ros.data.bag"):
        result = repair_bag(tmp_path / "killed", tmp_path / "new")
    assert "no metadata.yaml" in caplog.text and "bag repair" in caplog.text
    assert [p.name for p in read_bag_info(tmp_path / "killed").mcap_paths] == [p.name for p in files]
    assert list(iter_bag_episodes(tmp_path / "new")) == list(iter_bag_episodes(intact))
    assert result.info.closed and result.info.message_count == read_bag_info(intact).message_count


def test_repair_overwrite_never_deletes_a_folder_that_holds_more_than_a_bag(intact, tmp_path, capsys):
    """A metadata.yaml among a user's files does not make the folder a bag to replace."""
    out = tmp_path / "work"
    (out / "figures").mkdir(parents=True)
    (out / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    (out / "thesis.tex").write_text("years of work")
    (out / "figures" / "plot.png").write_bytes(b"png")
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert main(["bag", "repair", str(intact), "--out", str(out), "--overwrite"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a bag (holds figures, thesis.tex)" in err[0]
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before


def test_a_topic_of_two_types_keeps_a_channel_for_each(episodes, tmp_path):
    """A merged recording can hold a stack topic's name with another node's type too: the
    reader reads that channel as context, and repair copies each channel with its own type
    and schema (a writer keyed by name alone had put both on the first one's)."""
    bag = tmp_path / "bag"
    int32 = "std_msgs/msg/Int32"
    with BagWriter(bag) as writer:
        for i, episode in enumerate(episodes[:3]):
            writer.write_episode(episode)
            other = writer.channel("/action", int32, schema=(SchemaEncoding.ROS2, message_definition(int32).encode()))
            writer.add_record(other, msg_to_cdr(message_class(int32)(data=i)), (20 + i) * S, (20 + i) * S, 0)
    entries = [(t.name, t.msg_type, t.message_count) for t in read_bag_info(bag).entries if t.name == "/action"]
    assert entries == [("/action", "std_msgs/msg/String", entries[0][2]), ("/action", int32, 3)]
    reader = iter_bag_episodes(bag)
    assert list(reader) == episodes[:3] and reader.report.complete
    repair_bag(bag, tmp_path / "repaired")
    assert list(iter_bag_episodes(tmp_path / "repaired")) == episodes[:3]
    assert [(t.name, t.msg_type, t.message_count) for t in read_bag_info(tmp_path / "repaired").entries
            if t.name == "/action"] == entries
    with open(mcap_file(tmp_path / "repaired"), "rb") as f:
        summary = make_reader(f).get_summary()
    types = sorted(summary.schemas[c.schema_id].name for c in summary.channels.values() if c.topic == "/action")
    assert types == ["std_msgs/msg/Int32", "std_msgs/msg/String"]


def test_repairing_a_format_1_bag_keeps_its_format_and_its_episodes(tmp_path):
    """The messages are copied as they are, so the copy must still say format 1."""
    source = Path(__file__).parent / "fixtures" / "bag_v1"  # written by the format-1 writer
    expected = list(iter_bag_episodes(source))
    assert expected
    repair_bag(source, tmp_path / "copy")
    assert read_bag_info(tmp_path / "copy").format_version == 1
    assert list(iter_bag_episodes(tmp_path / "copy")) == expected


def test_repairing_a_format_1_bag_leaves_out_the_episodes_its_reader_drops(episodes, tmp_path):
    """A bad action token and a plain-text `/command` cost their episodes in the reader; the
    repaired bag leaves them out, so it reads the same episodes and nothing is lost."""
    from bag_support import legacy_bag, write_legacy_episode

    source = tmp_path / "v1"
    with legacy_bag(source) as writer:
        write_legacy_episode(writer, episodes[0], 0)
        write_legacy_episode(writer, episodes[1], 1, tokens=["walk", "jump", "<eos>"])
        writer.write_message("/command", interface.COMMAND.type, text_to_cdr("walk to a red circle"), 2 * S)
        writer.write_message("/action", interface.ACTION.type, text_to_cdr("<eos>"), 2 * S + STEP_NS)
        write_legacy_episode(writer, episodes[2], 3)
    reader = iter_bag_episodes(source)
    assert list(reader) == [episodes[0], episodes[2]]
    assert reader.report.drop_reasons == {"a bad /action message": 1, "a /command with no episode header": 1}
    result = repair_bag(source, tmp_path / "repaired")
    assert result.episodes == 2 and result.source.drop_reasons == reader.report.drop_reasons
    again = iter_bag_episodes(tmp_path / "repaired")
    assert list(again) == [episodes[0], episodes[2]] and again.report.complete


def test_repair_copies_another_nodes_topic_that_shares_a_stack_topics_name(episodes, tmp_path):
    """`ros2 bag record -a` also takes other nodes' topics; one named `/status` but of another
    type is no stack topic to the reader, and repair copies it as it is."""
    bag = tmp_path / "bag"
    with BagWriter(bag) as writer:
        for episode in episodes[:3]:
            writer.write_episode(episode)
        other = writer.register_channel("/status", "std_msgs/msg/Int32",
                                        schema=(SchemaEncoding.ROS2, message_definition("std_msgs/msg/Int32").encode()))
        writer.add_record(other, msg_to_cdr(message_class("std_msgs/msg/Int32")(data=7)), 10 * S, 10 * S, 0)
    assert list(iter_bag_episodes(bag)) == episodes[:3]
    repair_bag(bag, tmp_path / "repaired")
    assert list(iter_bag_episodes(tmp_path / "repaired")) == episodes[:3]
    assert [m[0] for m in _messages(tmp_path / "repaired")] == [m[0] for m in _messages(bag)]
    assert read_bag_info(tmp_path / "repaired").topics["/status"].msg_type == "std_msgs/msg/Int32"
