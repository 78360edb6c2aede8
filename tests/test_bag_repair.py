"""`repair_bag` / `gscan-ros bag repair`: a damaged or unfinished bag becomes a complete, indexed
bag that third-party readers open, holding exactly what the recovering reader gets out of it."""
import json
import random
from collections import Counter

import pytest
from mcap.reader import make_reader
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore
from std_msgs.msg import String

from gscan_ros.cli import main
from gscan_ros.data.bag import BagWriter, iter_bag_episodes, read_bag_info, repair_bag
from gscan_ros.errors import DatasetFormatError

from bag_support import copy_bag, damaged_copy, data_end, kill_writer, make_episodes, mcap_file, truncated_copy

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)


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
            writer.write_message("/status", String(data=f"episode {i} done"), end + 100)
    return bag


def _flip_middle_chunk(data: bytearray) -> None:
    data[len(data) // 4] ^= 0xFF


def _damaged(kind, intact, tmp_path):
    if kind == "truncated":
        return truncated_copy(intact, tmp_path / "cut", int(data_end(intact) * 0.6))
    if kind == "flipped byte":
        return damaged_copy(intact, tmp_path / "flip", _flip_middle_chunk)
    bag = tmp_path / "killed"
    kill_writer(bag)
    return bag


def _messages(bag):
    """(topic, log time, publish time, sequence, data) of every message, in file order."""
    with open(mcap_file(bag), "rb") as f:
        return [(c.topic, m.log_time, m.publish_time, m.sequence, m.data)
                for _, c, m in make_reader(f).iter_messages(log_time_order=False)]


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

    # The third-party reader opens it and decodes every message.
    commands = []
    with Reader(out) as bag:
        assert bag.message_count == result.messages
        for connection, _, raw in bag.messages():
            msg = TYPESTORE.deserialize_cdr(raw, connection.msgtype)
            if connection.topic == "/command":
                commands.append(json.loads(msg.data))
    assert [c["example_id"] for c in commands] == [e.example_id for e in recovered]
    assert [c["situation"] for c in commands] == [e.situation.to_json() for e in recovered]


@pytest.mark.parametrize("kind", ["truncated", "flipped byte"])
def test_repair_keeps_channels_times_and_other_topics(kind, intact, tmp_path):
    source = _damaged(kind, intact, tmp_path)
    kept = {e.example_id for e in iter_bag_episodes(source)}
    repair_bag(source, tmp_path / "repaired")
    original = _messages(intact)
    # Episode messages: exactly those of the recovered episodes, bytes and times unchanged.
    episode_topics = [m for m in original if m[0] != "/status" and m[1] // 1_000_000_000 in kept]
    repaired = _messages(tmp_path / "repaired")
    assert [m for m in repaired if m[0] != "/status"] == episode_topics
    # Other topics are copied whenever their chunk is intact, including after the damage.
    status = [m for m in repaired if m[0] == "/status"]
    assert status and set(status) <= set(original)
    if kind == "flipped byte":
        assert status[-1] == original[-1]  # the last message of the bag, well after the damage
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
    source = damaged_copy(intact, tmp_path / "flip", _flip_middle_chunk)
    assert main(["bag", "repair", str(source), "--out", str(tmp_path / "new")]) == 0
    out = capsys.readouterr().out
    assert "read" in out and "corrupt" in out
    assert "kept:" in out and "lost:" in out and "complete bag" in out
    assert main(["bag", "repair", str(source), "--out", str(tmp_path / "new")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--overwrite" in err[0] and err[0].startswith("gscan-ros bag: error:")
    assert main(["bag", "repair", str(source), "--out", str(tmp_path / "new"), "--overwrite"]) == 0
    # Bad arguments: one line, status 1, like every subcommand; nothing written.
    (tmp_path / "notes.txt").write_text("mine")
    for argv, name in (([str(tmp_path / "missing"), "--out", str(tmp_path / "x")], "BAG"),
                       ([str(source), "--out", str(tmp_path / "notes.txt")], "--out"),
                       ([str(tmp_path / "notes.txt"), "--out", str(tmp_path / "x")], "not a rosbag2 bag")):
        assert main(["bag", "repair", *argv]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and name in err[0] and err[0].startswith("gscan-ros bag: error:")
    assert not (tmp_path / "x").exists() and (tmp_path / "notes.txt").read_text() == "mine"


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
        with Reader(tmp_path / f"r{trial}") as repaired:
            assert sum(c.topic == "/command" for c, _, _ in repaired.messages()) == len(recovered)
        assert list(iter_bag_episodes(tmp_path / f"r{trial}")) == recovered == list(iter_bag_episodes(result.info.path))
