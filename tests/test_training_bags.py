"""Training from bags: the store comes from the bag's decode-once cache and equals the
dataset.txt store of the same episodes; later loads neither decode the bag nor replay World."""
import json

import numpy as np
import pytest
import torch

from gscan_ros.cli import main
from gscan_ros.data import bag_cache
from gscan_ros.data.bag import read_bag_info
from gscan_ros.data.bag_cache import cache_path
from gscan_ros.data.episode import Episode
from gscan_ros.language.lexicon import Lexicon
from gscan_ros.language.registry import get_parser
from gscan_ros.model.checkpoint import read_checkpoint
from gscan_ros.training.batches import EpisodeStore
from gscan_ros.training.config import TrainConfig
from gscan_ros.training.trainer import load_dev, load_split, load_train_store

GENERATE = ["--examples", "300", "--seed", "0", "--workers", "1", "--quiet"]


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """The same generated dataset as dataset.txt and as a directory of per-split bags."""
    txt, bags = tmp_path_factory.mktemp("txt"), tmp_path_factory.mktemp("bags")
    assert main(["generate", "--out", str(txt), *GENERATE]) == 0
    assert main(["generate", "--out", str(bags), "--format", "mcap", *GENERATE]) == 0
    return txt, bags


@pytest.fixture(scope="module")
def parser():
    return get_parser("semantic", Lexicon.none())


def assert_same_store(a: EpisodeStore, b: EpisodeStore) -> None:
    assert a.commands == b.commands and a.graphs == b.graphs
    for name in ("lengths", "ep_ptr", "actions", "bits", "state_ptr"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name


def test_bag_store_equals_the_dataset_store(data, parser):
    txt, bags = data
    cfg = TrainConfig(lexicon="none")
    from_bag = load_train_store(str(bags), cfg, parser)
    assert cache_path(bags / "train").is_file()
    episodes = load_split(str(txt), "train")
    assert len(from_bag) == len(episodes) > 100
    assert_same_store(from_bag, EpisodeStore(episodes, parser))
    assert_same_store(from_bag, EpisodeStore(iter(episodes), parser, chunk=7))  # streamed, chunk boundaries
    ids = [3, 0, 7]
    assert np.array_equal(from_bag.initial_states(ids), np.stack([episodes[i].states()[0] for i in ids]))


def test_example_limit_and_dev_subset_match_the_dataset(data, parser):
    txt, bags = data
    cfg = TrainConfig(lexicon="none", max_train_examples=10, dev_split="test", max_dev_examples=5)
    assert_same_store(load_train_store(str(bags), cfg, parser), load_train_store(str(txt), cfg, parser))
    dev = load_dev(str(bags), cfg)
    assert len(dev) == 5
    assert [(e.command, e.situation, e.actions) for e in dev] == [
        (e.command, e.situation, e.actions) for e in load_dev(str(txt), cfg)]


def test_dev_length_cap_keeps_only_short_episodes_from_either_source(data):
    txt, bags = data
    lengths = sorted(len(e.actions) for e in load_split(str(txt), "test"))
    cap = lengths[len(lengths) // 2]
    cfg = TrainConfig(lexicon="none", dev_split="test", max_dev_examples=0, max_dev_target_length=cap)
    short = [(e.command, e.situation, e.actions) for e in load_dev(str(txt), cfg)]
    assert len(short) == sum(n <= cap for n in lengths) < len(lengths)
    assert all(len(actions) <= cap for _, _, actions in short)
    assert [(e.command, e.situation, e.actions) for e in load_dev(str(bags), cfg)] == short


def test_second_load_uses_the_cache_without_world(data, parser, monkeypatch):
    _, bags = data
    cfg = TrainConfig(lexicon="none")
    first = load_train_store(str(bags), cfg, parser)
    assert cache_path(bags / "train").is_file()

    def forbidden(*args, **kwargs):
        raise AssertionError("decoded the bag or replayed World again")

    monkeypatch.setattr(bag_cache, "_decode", forbidden)
    monkeypatch.setattr(Episode, "states", forbidden)
    assert_same_store(load_train_store(str(bags), cfg, parser), first)


def test_train_cli_on_a_bag_dir(data, tmp_path):
    torch.set_num_threads(1)
    _, bags = data
    run = tmp_path / "run"
    assert main(["train", "--data", str(bags), "--out", str(run), "--quiet", "--set", "batch_size=16",
                 "--set", "max_updates=2", "--set", "validate_every=2", "--set", "threads=1",
                 "--set", "dev_split=test", "--set", "max_dev_examples=4", "--set", "lexicon=none"]) == 0
    assert read_checkpoint(run / "last.pt")["step"] == 2
    events = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    start = next(e for e in events if e["event"] == "start")
    assert start["train_examples"] == read_bag_info(bags / "train").episodes and start["dev_examples"] == 4
    assert any(e["event"] == "validation" for e in events)
