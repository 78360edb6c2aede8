"""The decode-once cache returns what the bag holds, notices when the bag changes, rebuilds a
cache file it cannot read, and never lets a fast load hide that its bag had lost data."""
import logging
import os
import subprocess
import sys

import numpy as np
import pytest

from gscan_ros.data import bag_cache
from gscan_ros.data.bag import BagWriter, repair_bag, write_bag
from gscan_ros.data.bag_cache import cache_path, load_episode_cache
from gscan_ros.errors import DatasetFormatError

from bag_support import data_end, make_episodes, mcap_file, on_grid, truncated_copy


@pytest.fixture
def bag(tmp_path):
    episodes = make_episodes(25, seed=4)
    write_bag(tmp_path / "bag", episodes)
    return tmp_path / "bag", episodes


def test_cache_holds_episodes_and_their_states(bag):
    bag_dir, episodes = bag
    cache = load_episode_cache(bag_dir)
    assert cache_path(bag_dir).is_file()
    assert cache.episodes == episodes and len(cache) == len(episodes)
    assert [e.meta["episode_id"] for e in cache.episodes] == list(range(len(episodes)))
    assert cache.commands == [e.command for e in episodes]
    assert cache.splits == [e.split for e in episodes]
    for i, episode in enumerate(episodes):
        assert cache.actions(i) == episode.actions
        assert np.array_equal(cache.states(i), episode.states())
        assert cache.packed_states(i).shape == (len(episode.actions) + 1, 6, 6, 2)
    assert cache.episode(3) is cache.episode(3)  # a situation is parsed once


def test_second_load_does_not_decode_the_bag(bag, monkeypatch):
    bag_dir, episodes = bag
    load_episode_cache(bag_dir)

    def no_decode(*args, **kwargs):
        raise AssertionError("bag decoded again")

    monkeypatch.setattr(bag_cache, "_decode", no_decode)
    assert load_episode_cache(bag_dir).episodes == episodes


def test_rewritten_bag_invalidates_the_cache(bag):
    bag_dir, episodes = bag
    load_episode_cache(bag_dir)
    write_bag(bag_dir, episodes[:5], overwrite=True)
    assert load_episode_cache(bag_dir).episodes == episodes[:5]


def test_split_filter_keeps_states_aligned(bag):
    bag_dir, episodes = bag
    cache = load_episode_cache(bag_dir, splits=["visual"])
    wanted = [e for e in episodes if e.split == "visual"]
    assert cache.episodes == wanted
    for i, episode in enumerate(wanted):
        assert np.array_equal(cache.states(i), episode.states())
    assert load_episode_cache(bag_dir, splits=["no such split"]).episodes == []


def test_torn_cache_file_is_rebuilt(bag):
    bag_dir, episodes = bag
    load_episode_cache(bag_dir)
    cache_path(bag_dir).write_bytes(b"garbage")
    assert load_episode_cache(bag_dir).episodes == episodes
    assert cache_path(bag_dir).stat().st_size > 100


def test_read_only_bag_still_loads(bag, monkeypatch, caplog):
    bag_dir, episodes = bag

    def refuse(*args, **kwargs):
        raise PermissionError("read-only file system")

    monkeypatch.setattr(bag_cache.np, "savez", refuse)
    assert load_episode_cache(bag_dir).episodes == episodes
    assert "cannot write bag cache" in caplog.text


