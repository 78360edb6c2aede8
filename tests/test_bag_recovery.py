"""Damaged bags: a torn tail is recovered episode by episode, anything else is one clear error."""
import logging
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from mcap.reader import make_reader

from bag_support import make_episodes
from gscan_ros.data.bag import BagWriter, iter_bag_episodes, read_bag_info
from gscan_ros.errors import DatasetFormatError

TESTS = Path(__file__).parent


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


def _data_end(bag: Path) -> int:
    """File offset after the last chunk (its message indexes and the summary follow)."""
    with open(bag / "bag_0.mcap", "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    return max(c.chunk_start_offset + c.chunk_length for c in chunks)


def _truncated_copy(src: Path, dst: Path, keep: int) -> Path:
    dst.mkdir()
    (dst / "metadata.yaml").write_text((src / "metadata.yaml").read_text().replace("bag_0.mcap", f"{dst.name}_0.mcap"))
    (dst / f"{dst.name}_0.mcap").write_bytes((src / "bag_0.mcap").read_bytes()[:keep])
    return dst


@pytest.mark.parametrize("fraction", [0.02, 0.3, 0.5, 0.77, 0.95, 0.9999])
def test_truncated_file_yields_a_prefix_and_counts_the_loss(small_chunk_bag, episodes, tmp_path, fraction, caplog):
    bag = _truncated_copy(small_chunk_bag, tmp_path / "cut", int(_data_end(small_chunk_bag) * fraction))
    reader = iter_bag_episodes(bag)
    with caplog.at_level(logging.WARNING, logger="gscan_ros.data.bag"):
        recovered = list(reader)
    report = reader.report
    assert recovered == episodes[: len(recovered)]
    assert report.truncated
    assert report.episodes_read == len(recovered)
    assert report.lost_episodes == len(episodes) - len(recovered) > 0
    info = read_bag_info(small_chunk_bag)
    kept = sum(1 + 2 * (len(e.actions) + 1) for e in recovered)
    assert report.lost_messages == info.message_count - kept
    assert "recovered" in caplog.text and "lost" in caplog.text
    if fraction >= 0.5:
        assert len(recovered) >= 10  # whole chunks before the cut survive


def test_truncation_inside_the_summary_loses_nothing(small_chunk_bag, episodes, tmp_path):
    bag = _truncated_copy(small_chunk_bag, tmp_path / "cut", _data_end(small_chunk_bag) + 10)
    reader = iter_bag_episodes(bag)
    assert list(reader) == episodes
    assert reader.report.truncated and reader.report.lost_messages == 0 and reader.report.lost_episodes == 0


WRITER = textwrap.dedent(
    """
    import sys
    sys.path.insert(0, {tests!r})
    import itertools, random
    from bag_support import make_episode
    from gscan_ros.data.bag import BagWriter

    writer = BagWriter({bag!r}, chunk_size=2048).open()
    rng = random.Random(11)
    for i in itertools.count():  # until killed
        writer.write_episode(make_episode(rng, i))
        if i == 40:
            writer.flush()
            print("flushed", i + 1, flush=True)
    """
)


def test_killed_writer_leaves_every_flushed_episode_readable(tmp_path):
    bag = tmp_path / "killed"
    child = subprocess.Popen(
        [sys.executable, "-c", WRITER.format(tests=str(TESTS), bag=str(bag))],
        stdout=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        line = child.stdout.readline()
        assert line.startswith("flushed"), line
        flushed = int(line.split()[1])
        os.killpg(child.pid, signal.SIGKILL)
    finally:
        child.kill()
        child.wait(timeout=30)
    assert not read_bag_info(bag).closed
    reader = iter_bag_episodes(bag)
    recovered = list(reader)
    assert len(recovered) >= flushed
    assert recovered == make_episodes(len(recovered), seed=11)
    assert reader.report.truncated and reader.report.expected_messages is None
    assert reader.report.lost_episodes == reader.report.incomplete_episodes <= 1


def test_corrupt_chunk_is_one_error_naming_the_file(small_chunk_bag, tmp_path):
    data = bytearray((small_chunk_bag / "bag_0.mcap").read_bytes())
    middle = len(data) // 2
    data[middle : middle + 64] = bytes(64)
    bag = _truncated_copy(small_chunk_bag, tmp_path / "bad", len(data))
    (bag / "bad_0.mcap").write_bytes(bytes(data))
    with pytest.raises(DatasetFormatError, match=r"bad_0\.mcap: corrupt MCAP data") as err:
        list(iter_bag_episodes(bag))
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("content", [b"", b"not an mcap file at all\n" * 10, b"\x89MCAP0\r\n" + bytes(3)])
def test_not_an_mcap_file(small_chunk_bag, tmp_path, content):
    bag = _truncated_copy(small_chunk_bag, tmp_path / "junk", 0)
    (bag / "junk_0.mcap").write_bytes(content)
    with pytest.raises(DatasetFormatError, match=r"junk_0\.mcap: not an MCAP file"):
        list(iter_bag_episodes(bag))


def test_metadata_problems_name_the_file(small_chunk_bag, tmp_path):
    with pytest.raises(DatasetFormatError, match="no metadata.yaml"):
        iter_bag_episodes(tmp_path)
    bag = _truncated_copy(small_chunk_bag, tmp_path / "meta", 10)
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: [unclosed")
    with pytest.raises(DatasetFormatError, match="metadata.yaml: invalid YAML"):
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
