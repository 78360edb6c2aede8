"""Oversampling the episodes of one word (TrainConfig.oversample_word): each such episode
appears `oversample_factor` times per epoch, every other once, under either batching."""
from collections import Counter

import numpy as np
import pytest

from gscan_ros.cli import main
from gscan_ros.training.batches import batch_order, has_word, word_repeats
from gscan_ros.training.config import ConfigError, TrainConfig


class Commands:
    def __init__(self, commands):
        self.commands = commands

    def __len__(self):
        return len(self.commands)


STORE = Commands(["walk to a circle cautiously", "walk to a square", "push a circle", "walk to a square"] * 5
                 + ["pull a circle cautiously"])


@pytest.mark.parametrize("batching", ["mixed", "per_command"])
def test_each_episode_appears_as_often_as_asked(batching):
    repeats = word_repeats(STORE.commands, "cautiously", 4)
    assert sorted(set(repeats.tolist())) == [1, 4] and repeats.sum() == len(STORE) + 3 * 6
    order = batch_order(STORE, 3, batching, np.random.default_rng(0), repeats)
    seen = Counter(int(i) for batch in order for i in batch)
    assert [seen[i] for i in range(len(STORE))] == repeats.tolist()
    if batching == "per_command":
        assert all(len({STORE.commands[i] for i in batch}) == 1 for batch in order)


@pytest.mark.parametrize("batching", ["mixed", "per_command"])
def test_no_oversampling_is_the_epoch_as_before(batching):
    assert word_repeats(STORE.commands, "", 1) is None and word_repeats(STORE.commands, "cautiously", 1) is None
    order = batch_order(STORE, 3, batching, np.random.default_rng(5))
    ones = batch_order(STORE, 3, batching, np.random.default_rng(5), np.ones(len(STORE), dtype=int))
    assert [b.tolist() for b in order] == [b.tolist() for b in ones]
    if batching == "mixed":  # runs trained before the option keep their batches
        assert np.concatenate(order).tolist() == np.random.default_rng(5).permutation(len(STORE)).tolist()


def test_a_word_is_a_whole_word_of_the_command():
    assert has_word("walk to a circle cautiously", "cautiously")
    assert not has_word("walk to a circle cautiously", "cautious") and not has_word("walking", "walk")


def test_a_word_no_command_has_is_named():
    with pytest.raises(ValueError, match="'zebra'"):
        word_repeats(STORE.commands, "zebra", 2)


@pytest.mark.parametrize("overrides", [["oversample_factor=3"], ["oversample_word=cautiously"],
                                       ["oversample_word=cautiously", "oversample_factor=0"],
                                       ["oversample_word=cautiously", "oversample_factor=2.5"]])
def test_word_and_factor_go_together(overrides):
    with pytest.raises(ConfigError, match="oversample"):
        TrainConfig.load(None, overrides)


def test_train_cli_oversamples_and_names_a_missing_word(tiny_dataset, tmp_path, capsys):
    common = ["train", "--data", str(tiny_dataset), "--quiet", "--set", "batch_size=8", "--set", "max_updates=2",
              "--set", "validate_every=2", "--set", "threads=1", "--set", "max_dev_examples=4",
              "--set", "oversample_factor=3"]
    assert main([*common, "--out", str(tmp_path / "ok"), "--set", "oversample_word=walk"]) == 0
    assert "oversample_word: walk" in (tmp_path / "ok" / "config.yaml").read_text()
    assert main([*common, "--out", str(tmp_path / "bad"), "--set", "oversample_word=zebra"]) == 1
    err = capsys.readouterr().err
    assert "'zebra'" in err and "Traceback" not in err