@pytest.mark.parametrize("damage", ["empty", "garbage", "torn", "directory"])
def test_unreadable_cache_file_is_rebuilt_with_a_warning(bag, caplog, damage):
    bag_dir, episodes = bag
    load_episode_cache(bag_dir)
    path = cache_path(bag_dir)
    data = path.read_bytes()
    if damage == "directory":
        path.unlink()
        path.mkdir()
    else:
        path.write_bytes({"empty": b"", "garbage": b"garbage" * 10, "torn": data[: len(data) // 2]}[damage])
    with caplog.at_level(logging.WARNING, logger="gscan_ros.data.bag_cache"):
        assert load_episode_cache(bag_dir).episodes == episodes
    assert "unreadable" in caplog.text and "rebuilding" in caplog.text
    if damage != "directory":
        assert load_episode_cache(bag_dir).episodes == episodes  # the rebuilt file loads


def test_inconsistent_cache_arrays_are_rebuilt(bag, caplog):
    bag_dir, episodes = bag
    load_episode_cache(bag_dir)
    with np.load(cache_path(bag_dir)) as data:
        arrays = {name: data[name] for name in data.files}
    arrays["action_offsets"] = arrays["action_offsets"][:-3]  # same key, wrong shapes
    np.savez(cache_path(bag_dir), **arrays)
    with caplog.at_level(logging.WARNING, logger="gscan_ros.data.bag_cache"):
        cache = load_episode_cache(bag_dir)
    assert cache.episodes == episodes and "unreadable" in caplog.text


def test_touched_bag_rebuilds_the_cache(bag, monkeypatch):
    bag_dir, episodes = bag
    load_episode_cache(bag_dir)
    stat = mcap_file(bag_dir).stat()
    os.utime(mcap_file(bag_dir), ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))
    decoded = []
    decode = bag_cache._decode
    monkeypatch.setattr(bag_cache, "_decode", lambda *args: decoded.append(1) or decode(*args))
    assert load_episode_cache(bag_dir).episodes == episodes
    assert decoded == [1]
    assert load_episode_cache(bag_dir).episodes == episodes and decoded == [1]


@pytest.fixture
def truncated_bag(tmp_path):
    episodes = make_episodes(40, seed=2)
    with BagWriter(tmp_path / "full", chunk_size=4096) as writer:
        for episode in episodes:
            writer.write_episode(episode)
    return truncated_copy(tmp_path / "full", tmp_path / "cut", data_end(tmp_path / "full") // 2), episodes


def test_cache_of_a_damaged_bag_warns_once_per_process_on_every_load(truncated_bag, monkeypatch, caplog):
    bag_dir, episodes = truncated_bag
    with caplog.at_level(logging.WARNING, logger="gscan_ros.data.bag_cache"):
        cache = load_episode_cache(bag_dir)
    lost = len(episodes) - len(cache)
    assert 0 < len(cache) < len(episodes)
    assert cache.episodes == episodes[: len(cache)]
    assert not cache.complete and cache.lost_episodes == lost
    assert cache.source["state"] == "truncated"
    assert f"built from a damaged bag: {lost} episodes lost" in caplog.text

    def no_decode(*args, **kwargs):
        raise AssertionError("bag decoded again")

    monkeypatch.setattr(bag_cache, "_decode", no_decode)
    for new_process in (False, True):  # later loads come from the cache file and still say so
        if new_process:
            monkeypatch.setattr(bag_cache, "_WARNED", set())
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="gscan_ros.data.bag_cache"):
            again = load_episode_cache(bag_dir, ["train"])
        # Once per process (training loads train and dev of one bag), again in the next one.
        assert (f"built from a damaged bag: {lost} episodes lost" in caplog.text) is new_process
        assert not again.complete and again.subset([0]).lost_episodes == lost


def test_damaged_bag_warning_reaches_stderr_without_logging_setup(truncated_bag):
    bag_dir, _ = truncated_bag
    code = "import sys; from gscan_ros.data.bag_cache import load_episode_cache; load_episode_cache(sys.argv[1])"
    for _ in range(2):  # the build, then a load from the cache file
        run = subprocess.run([sys.executable, "-c", code, str(bag_dir)], capture_output=True, text=True, timeout=120)
        assert run.returncode == 0, run.stderr
        assert "built from a damaged bag" in run.stderr and "Traceback" not in run.stderr


def test_complete_and_repaired_bags_load_without_warnings(bag, truncated_bag, tmp_path, caplog):
    bag_dir, _ = bag
    cut, _ = truncated_bag
    repair_bag(cut, tmp_path / "repaired")
    with caplog.at_level(logging.WARNING):
        for path in (bag_dir, tmp_path / "repaired"):
            for _ in range(2):
                assert load_episode_cache(path).complete
    assert caplog.text == ""


def test_a_bag_on_two_grid_sizes_is_refused_naming_them(tmp_path):
    """Training stacks a bag's states into one array of one grid size: refused at load, in one line."""
    write_bag(tmp_path / "bag", make_episodes(3, seed=1) + on_grid(make_episodes(2, seed=2), 8))
    with pytest.raises(DatasetFormatError, match=r"bag: episodes on 2 grid sizes \(3 on 6x6, 2 on 8x8\)"):
        load_episode_cache(tmp_path / "bag")
    assert not cache_path(tmp_path / "bag").exists()
