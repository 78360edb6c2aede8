"""Split assignment: hold-out rules B-H, random test/dev, de-duplication, k-shot (LauraRuis/groundedSCAN `dataset.py`).

The rules only look at the command, the target object and the direction to the
target, so they are decided before an example is planned; examples matching more than
one rule are dropped (as the original generator does). The set operations work on
arrays of example indices and are driven by one seeded Generator; `sample_splits`
draws a subset (`generate --examples`) split by split.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Callable, Iterable, Mapping

import numpy as np

from gscan_ros.data.commands import Command
from gscan_ros.data.sampling import ObjectSpec
from gscan_ros.errors import DatasetFormatError

# Released split keys, in the order dataset.txt lists them.
SPLIT_NAMES = (
    "train", "dev", "test", "visual", "situational_1", "situational_2", "contextual",
    "adverb_1", "adverb_2", "visual_easier", "target_lengths",
)
K_SHOT_SPLIT = "adverb_1"


@dataclass(frozen=True)
class HoldOutRule:
    letter: str
    split: str
    description: str
    holds_out: Callable[[Command, ObjectSpec, str], bool]


# groundedSCAN `dataset.py` `assign_splits`. B needs "yellow" in the command; F tests no color (the original
# comment says "red square" but the code does not check it).
HOLD_OUT_RULES: tuple[HoldOutRule, ...] = (
    HoldOutRule("B", "visual_easier", "yellow square target referred to with 'yellow'",
                lambda c, t, d: c.color == "yellow" and t.color == "yellow" and t.shape == "square"),
    HoldOutRule("C", "visual", "red square target",
                lambda c, t, d: t.color == "red" and t.shape == "square"),
    HoldOutRule("D", "situational_1", "target south-west of the agent",
                lambda c, t, d: d == "sw"),
    HoldOutRule("E", "situational_2", "size-2 circle target referred to as 'small'",
                lambda c, t, d: c.size == "small" and t.shape == "circle" and t.size == 2),
    HoldOutRule("F", "contextual", "push a size-3 square",
                lambda c, t, d: c.verb == "push" and t.shape == "square" and t.size == 3),
    HoldOutRule("G", "adverb_1", "adverb 'cautiously'",
                lambda c, t, d: c.adverb == "cautiously"),
    HoldOutRule("H", "adverb_2", "pull while spinning",
                lambda c, t, d: c.verb == "pull" and c.adverb == "while spinning"),
)


# Letters of the test splits, as the gSCAN paper (Ruis et al. 2020, Table 1) and Kuo et
# al. (2021, Tables 1-2) name them: A the random test split, B-H the hold-out rules, I
# the target-length split.
SPLIT_LETTERS: dict[str, str] = {
    "test": "A", **{rule.split: rule.letter for rule in sorted(HOLD_OUT_RULES, key=lambda r: r.letter)},
    "target_lengths": "I",
}
# Test splits of each dataset kind, in letter order (the length data's `test` holds the
# trained-on lengths, e.g. Kuo et al. Table 2's row 15).
TEST_SPLITS: dict[str, tuple[str, ...]] = {
    "compositional": tuple(s for s in SPLIT_LETTERS if s != "target_lengths"),
    "length": ("test", "target_lengths"),
}
SPLIT_KINDS = tuple(TEST_SPLITS)
ALL_TEST_SPLITS = tuple(SPLIT_LETTERS)


def held_out_splits(command: Command, target: ObjectSpec, direction: str) -> tuple[str, ...]:
    """Keys of every hold-out rule the example matches (empty: training pool)."""
    return tuple(rule.split for rule in HOLD_OUT_RULES if rule.holds_out(command, target, direction))


def take_fraction(rng: np.random.Generator, indices: np.ndarray, fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """(rest, taken): int(fraction * n) indices drawn without replacement, both sorted."""
    return take(rng, indices, int(fraction * len(indices)))


def take(rng: np.random.Generator, indices: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """(rest, taken): `count` indices drawn without replacement, both in their order in `indices`."""
    mask = np.zeros(len(indices), dtype=bool)
    mask[rng.choice(len(indices), size=count, replace=False)] = True
    return indices[~mask], indices[mask]


def discard_equivalent(test: np.ndarray, train: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """Test indices whose equivalence key (command, target sequence, target cell) no
    training example has; one hash-set lookup per example instead of pairwise compares."""
    return test[~np.isin(keys[test], keys[train])]


@dataclass
class SplitResult:
    """Example indices per split (generation order; k-shot examples last in train)."""

    splits: dict[str, np.ndarray]
    dropped_multiple_rules: int = 0
    discarded_equivalent: int = 0
    k_shot: tuple[int, ...] = ()  # generation indices moved from adverb_1 to train


def assign_compositional(rng: np.random.Generator, labels: np.ndarray, keys: np.ndarray,
                         percentage_train: float, percentage_dev: float, k_shot: int,
                         dropped: int = 0) -> SplitResult:
    """Splits A-H from per-example labels (index into SPLIT_NAMES; 0 = training pool).

    Order as in the original: random test from the pool, drop test examples equivalent
    to a training one, dev from the remaining train, then move k adverb_1 examples.
    """
    indices = np.arange(len(labels))
    train, test = take_fraction(rng, indices[labels == 0], 1.0 - percentage_train)
    kept_test = discard_equivalent(test, train, keys)
    train, dev = take_fraction(rng, train, percentage_dev)
    splits = {"train": train, "dev": dev, "test": kept_test}
    for rule in HOLD_OUT_RULES:
        splits[rule.split] = indices[labels == SPLIT_NAMES.index(rule.split)]
    adverb = splits[K_SHOT_SPLIT]
    moved = np.sort(rng.choice(len(adverb), size=min(k_shot, len(adverb)), replace=False))
    splits["train"] = np.concatenate([train, adverb[moved]])
    splits[K_SHOT_SPLIT] = np.delete(adverb, moved)
    return SplitResult(
        splits={name: splits[name] for name in SPLIT_NAMES if name in splits},
        dropped_multiple_rules=dropped,
        discarded_equivalent=len(test) - len(kept_test),
        k_shot=tuple(int(i) for i in adverb[moved]),
    )


def assign_length(rng: np.random.Generator, lengths: np.ndarray, keys: np.ndarray, cut_off: int,
                  percentage_train: float, percentage_dev: float) -> SplitResult:
    """Split I: target length > cut_off goes to `target_lengths`; random test and dev
    are drawn from the rest (the released key layout, quirk Q13, docs/model.md)."""
    indices = np.arange(len(lengths))
    long = indices[lengths > cut_off]
    train, test = take_fraction(rng, indices[lengths <= cut_off], 1.0 - percentage_train)
    kept_test = discard_equivalent(test, train, keys)
    train, dev = take_fraction(rng, train, percentage_dev)
    return SplitResult(
        splits={"train": train, "dev": dev, "test": kept_test, "target_lengths": long},
        discarded_equivalent=len(test) - len(kept_test),
    )


def sample_splits(rng: np.random.Generator, result: SplitResult, size: int) -> SplitResult:
    """A `size`-example subset of `result`, split by split, so each example keeps its split.

    The k-shot examples stay (train keeps its K "cautiously" examples, last); the other
    `size - K` are shared out over the splits in proportion to their sizes (largest
    remainders) and drawn within each split, in the order `result` lists them.
    """
    k = len(result.k_shot)
    pools = {name: indices[:len(indices) - k] if name == "train" else indices
             for name, indices in result.splits.items()}
    counts = _apportion(size - k, np.array([len(v) for v in pools.values()], dtype=np.int64))
    splits = {name: take(rng, indices, int(count))[1] for (name, indices), count in zip(pools.items(), counts)}
    splits["train"] = np.concatenate([splits["train"], result.splits["train"][len(pools["train"]):]])
    return SplitResult(splits=splits, dropped_multiple_rules=result.dropped_multiple_rules,
                       discarded_equivalent=result.discarded_equivalent, k_shot=result.k_shot)


def _apportion(total: int, sizes: np.ndarray) -> np.ndarray:
    """`total` shared out in proportion to `sizes` (Hamilton's largest remainders, in
    integers): each share within one of its exact quota, none above its size."""
    if total >= sizes.sum():
        return sizes
    quotas, remainders = np.divmod(total * sizes, sizes.sum())
    quotas[np.argsort(-remainders, kind="stable")[:total - quotas.sum()]] += 1
    return quotas


def require_splits(wanted: Iterable[str], counts: Mapping[str, int], source: str | os.PathLike) -> None:
    """Refuse requested splits that `source` has no examples of (absent, empty or misspelt),
    naming them and the splits it has: the one check of dataset.txt and bag readers."""
    missing = [split for split in wanted if not counts.get(split)]
    if missing:
        present = ", ".join(split for split, n in counts.items() if n) or "none"
        raise DatasetFormatError(f"no examples in split(s) {', '.join(missing)} of {source} (it has: {present})")
