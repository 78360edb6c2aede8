"""Paraphrases of a gSCAN command: the inverse of `canonicalize`, for tests and bench/research/paraphrase.py.

Each content word is replaced by one of its accepted WordNet synonyms (or kept), "a"
becomes "a", "an" or "the", a color+size pair may take English order ("small red"),
and the case and trailing punctuation vary. `canonicalize(paraphrase(c, rng))` is `c`.
"""
from __future__ import annotations

import random
from collections import defaultdict
from functools import cache

from gscan_ros.language.synonyms import synonym_table
from gscan_ros.language.tokens import tokenize
from gscan_ros.world.types import COLOR_ADJECTIVES, SIZE_ADJECTIVES


@cache
def _synonyms_of() -> dict[str, tuple[str, ...]]:
    by_target: dict[str, list[str]] = defaultdict(list)
    for synonym in synonym_table().accepted.values():
        by_target[synonym.target].append(synonym.word)
    return {target: tuple(words) for target, words in by_target.items()}


def paraphrase(command: str, rng: random.Random) -> str:
    """A random paraphrase of the gSCAN command `command` (LexiconError without WordNet)."""
    tokens = list(tokenize(command))
    for i in range(len(tokens) - 1):  # English order: size before color
        if tokens[i] in COLOR_ADJECTIVES and tokens[i + 1] in SIZE_ADJECTIVES and rng.random() < 0.5:
            tokens[i], tokens[i + 1] = tokens[i + 1], tokens[i]
    words = []
    for token in tokens:
        if token == "a":
            words.append(rng.choice(("a", "an", "the")))
        else:
            words.append(rng.choice((token,) + _synonyms_of().get(token, ())))
    text = " ".join(words)
    text = rng.choice((text, text.capitalize(), text.upper()))
    return text + rng.choice(("", ".", "!"))
