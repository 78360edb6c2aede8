"""The decode-once cache returns what the bag holds and notices when the bag changes."""
import numpy as np
import pytest

from bag_support import make_episodes
from gscan_ros.data import bag_cache
from gscan_ros.data.bag import write_bag
from gscan_ros.data.bag_cache import cache_path, load_episode_cache


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
