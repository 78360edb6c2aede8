"""The word modules a compositional network owns: one per module key of the parses, with
its arity, attention heads and antonym head pairs (WordNet sharing: big|small is one
module with two heads). The table is the model's vocabulary and is saved in checkpoints.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

import numpy as np

from gscan_ros.errors import CheckpointError, GraphError, LexiconError
from gscan_ros.language.graph import CommandGraph


@dataclass(frozen=True)
class ModuleSpec:
    """One word module: its key, number of argument slots and attention heads."""

    key: str
    arity: int
    num_heads: int = 1
    antonyms: tuple[tuple[int, int], ...] = ()  # head pairs whose maps should not overlap

    @property
    def slots(self) -> int:
        """Attention inputs: one per child; a leaf attends over the raw features (CG n=0 -> 1)."""
        return max(1, self.arity)

    def antonym_of(self, head: int) -> tuple[int, ...]:
        return tuple(b if a == head else a for a, b in self.antonyms if head in (a, b))


class ModuleTable:
    """The ordered set of word modules a network owns (the model's 'vocabulary')."""

    def __init__(self, specs: Iterable[ModuleSpec]):
        self.specs: tuple[ModuleSpec, ...] = tuple(sorted(specs, key=lambda s: s.key))
        self.index = {s.key: i for i, s in enumerate(self.specs)}
        self.level_cache: dict[str, list] = {}  # graph JSON -> _graph_levels(graph, self)
        if len(self.index) != len(self.specs):
            raise ValueError("duplicate module keys")
        bases = np.cumsum([0] + [s.num_heads for s in self.specs])
        self.unit_base = {s.key: int(b) for s, b in zip(self.specs, bases)}
        self.num_units = int(bases[-1])

    def __len__(self) -> int:
        return len(self.specs)

    def spec(self, key: str) -> ModuleSpec:
        return self.specs[self.index[key]]

    @classmethod
    def from_graphs(cls, graphs: Iterable[CommandGraph], lexicon=None) -> "ModuleTable":
        """Collect modules from parses; heads and antonym pairs come from the lexicon if it knows the key."""
        arity: dict[str, int] = {}
        heads: dict[str, int] = {}
        for g in graphs:
            for n in g.nodes:
                if arity.setdefault(n.module, n.arity) != n.arity:
                    raise GraphError(f"module {n.module!r} used with arities {arity[n.module]} and {n.arity}")
                heads[n.module] = max(heads.get(n.module, 1), n.head + 1)
        specs = []
        for key in arity:
            num_heads, pairs = _lexicon_heads(lexicon, key)
            specs.append(ModuleSpec(key, arity[key], max(num_heads, heads[key]), pairs))
        return cls(specs)

    def to_list(self) -> list[dict]:
        return [
            {"key": s.key, "arity": s.arity, "num_heads": s.num_heads, "antonyms": [list(p) for p in s.antonyms]}
            for s in self.specs
        ]

    @classmethod
    def from_list(cls, items: list[dict]) -> "ModuleTable":
        try:
            return cls(
                ModuleSpec(str(d["key"]), int(d["arity"]), int(d["num_heads"]), tuple(tuple(p) for p in d["antonyms"]))
                for d in items
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise CheckpointError(f"malformed module table in checkpoint: {exc}") from None


def _lexicon_heads(lexicon, key: str) -> tuple[int, tuple[tuple[int, int], ...]]:
    """(heads, antonym head pairs) of a concept module; (1, ()) for keys the lexicon does not
    group (structural keys like "NP_2", or no lexicon at all)."""
    if lexicon is None:
        return 1, ()
    try:
        heads = int(lexicon.num_heads(key))
        pairs = {tuple(sorted((int(a), int(b)))) for a, b in lexicon.antonym_heads(key)}
    except (LexiconError, KeyError):
        return 1, ()
    return heads, tuple(sorted(pairs))
