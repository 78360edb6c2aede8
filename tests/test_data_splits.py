"""Hold-out rules B-H and the split set operations (Ruis et al. 2020; docs/data.md)."""
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from gscan_ros.data.commands import parse_command
from gscan_ros.data.generate import _DROPPED, GenerationConfig, _labels
from gscan_ros.data.sampling import ObjectSpec, Placement
from gscan_ros.data.splits import (
    SPLIT_NAMES,
    assign_compositional,
    assign_length,
    discard_equivalent,
    held_out_splits,
    sample_splits,
    take_fraction,
)
from gscan_ros.world.types import Position


@pytest.mark.parametrize("command, target, direction, expected", [
    # B: yellow square target AND "yellow" said.
    ("walk to a yellow square", (1, "yellow", "square"), "n", ("visual_easier",)),
    ("push a yellow small square", (2, "yellow", "square"), "e", ("visual_easier",)),
    ("walk to a square", (1, "yellow", "square"), "n", ()),
    ("walk to a small square", (1, "yellow", "square"), "n", ()),
    # C: red square target, however referred to.
    ("walk to a square", (2, "red", "square"), "n", ("visual",)),
    ("walk to a red big square", (4, "red", "square"), "w", ("visual",)),
    # D: south-west.
    ("walk to a circle", (1, "blue", "circle"), "sw", ("situational_1",)),
    ("walk to a circle", (1, "blue", "circle"), "s", ()),
    # E: "small" and a size-2 circle.
    ("walk to a small circle", (2, "green", "circle"), "n", ("situational_2",)),
    ("walk to a green small circle", (2, "green", "circle"), "n", ("situational_2",)),
    ("walk to a big circle", (2, "green", "circle"), "n", ()),
    ("walk to a small circle", (1, "green", "circle"), "n", ()),
    # F: push a size-3 square of any color and form.
    ("push a square", (3, "green", "square"), "n", ("contextual",)),
    ("push a blue big square", (3, "blue", "square"), "n", ("contextual",)),
    ("pull a square", (3, "green", "square"), "n", ()),
    ("push a square", (4, "green", "square"), "n", ()),
    # G, H.
    ("walk to a circle cautiously", (1, "blue", "circle"), "n", ("adverb_1",)),
    ("pull a circle while spinning", (1, "blue", "circle"), "n", ("adverb_2",)),
    ("push a circle while spinning", (1, "blue", "circle"), "n", ()),
    # Several rules: dropped later.
    ("walk to a circle cautiously", (1, "blue", "circle"), "sw", ("situational_1", "adverb_1")),
    ("push a square", (3, "red", "square"), "n", ("visual", "contextual")),
])
def test_hold_out_rules(command, target, direction, expected):
    assert held_out_splits(parse_command(command), ObjectSpec(*target), direction) == expected


def test_examples_matching_several_rules_are_dropped():
    layouts = tuple(Placement(Position(0, 0), Position(0, 0), d, 1) for d in ("n", "sw"))
    labels = _labels(GenerationConfig().resolved(), parse_command("pull a circle cautiously"),
                     ObjectSpec(1, "blue", "circle"), layouts)
    assert labels.tolist() == [SPLIT_NAMES.index("adverb_1"), _DROPPED]


def test_take_fraction_counts_and_partition():
    rng = np.random.default_rng(0)
    rest, taken = take_fraction(rng, np.arange(1000), 0.1)
    assert len(taken) == 100 and len(rest) == 900
    assert sorted(np.concatenate([rest, taken]).tolist()) == list(range(1000))


def test_discard_equivalent_uses_keys():
    keys = np.array([5, 6, 7, 5, 8], dtype=np.uint64)
    assert discard_equivalent(np.array([3, 4]), np.array([0, 1, 2]), keys).tolist() == [4]


def test_assign_compositional_fractions_and_k_shot():
    labels = np.array([0] * 1000 + [SPLIT_NAMES.index("adverb_1")] * 50 + [SPLIT_NAMES.index("visual")] * 20)
    keys = np.arange(len(labels), dtype=np.uint64)  # all distinct: nothing discarded
    result = assign_compositional(np.random.default_rng(1), labels, keys, 0.9, 0.01, k_shot=3)
    sizes = {k: len(v) for k, v in result.splits.items()}
    # int((1 - 0.9) * n) as the original computes it (floating point gives 99).
    n_test = int((1 - 0.9) * 1000)
    n_dev = int(0.01 * (1000 - n_test))
    assert sizes["test"] == n_test and sizes["dev"] == n_dev and sizes["train"] == 1000 - n_test - n_dev + 3
    assert sizes["adverb_1"] == 47 and sizes["visual"] == 20
    assert set(result.splits["train"][-3:].tolist()) == set(result.k_shot)
    assert all(labels[i] == SPLIT_NAMES.index("adverb_1") for i in result.k_shot)


def test_assign_compositional_discards_test_duplicates_of_train():
    labels = np.zeros(200, dtype=np.int8)
    keys = np.zeros(200, dtype=np.uint64)  # every example equivalent to every other
    result = assign_compositional(np.random.default_rng(2), labels, keys, 0.9, 0.0, k_shot=0)
    assert len(result.splits["test"]) == 0 and result.discarded_equivalent == int((1 - 0.9) * 200)


def test_assign_length_cut_off():
    lengths = np.array([3, 20, 15, 16, 9] * 40)
    keys = np.arange(len(lengths), dtype=np.uint64)
    result = assign_length(np.random.default_rng(3), lengths, keys, 15, 0.8, 0.01)
    assert (lengths[result.splits["target_lengths"]] > 15).all()
    assert len(result.splits["target_lengths"]) == 80
    for split in ("train", "dev", "test"):
        assert (lengths[result.splits[split]] <= 15).all()
    assert len(result.splits["test"]) == int((1 - 0.8) * 120)


@given(seed=st.integers(0, 2**32 - 1), size=st.integers(3, 1100), k_shot=st.integers(0, 3))
def test_sample_splits_draws_each_split_in_proportion(seed, size, k_shot):
    labels = np.array([0] * 1000 + [SPLIT_NAMES.index("adverb_1")] * 50 + [SPLIT_NAMES.index("visual")] * 7)
    full = assign_compositional(np.random.default_rng(seed), labels, np.arange(len(labels), dtype=np.uint64),
                                0.9, 0.01, k_shot)
    subset = sample_splits(np.random.default_rng([seed, 1]), full, size)
    again = sample_splits(np.random.default_rng([seed, 1]), full, size)
    assert all(np.array_equal(subset.splits[s], again.splits[s]) for s in full.splits)
    total = sum(len(v) for v in full.splits.values())
    assert sum(len(v) for v in subset.splits.values()) == min(size, total)
    train = subset.splits["train"]
    assert train[len(train) - k_shot:].tolist() == list(full.k_shot) and subset.k_shot == full.k_shot
    for name, indices in subset.splits.items():
        members = full.splits[name]
        assert np.array_equal(indices, members[np.isin(members, indices)]), name  # a subsequence of its split
        shared = len(members) - (k_shot if name == "train" else 0)
        quota = (size - k_shot) * shared / (total - k_shot) if size < total else shared
        assert abs(len(indices) - (k_shot if name == "train" else 0) - quota) < 1, name
