"""Damaged bags: a torn tail is recovered episode by episode, damage in the middle costs only
the episodes of the damaged chunks, a file that is not MCAP is one clear error."""
import io
import logging
import shutil
from pathlib import Path

import pytest
import yaml
from mcap.reader import make_reader
from mcap.records import Message
from mcap.stream_reader import StreamReader, breakup_chunk

from gscan_ros.cli import main
from gscan_ros.data.bag import (
    EPISODE_PERIOD_NS,
    STEP_NS,
    BagWriter,
    iter_bag_episodes,
    read_bag_info,
    repair_bag,
    write_bag,
)
from gscan_ros.data.bag_cache import load_episode_cache
from gscan_ros.errors import DatasetFormatError

from bag_support import (
    ROSBAG2_NAME,
    copy_bag,
    damaged_copy,
    data_end,
    kill_writer,
    make_episodes,
    mcap_file,
    message_lost,
    messages_of,
    rosbag2_copy,
    truncated_copy,
    write_message_chunks,
)


@pytest.fixture(scope="module")
def episodes():
    return make_episodes(60, seed=7)


@pytest.fixture(scope="module")
def small_chunk_bag(tmp_path_factory, episodes):
    """A closed bag with many small chunks, so truncation points fall in different chunks."""
    bag_dir = tmp_path_factory.mktemp("full") / "bag"
    with BagWriter(bag_dir, chunk_size=4096) as writer:
        for episode in episodes:
            writer.write_episode(episode)
    return bag_dir


@pytest.mark.parametrize("fraction", [0.02, 0.3, 0.5, 0.77, 0.95, 0.9999])
def test_truncated_file_yields_a_prefix_and_counts_the_loss(small_chunk_bag, episodes, tmp_path, fraction, caplog):
    bag = truncated_copy(small_chunk_bag, tmp_path / "cut", int(data_end(small_chunk_bag) * fraction))
    reader = iter_bag_episodes(bag)
    with caplog.at_level(logging.WARNING, logger="gscan_ros.data.bag"):
        recovered = list(reader)
    report = reader.report
    assert recovered == episodes[: len(recovered)]
    assert report.truncated
    assert report.episodes_read == len(recovered)
    assert report.lost_episodes == len(episodes) - len(recovered) > 0
    info = read_bag_info(small_chunk_bag)
    kept = sum(map(messages_of, recovered))
    assert report.lost_messages == info.message_count - kept
    assert "recovered" in caplog.text and "lost" in caplog.text
    if fraction >= 0.5:
        assert len(recovered) >= 10  # whole chunks before the cut survive


def test_truncation_inside_the_summary_loses_nothing(small_chunk_bag, episodes, tmp_path):
    bag = truncated_copy(small_chunk_bag, tmp_path / "cut", data_end(small_chunk_bag) + 10)
    reader = iter_bag_episodes(bag)
    assert list(reader) == episodes
    assert reader.report.truncated and reader.report.lost_messages == 0 and reader.report.lost_episodes == 0


def test_killed_writer_leaves_every_flushed_episode_readable(tmp_path):
    bag = tmp_path / "killed"
    flushed = kill_writer(bag)
    assert not read_bag_info(bag).closed
    reader = iter_bag_episodes(bag)
    recovered = list(reader)
    assert len(recovered) >= flushed
    assert recovered == make_episodes(len(recovered), seed=11)
    assert reader.report.truncated and reader.report.expected_messages is None
    assert reader.report.lost_episodes == reader.report.incomplete_episodes <= 1


