"""WordNet synonyms of the trained words: what an operator may type instead of them.

Paper §3.3 builds the lexicon from WordNet synonyms and antonyms; the module sharing
(`Lexicon`) uses the antonym half among the trained words, this table the synonym
half: a word WordNet ties to a trained word is read as that word, so it reaches the
trained module and attention head with no training ("large" -> big, "little" -> small).

The table is generated from WordNet, not written by hand. `GSCAN_SENSES` picks, per
trained content word, the WordNet synset of the sense gSCAN uses (big: large.a.01,
"above average in size"; circle: circle.n.01, the shape). Its candidates are the other
lemmas of that synset and, for a head adjective, the lemmas of the satellite synsets
WordNet links to it as similar (`similar_tos`: huge.s.01 -> large.a.01). A candidate is
left out, with the reason kept in `SynonymTable.left_out`, when it is:

- not one word ("king_size", "king-size"): the tokenizer reads runs of letters;
- in a sense of `EXCLUDED_SENSES` (a similar satellite that is not about the relative
  size of an object on a grid: deep.s.09, microscopic.s.03, ...);
- in `EXCLUDED_WORDS` (a lemma of a chosen sense whose everyday reading in a command
  is another: "draw a circle" means sketching one, not pull.v.01);
- tied to two trained words ("force" is in push.v.01 and pull.v.01).

docs/language.md lists the accepted table and what was left out (a test keeps it in
step). The clause adverbs "while spinning"/"while zigzagging" have no WordNet entry.
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass
from functools import cache
from types import MappingProxyType
from typing import Mapping

from nltk.corpus.reader.wordnet import WordNetError

from gscan_ros.errors import LexiconError
from gscan_ros.language.lexicon import wordnet_reader, wordnet_root

# The WordNet sense gSCAN uses for each trained content word (adjectives as adjectives:
# colours are the satellites red.s.01 ..., sizes the heads large.a.01 / small.a.01).
GSCAN_SENSES: Mapping[str, str] = MappingProxyType({
    "walk": "walk.v.01",  # use one's feet to advance; advance by steps
    "push": "push.v.01",  # move with force
    "pull": "pull.v.01",  # cause to move by pulling
    "circle": "circle.n.01",  # ellipse in which the two axes are of equal length
    "square": "square.n.01",  # a plane rectangle with four equal sides
    "cylinder": "cylinder.n.01",  # a solid bounded by a cylindrical surface and two parallel planes
    "red": "red.s.01",
    "green": "green.s.01",
    "yellow": "yellow.s.01",
    "blue": "blue.s.01",
    "big": "large.a.01",  # above average in size or number or quantity or magnitude or extent
    "small": "small.a.01",  # limited or below average in number or quantity or magnitude or extent
    "cautiously": "cautiously.r.01",  # with caution or prudence or tact
    "hesitantly": "hesitantly.r.01",  # with hesitation
})

_INVISIBLE = "too small to see, and every object on the grid is visible"
# Satellites similar to large.a.01 / small.a.01 whose sense is not an object's size on a grid.
EXCLUDED_SENSES: Mapping[str, str] = MappingProxyType({
    "great.s.01": "'great circle' is a geometry term and 'great' mostly means excellent",
    "astronomic.s.01": "astronomical scale (astronomic, galactic)",
    "cosmic.s.01": "extent in space or time",
    "deep.s.09": "depth or quantity, not size",
    "epic.s.01": "impressiveness (epic, heroic)",
    "life-size.s.01": "the size of an original, not relative size",
    "volumed.s.01": "a shape: rising in rounded masses",
    "blown-up.s.01": "made larger, as of a photograph (enlarged)",
    "double.s.04": "large enough for two; reads as a count",
    "titanic.s.01": "force or power",
    "bouffant.s.01": "hair or clothing (bouffant, puffy)",
    "broad.s.05": "expanse or width (broad, spacious, wide), not an object's size",
    "capacious.s.01": "capacity of a container",
    "super.s.03": "'super' mostly means excellent",
    "macro.s.01": "scale or scope",
    "rangy.s.03": "room for ranging",
    "macroscopic.s.02": "visible to the naked eye: says nothing about relative size",
    "extensive.s.01": "extent of an area or range (extensive, extended)",
    "grand.s.06": "'grand' mostly means impressive",
    "gnomish.s.01": "deformed creatures",
    "micro.s.01": "scale or scope",
    "pocket-size.s.02": "portability (pocketable)",
    "subatomic.s.01": _INVISIBLE,
    "atomic.s.01": _INVISIBLE,
    "microscopic.s.03": _INVISIBLE,
    "infinitesimal.s.01": _INVISIBLE + " (infinitesimal, minute)",
    "slender.s.04": "quantity; 'slender' and 'slim' describe a thin shape",
})
# Lemmas of a chosen sense whose everyday reading in a grid-world command is another.
EXCLUDED_WORDS: Mapping[str, str] = MappingProxyType({
    "draw": "'draw a circle' means sketching one, not pulling it (pull.v.01)",
})

_ONE_WORD = re.compile(r"[a-z]+")


@dataclass(frozen=True)
class Synonym:
    """`word` is read as the trained word `target`; WordNet puts it in `synset`."""

    word: str
    target: str
    synset: str
    sense: str  # target's gSCAN sense: `synset` itself, or the head `synset` is similar to

    @property
    def reason(self) -> str:
        if self.synset == self.sense:
            return f"WordNet synonym in {self.sense}"
        return f"WordNet {self.synset}, similar to {self.sense}"


@dataclass(frozen=True)
class SynonymTable:
    accepted: Mapping[str, Synonym]  # word -> how it maps; words sorted by target, then word
    left_out: Mapping[str, str]  # candidate word -> why it is not accepted

    def lookup(self, word: str) -> Synonym | None:
        return self.accepted.get(word)


def synonym_table(wordnet_dir: str | os.PathLike | None = None) -> SynonymTable:
    """The table generated from WordNet (cached per process); LexiconError without WordNet."""
    return _table(wordnet_root(wordnet_dir))


@cache
def _table(root: str) -> SynonymTable:
    reader = wordnet_reader(root)
    targets: dict[str, dict[str, Synonym]] = {}  # word -> target -> first route to it
    left_out: dict[str, str] = {}
    for target, sense_name in GSCAN_SENSES.items():
        try:
            sense = reader.synset(sense_name)
        except (WordNetError, ValueError) as exc:  # another WordNet version than 3.0
            raise LexiconError(f"WordNet in {root} has no synset {sense_name} ({target}'s sense): {exc}") from None
        routes = [sense] + (sense.similar_tos() if sense.pos() == "a" else [])
        for synset in routes:
            for lemma in synset.lemma_names():
                word = lemma.replace("_", " ").lower()
                if word == target:
                    continue
                if not _ONE_WORD.fullmatch(word):
                    left_out[word] = "not a single word"
                elif synset.name() in EXCLUDED_SENSES:
                    left_out[word] = f"{synset.name()}: {EXCLUDED_SENSES[synset.name()]}"
                elif word in EXCLUDED_WORDS:
                    left_out[word] = EXCLUDED_WORDS[word]
                else:
                    targets.setdefault(word, {}).setdefault(target, Synonym(word, target, synset.name(), sense_name))
    accepted: dict[str, Synonym] = {}
    for word, by_target in targets.items():
        if len(by_target) > 1:
            routes = " and ".join(f"{s.synset} ({t})" for t, s in by_target.items())
            left_out[word] = f"ambiguous: in {routes}"
        else:
            left_out.pop(word, None)  # accepted through one sense, whatever another left out
            accepted[word] = next(iter(by_target.values()))
    order = list(GSCAN_SENSES)
    ranked = sorted(accepted.values(), key=lambda s: (order.index(s.target), s.word))
    return SynonymTable(
        MappingProxyType({s.word: s for s in ranked}),
        MappingProxyType(dict(sorted(left_out.items()))),
    )