def _chunk_episodes(bag: Path) -> list[tuple[int, int, set[int]]]:
    """(start, end, ids of the episodes with a message in it) for each chunk of an intact bag
    (generated times: episode i's messages lie in [i s, i s + 1 s))."""
    chunks = []
    with open(mcap_file(bag), "rb") as f:
        for index in make_reader(f).get_summary().chunk_indexes:
            f.seek(index.chunk_start_offset)
            raw = f.read(index.chunk_length)
            chunk = next(StreamReader(io.BytesIO(raw), skip_magic=True, emit_chunks=True).records)
            ids = {m.log_time // EPISODE_PERIOD_NS for m in breakup_chunk(chunk) if isinstance(m, Message)}
            chunks.append((index.chunk_start_offset, index.chunk_start_offset + index.chunk_length, ids))
    return chunks


# Where the flipped byte goes, given the chunks' (start, end): inside a chunk's compressed
# data, its length field or its opcode; the first chunk holds the schema/channel records
# (the summary's copies then name the channels); between chunks lie message indexes.
FLIPS = {
    "first chunk": lambda chunks: chunks[0][0] + 60,
    "chunk at 30%": lambda chunks: sum(chunks[len(chunks) * 3 // 10][:2]) // 2,
    "chunk length at 50%": lambda chunks: chunks[len(chunks) // 2][0] + 3,
    "chunk opcode at 70%": lambda chunks: chunks[len(chunks) * 7 // 10][0],
    "last chunk": lambda chunks: chunks[-1][1] - 5,
    "message index": lambda chunks: chunks[len(chunks) // 3][1] + 30,
}


@pytest.mark.parametrize("where", FLIPS)
def test_flipped_byte_loses_only_the_episodes_of_its_chunk(small_chunk_bag, episodes, tmp_path, where):
    chunks = _chunk_episodes(small_chunk_bag)
    offset = FLIPS[where]([c[:2] for c in chunks])

    def flip(data):
        data[offset] ^= 0xFF

    bag = damaged_copy(small_chunk_bag, tmp_path / "flip", flip)
    reader = iter_bag_episodes(bag)
    recovered = list(reader)
    hit = [ids for start, end, ids in chunks if start <= offset < end]
    lost = set().union(*hit)
    # Every episode with no message in the damaged chunk is recovered, in order, and the
    # episodes it touched are dropped, not stitched together from what is left.
    assert recovered == [e for i, e in enumerate(episodes) if i not in lost]
    report = reader.report
    assert report.lost_episodes == len(lost)
    assert not report.truncated
    if hit:
        assert report.corrupt and report.lost_chunks == 1 and len(report.corrupt_regions) == 1
        assert report.lost_messages == sum(messages_of(episodes[i]) for i in lost)
        assert "corrupt" in report.summary()


def test_zeroed_bytes_in_the_middle_are_skipped(small_chunk_bag, episodes, tmp_path):
    middle = data_end(small_chunk_bag) // 2

    def zero(data):
        data[middle : middle + 5000] = bytes(5000)  # more than one 4 KiB chunk

    bag = damaged_copy(small_chunk_bag, tmp_path / "bad", zero)
    reader = iter_bag_episodes(bag)
    recovered = list(reader)
    assert recovered[-1] == episodes[-1] and recovered[0] == episodes[0]
    kept = {e.example_id for e in recovered}
    assert recovered == [e for e in episodes if e.example_id in kept]  # in order, none stitched
    assert reader.report.corrupt and not reader.report.truncated and reader.report.lost_chunks >= 2
    assert reader.report.lost_episodes == len(episodes) - len(recovered) >= 2


def test_damaged_summary_loses_nothing_but_is_reported(small_chunk_bag, episodes, tmp_path):
    end = data_end(small_chunk_bag)
    size = (small_chunk_bag / "bag_0.mcap").stat().st_size

    def flip(data):
        data[(end + size) // 2] ^= 0xFF

    reader = iter_bag_episodes(damaged_copy(small_chunk_bag, tmp_path / "summary", flip))
    assert list(reader) == episodes
    assert reader.report.lost_episodes == reader.report.lost_messages == 0
    assert not reader.report.truncated


def test_cut_inside_the_first_chunk_is_truncated_not_corrupt(episodes, tmp_path):
    full = tmp_path / "bag"
    write_bag(full, episodes)  # one 1 MiB chunk holds them all
    assert len(_chunk_episodes(full)) == 1
    bag = truncated_copy(full, tmp_path / "cut", data_end(full) // 2)
    reader = iter_bag_episodes(bag)
    assert list(reader) == []
    report = reader.report
    assert report.truncated and not report.corrupt and report.lost_chunks == 1
    assert report.lost_episodes == len(episodes)
    assert report.summary().startswith(f"{bag}: truncated: recovered 0 complete episodes (of {len(episodes)} recorded)")


def test_killed_writer_with_a_damaged_first_chunk_recovers_the_rest(tmp_path):
    """No summary to name the channels: a gscan_ros bag's metadata.yaml lists them in id order."""
    bag = tmp_path / "killed"
    kill_writer(bag)
    data = bytearray((bag / "killed_0.mcap").read_bytes())
    header_end = 8 + 9 + int.from_bytes(data[9:17], "little")
    assert data[header_end] == 0x06  # the first chunk: schemas, channels, first messages
    data[header_end + 80] ^= 0xFF
    (bag / "killed_0.mcap").write_bytes(bytes(data))
    reader = iter_bag_episodes(bag)
    recovered = list(reader)
    first = recovered[0].example_id
    assert first > 0 and len(recovered) > 30
    assert recovered == make_episodes(first + len(recovered), seed=11)[first:]
    assert reader.report.corrupt and reader.report.truncated


@pytest.fixture(scope="module")
def message_chunks(tmp_path_factory, episodes):
    return write_message_chunks(tmp_path_factory.mktemp("messages") / "bag", episodes[:6])


def test_a_lost_episode_record_loses_its_episode(message_chunks, episodes, tmp_path):
    """The damage takes only episode 2's `/episode` record (its split, example id, fields):
    its situation, command and actions survive, but it is dropped, not read as a live one."""
    bag = message_lost(message_chunks, tmp_path / "lost", 2 * EPISODE_PERIOD_NS)
    reader = iter_bag_episodes(bag)
    assert list(reader) == [e for i, e in enumerate(episodes[:6]) if i != 2]
    report = reader.report
    assert report.drop_reasons == {"its /episode record was lost": 1} and report.incomplete_episodes == 1
    assert report.lost_episodes == 1 and report.lost_messages == messages_of(episodes[2])


def test_an_episode_cut_by_lost_data_counts_once(message_chunks, episodes, tmp_path):
    """A writer that died after damage mid-episode (no summary, metadata.yaml still
    `recording`): the losses it reports are lower bounds, and count the cut episode once."""
    middle = 3 * EPISODE_PERIOD_NS + 2 * STEP_NS  # episode 3's second action
    assert len(episodes[3].actions) >= 2
    damaged = message_lost(message_chunks, tmp_path / "damaged", middle)
    bag = copy_bag(damaged, tmp_path / "unclosed", mcap_file(damaged).read_bytes()[: data_end(message_chunks)])
    metadata = bag / "metadata.yaml"
    metadata.write_text(metadata.read_text().replace("gscan_ros.status: closed", "gscan_ros.status: recording"))
    reader = iter_bag_episodes(bag)
    assert list(reader) == [e for i, e in enumerate(episodes[:6]) if i != 3]
    report = reader.report
    assert not report.messages_exact and report.drop_reasons == {"cut by lost data": 1}
    assert report.incomplete_episodes == report.lost_episodes == 1
    assert report.lost_messages == messages_of(episodes[3])
    assert "lost at least 1 episodes" in report.summary()


@pytest.mark.parametrize("content", [b"not an mcap file at all\n" * 10, b"\x89MCAP0\r\n" + bytes(3)])
def test_not_an_mcap_file(small_chunk_bag, tmp_path, content):
    bag = truncated_copy(small_chunk_bag, tmp_path / "junk", 0)
    (bag / "junk_0.mcap").write_bytes(content)
    with pytest.raises(DatasetFormatError, match=r"junk_0\.mcap: not an MCAP file"):
        list(iter_bag_episodes(bag))


def test_metadata_problems_name_the_file(small_chunk_bag, tmp_path):
    with pytest.raises(DatasetFormatError, match="no metadata.yaml"):
        iter_bag_episodes(tmp_path)
    bag = truncated_copy(small_chunk_bag, tmp_path / "meta", 10)
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: [unclosed")
    with pytest.raises(DatasetFormatError, match="metadata.yaml is not valid YAML"):
        read_bag_info(bag)
    for empty in ("", "rosbag2_bagfile_information:", "- a list"):  # no Python internals in the message
        (bag / "metadata.yaml").write_text(empty)
        with pytest.raises(DatasetFormatError, match="metadata.yaml: not rosbag2 metadata"):
            read_bag_info(bag)
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: {version: 9}")
    with pytest.raises(DatasetFormatError, match="metadata.yaml: missing rosbag2 key 'storage_identifier'"):
        read_bag_info(bag)
    text = (small_chunk_bag / "metadata.yaml").read_text()
    (bag / "metadata.yaml").write_text(text)  # names bag_0.mcap, which is not in this directory
    with pytest.raises(DatasetFormatError, match="storage file bag_0.mcap is missing"):
        read_bag_info(bag)
    (bag / "metadata.yaml").write_text(text.replace("storage_identifier: mcap", "storage_identifier: sqlite3"))
    with pytest.raises(DatasetFormatError, match="storage 'sqlite3' is not supported"):
        read_bag_info(bag)
    info = yaml.safe_load(text)
    info["rosbag2_bagfile_information"].update(compression_mode="MESSAGE", compression_format="zstd")
    (bag / "metadata.yaml").write_text(yaml.safe_dump(info))
    with pytest.raises(DatasetFormatError, match="compression_mode 'MESSAGE' is not supported; MCAP's own chunk"):
        read_bag_info(bag)
    info = yaml.safe_load(text)
    info["rosbag2_bagfile_information"]["relative_file_paths"] = "bag_0.mcap"  # a string, not a list
    (bag / "metadata.yaml").write_text(yaml.safe_dump(info))
    with pytest.raises(DatasetFormatError, match="relative_file_paths must be a list of file names, got 'bag_0.mcap'"):
        read_bag_info(bag)
    info = yaml.safe_load(text)
    info["rosbag2_bagfile_information"]["topics_with_message_count"][0]["topic_metadata"]["type"] = 7
    (bag / "metadata.yaml").write_text(yaml.safe_dump(info))
    with pytest.raises(DatasetFormatError, match="a topic's name and type must be text, got '/.*' of type 7"):
        read_bag_info(bag)
    shutil.copy(small_chunk_bag / "bag_0.mcap", bag / "bag_0.mcap")
    for version, problem in (("'x'", "'x' is not a version number"), ("'9'", "'9' is newer than supported")):
        (bag / "metadata.yaml").write_text(text.replace("gscan_ros.format_version: '2'",
                                                        f"gscan_ros.format_version: {version}"))
        with pytest.raises(DatasetFormatError, match=problem):
            read_bag_info(bag)


@pytest.fixture(scope="module")
def rosbag2_bag(tmp_path_factory, small_chunk_bag):
    """`small_chunk_bag` as `ros2 bag record` splits it: three files, no episode count."""
    bag = tmp_path_factory.mktemp("rosbag2") / "bag"
    rosbag2_copy(small_chunk_bag, bag, 3)
    return bag


@pytest.mark.parametrize("keep", [0, 5], ids=["empty", "5 bytes"])
def test_an_empty_last_file_is_truncated_like_a_torn_one(rosbag2_bag, episodes, tmp_path, keep):
    """The recorder split to a new file and died: nothing is recovered from it, the rest is."""
    bag = tmp_path / "bag"
    shutil.copytree(rosbag2_bag, bag)
    last = sorted(bag.glob("*.mcap"))[-1]
    last.write_bytes(last.read_bytes()[:keep])
    reader = iter_bag_episodes(bag)
    recovered = list(reader)
    assert recovered == episodes[: len(recovered)] and len(recovered) > len(episodes) // 2
    assert reader.report.truncated_files == [last] and reader.report.lost_messages > 0


def test_a_folder_of_mcap_files_without_metadata_reads_with_a_warning(rosbag2_bag, episodes, tmp_path, caplog):
    """A killed `ros2 bag record` never wrote metadata.yaml: its files are read in name order."""
    bag = tmp_path / "bag"
    shutil.copytree(rosbag2_bag, bag)
    (bag / "metadata.yaml").unlink()
    with caplog.at_level(logging.WARNING, logger="gscan_ros.data.bag"):
        reader = iter_bag_episodes(bag)
        assert list(reader) == episodes
    assert "no metadata.yaml" in caplog.text and "3 .mcap file(s) in name order" in caplog.text
    assert not reader.info.closed and not reader.report.messages_exact


def test_mcap_files_metadata_does_not_list_are_read_with_a_warning(rosbag2_bag, episodes, tmp_path, caplog):
    bag = tmp_path / "bag"
    shutil.copytree(rosbag2_bag, bag)
    metadata = yaml.safe_load((bag / "metadata.yaml").read_text())
    info = metadata["rosbag2_bagfile_information"]
    unlisted = info["relative_file_paths"].pop()
    (bag / "metadata.yaml").write_text(yaml.safe_dump(metadata))
    with caplog.at_level(logging.WARNING, logger="gscan_ros.data.bag"):
        reader = iter_bag_episodes(bag)
        assert list(reader) == episodes
    assert f"does not list 1 .mcap file(s) of the folder ({unlisted})" in caplog.text
    assert not reader.info.closed  # metadata.yaml's counts leave the file out


@pytest.fixture(scope="module")
def split_bag(tmp_path_factory, small_chunk_bag):
    """`small_chunk_bag` as `ros2 bag record` splits it: twelve files `_0` .. `_11`."""
    bag = tmp_path_factory.mktemp("split") / "bag"
    rosbag2_copy(small_chunk_bag, bag, 12)
    return bag


def without_split_file(split_bag: Path, bag: Path, n: int, *, metadata: bool) -> tuple[Path, set[int]]:
    """A copy of `split_bag` without its file `_<n>` (and without metadata.yaml unless
    `metadata`): that file, and the ids of the episodes with a message in it."""
    shutil.copytree(split_bag, bag)
    gone = bag / f"{ROSBAG2_NAME}_{n}.mcap"
    with open(gone, "rb") as f:
        hit = {m.log_time // EPISODE_PERIOD_NS for _, _, m in make_reader(f).iter_messages(log_time_order=False)}
    gone.unlink()
    if not metadata:
        (bag / "metadata.yaml").unlink()
    return gone, hit


MISSING = pytest.mark.parametrize("metadata", [True, False], ids=["listed in metadata.yaml", "numbering gap"])


@MISSING
def test_a_missing_split_file_is_lost_data_at_its_place(split_bag, episodes, tmp_path, caplog, metadata):
    """`_5` of `_0` .. `_11` is gone: the other files are read, the episodes with a message in
    it are dropped (none stitched across the gap), and the report names the file."""
    bag = tmp_path / "bag"
    gone, hit = without_split_file(split_bag, bag, 5, metadata=metadata)
    assert read_bag_info(bag).missing == (gone,)
    with caplog.at_level(logging.WARNING, logger="gscan_ros.data.bag"):
        reader = iter_bag_episodes(bag)
        recovered = list(reader)
    assert recovered == [e for i, e in enumerate(episodes) if i not in hit]
    assert recovered[0] == episodes[0] and recovered[-1] == episodes[-1]
    report = reader.report
    assert report.missing_files == [gone] and not report.truncated and not report.corrupt
    assert not report.complete and report.state() == "missing files"
    assert report.drop_reasons.get("cut by lost data") == 1 and report.lost_episodes >= 1
    assert f"missing files: recovered {len(recovered)} complete episodes" in report.summary()
    assert f"1 storage file(s) missing: {gone.name}" in report.summary()
    assert gone.name in caplog.text and report.summary() in caplog.text
    kept = sum(map(messages_of, recovered))
    if metadata:  # metadata.yaml counts what was recorded: the loss is exact
        assert report.messages_exact and report.lost_messages == read_bag_info(split_bag).message_count - kept
    else:
        assert not report.messages_exact and report.lost_messages > 0


@MISSING
def test_a_bag_with_a_missing_split_file_fails_verify_and_repairs(split_bag, episodes, tmp_path, capsys, metadata):
    bag = tmp_path / "bag"
    gone, hit = without_split_file(split_bag, bag, 5, metadata=metadata)
    recovered = [e for i, e in enumerate(episodes) if i not in hit]
    try:
        code = main(["verify", str(bag), "--quiet"])
    except SystemExit as exc:
        code = exc.code
    [lost] = [line for line in capsys.readouterr().err.splitlines() if "lost data" in line]
    assert code == 1 and lost.startswith("gscan-ros verify: error: lost data:") and gone.name in lost
    cache = load_episode_cache(bag)  # the missing file is part of its key, and the loss is recorded
    assert len(cache) == len(recovered) and not cache.complete and gone.name in cache.source["summary"]
    result = repair_bag(bag, tmp_path / "repaired")
    assert result.source.missing_files == [gone] and gone.name in result.summary()
    assert result.episodes == len(recovered)
    info = read_bag_info(tmp_path / "repaired")
    assert info.closed and info.missing == () and gone.name in info.custom["gscan_ros.repair"]
    again = iter_bag_episodes(tmp_path / "repaired")
    assert list(again) == recovered and again.report.complete


def test_numbering_gaps_count_from_the_first_split_file(split_bag, tmp_path):
    bag = tmp_path / "bag"
    gone, _ = without_split_file(split_bag, bag, 0, metadata=False)
    info = read_bag_info(bag)
    assert info.missing == (gone,) and info.mcap_paths[0] == gone and len(info.mcap_paths) == 12
    assert f"{gone.name} missing from their numbering" in info.warnings[0]
    # A number that is no split's (a date stamp) is a name: nothing is missing before it.
    other = tmp_path / "other"
    other.mkdir()
    shutil.copy(bag / f"{ROSBAG2_NAME}_1.mcap", other / "run_20250101.mcap")
    assert read_bag_info(other).missing == ()


def test_a_bag_none_of_whose_listed_files_exist_is_refused(split_bag, tmp_path):
    bag = tmp_path / "bag"
    shutil.copytree(split_bag, bag)
    for path in bag.glob("*.mcap"):
        path.unlink()
    with pytest.raises(DatasetFormatError, match=r"metadata.yaml: all 12 storage files are missing \(rosbag2_"):
        read_bag_info(bag)


@pytest.mark.parametrize("key, value", [("gscan_ros.episodes", "many"), ("gscan_ros.splits", "'{bad'"),
                                        ("gscan_ros.splits", "'[1, 2]'")])
def test_malformed_custom_data_is_ignored_with_a_warning(small_chunk_bag, episodes, tmp_path, caplog, key, value):
    """Our counts in custom_data are advisory: a bad one costs the count, not the bag."""
    bag = copy_bag(small_chunk_bag, tmp_path / "bag", mcap_file(small_chunk_bag).read_bytes())
    metadata = bag / "metadata.yaml"
    text = metadata.read_text()
    start = text.index(f"    {key}:")
    metadata.write_text(text[:start] + f"    {key}: {value}\n" + text[text.index("\n", start) + 1:])
    info = read_bag_info(bag)
    assert key not in info.custom and (info.episodes is None if key == "gscan_ros.episodes" else info.splits == {})
    with caplog.at_level(logging.WARNING, logger="gscan_ros.data.bag"):
        assert list(iter_bag_episodes(bag)) == episodes
    assert f"custom_data {key} is not" in caplog.text and "ignoring it" in caplog.text
    metadata.write_text(text.replace("  custom_data:\n", "  custom_data: [1, 2]\n  ignored:\n"))
    assert read_bag_info(bag).custom == {} and "custom_data is not a map" in read_bag_info(bag).warnings[0]
