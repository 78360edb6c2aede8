"""Concept groups from WordNet: related words share one word module, one attention head each.

Paper §3.3: the transitive closure of WordNet synonyms and antonyms among the command
words becomes one module ("Small&Large"), with one attention head per word and an
auxiliary loss that keeps antonyms' attention maps apart. `Lexicon` is that grouping;
parsers ask it for each word's `(module_key, head)`, the model for head counts and
antonym pairs, and checkpoints store it (`to_dict`), so inference needs no WordNet.

Which parts of speech may link words is a switch (`parts_of_speech`). The default,
adjectives only, reproduces the original (only big/small shared): WordNet also lists
push<->pull as verb antonyms, but those verbs act on the *same* object, so a loss that
keeps their attention maps apart would be wrong (docs/language.md).

WordNet 3.0 comes from Debian's `wordnet-base` (/usr/share/wordnet) read with nltk's
reader; `_DebianWordNetReader` bridges the differences (see its docstring).
"""
from __future__ import annotations

import io
import os
import warnings
from dataclasses import dataclass
from functools import cache, lru_cache
from pathlib import Path
from typing import Iterable

import nltk
from nltk.corpus.reader.wordnet import WordNetCorpusReader

from gscan_ros.errors import LexiconError, quoted
from gscan_ros.language.tokens import CONTENT_WORDS

DEFAULT_WORDNET_DIR = "/usr/share/wordnet"
WORDNET_DIR_ENV = "GSCAN_WORDNET_DIR"
# WordNet parts of speech: a = adjective, s = satellite adjective, r = adverb, v = verb, n = noun.
ADJECTIVES = ("a", "s")
_ALL_POS = frozenset("asrvn")
_REQUIRED_FILES = tuple(f"{kind}.{pos}" for kind in ("index", "data") for pos in ("noun", "verb", "adj", "adv"))
# WordNet 3.0 lexicographer files in file-number order (wndb(5WN) "lexnames"); Debian omits the file.
_LEXNAMES = (
    ("adj.all", "adj.pert", "adv.all")
    + tuple(
        "noun." + n
        for n in (
            "Tops act animal artifact attribute body cognition communication event feeling food group location "
            "motive object person phenomenon plant possession process quantity relation shape state substance time"
        ).split()
    )
    + tuple(
        "verb." + v
        for v in (
            "body change cognition communication competition consumption contact creation emotion motion "
            "perception possession social stative weather"
        ).split()
    )
    + ("adj.ppl",)
)
_LEXNAME_POS = {"adj": 3, "adv": 4, "noun": 1, "verb": 2}
LEXICON_FORMAT = 1
# Lexicon names a config or command line may give (`Lexicon.named`).
LEXICONS = ("wordnet", "none")


@dataclass(frozen=True)
class Concept:
    """Words sharing one module; head i belongs to words[i] (words sorted)."""

    words: tuple[str, ...]
    antonyms: tuple[tuple[int, int], ...] = ()  # head pairs (i < j) whose maps must not overlap

    @property
    def key(self) -> str:
        return "|".join(self.words)


@dataclass(frozen=True)
class Lexicon:
    """Word -> (module key, head). Words outside every concept keep their own module."""

    concepts: tuple[Concept, ...] = ()
    parts_of_speech: tuple[str, ...] = ()  # WordNet POS the relations were taken from

    def __post_init__(self) -> None:
        seen: set[str] = set()
        for concept in self.concepts:
            if len(concept.words) < 2 or list(concept.words) != sorted(set(concept.words)):
                raise LexiconError(f"concept {concept.words} must list at least two distinct words, sorted")
            if seen & set(concept.words):
                raise LexiconError(f"words {sorted(seen & set(concept.words))} belong to two concepts")
            seen |= set(concept.words)
            for i, j in concept.antonyms:
                if not 0 <= i < j < len(concept.words):
                    raise LexiconError(f"antonym heads ({i}, {j}) out of range for concept {concept.key!r}")
        # Lookup tables (not dataclass fields: equality and hashing see only the concepts).
        object.__setattr__(self, "_heads", {w: (c.key, i) for c in self.concepts for i, w in enumerate(c.words)})
        object.__setattr__(self, "_by_key", {c.key: c for c in self.concepts})

    # ------------------------------------------------------------ construction
    @classmethod
    def named(cls, name: str) -> "Lexicon":
        """The lexicon a config's `lexicon: wordnet | none` means."""
        if name not in LEXICONS:
            raise LexiconError(f"lexicon must be one of {list(LEXICONS)}, got {quoted(name)}")
        return cls.from_wordnet() if name == "wordnet" else cls.none()

    @classmethod
    def none(cls) -> "Lexicon":
        """No sharing: every word is its own module (the 'no WordNet' ablation)."""
        return cls()

    @classmethod
    def from_wordnet(
        cls,
        vocabulary: Iterable[str] = CONTENT_WORDS,
        *,
        parts_of_speech: Iterable[str] = ADJECTIVES,
        wordnet_dir: str | os.PathLike | None = None,
    ) -> "Lexicon":
        """Concepts = connected components of WordNet synonym/antonym links among `vocabulary`.

        Only senses whose part of speech is in `parts_of_speech` count (default:
        adjectives; add "v" to also share push/pull). Computed once per process for
        each (vocabulary, parts of speech, directory); raises LexiconError if WordNet is missing.
        """
        pos = tuple(sorted(set(parts_of_speech)))
        if not set(pos) <= _ALL_POS:
            raise LexiconError(f"unknown WordNet parts of speech {sorted(set(pos) - _ALL_POS)}; use a, s, r, v, n")
        vocab = tuple(sorted({w.lower() for w in vocabulary}))
        return cls(_wordnet_concepts(vocab, pos, wordnet_root(wordnet_dir)), pos)

    # ------------------------------------------------------------------ lookup
    def module_for(self, word: str) -> tuple[str, int]:
        """(module key, attention head) of `word`."""
        return self._heads.get(word, (word, 0))

    def num_heads(self, module_key: str) -> int:
        concept = self._concept(module_key)
        return len(concept.words) if concept else 1

    def antonym_heads(self, module_key: str) -> list[tuple[int, int]]:
        concept = self._concept(module_key)
        return list(concept.antonyms) if concept else []

    def _concept(self, module_key: str) -> Concept | None:
        """The concept of a module key; per-arity keys ("big|small_0", dependency) included."""
        concept = self._by_key.get(module_key)
        if concept is None:
            base, _, arity = module_key.rpartition("_")
            concept = self._by_key.get(base) if arity.isdigit() else None
        return concept

    # --------------------------------------------------------------- storage
    def to_dict(self) -> dict:
        return {
            "format": LEXICON_FORMAT,
            "parts_of_speech": list(self.parts_of_speech),
            "concepts": [{"words": list(c.words), "antonyms": [list(p) for p in c.antonyms]} for c in self.concepts],
        }

    @classmethod
    def from_dict(cls, d: dict) -> "Lexicon":
        if not isinstance(d, dict) or d.get("format") != LEXICON_FORMAT:
            raise LexiconError(f"not a lexicon of format {LEXICON_FORMAT}: {str(d)[:80]}")
        try:
            concepts = tuple(
                Concept(tuple(str(w) for w in c["words"]), tuple((int(i), int(j)) for i, j in c["antonyms"]))
                for c in d["concepts"]
            )
            return cls(concepts, tuple(str(p) for p in d["parts_of_speech"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise LexiconError(f"malformed lexicon: {type(exc).__name__}: {exc}") from None


# ------------------------------------------------------------------- WordNet
class _DebianWordNetReader(WordNetCorpusReader):
    """nltk's WordNet reader on Debian's WordNet 3.0 files.

    nltk 3.10 (1) refuses roots outside `nltk.data.path` (and symlinked roots), (2)
    opens a `lexnames` file that Debian does not ship, and (3) maps synsets from the
    nltk_data WordNet version, which is not installed. `_open_wordnet` handles (1) by
    appending the resolved root to `nltk.data.path`; this class serves the fixed
    WordNet 3.0 lexnames table from memory (2) and skips the version map (3): the data
    is WordNet 3.0 itself, there is nothing to map.
    """

    def open(self, fileid):
        if fileid == "lexnames":
            return io.StringIO("".join(f"{i:02d} {name} {_LEXNAME_POS[name.split('.')[0]]}\n"
                                       for i, name in enumerate(_LEXNAMES)))
        return super().open(fileid)

    def map_wn(self, version="wordnet"):
        return None


def wordnet_root(wordnet_dir: str | os.PathLike | None = None) -> str:
    """The WordNet directory: `wordnet_dir`, else $GSCAN_WORDNET_DIR, else /usr/share/wordnet (resolved)."""
    return str(Path(wordnet_dir or os.environ.get(WORDNET_DIR_ENV) or DEFAULT_WORDNET_DIR).resolve())


def wordnet_reader(wordnet_dir: str | os.PathLike | None = None) -> WordNetCorpusReader:
    """nltk's reader on WordNet 3.0 (cached per process); LexiconError if the data is missing."""
    return _open_wordnet(wordnet_root(wordnet_dir))


@lru_cache(maxsize=1)
def _open_wordnet(root: str) -> _DebianWordNetReader:
    missing = [f for f in _REQUIRED_FILES if not os.path.isfile(os.path.join(root, f))]
    if missing:
        raise LexiconError(
            f"WordNet 3.0 data not found in {root} (missing {', '.join(missing)}); "
            f"install it with `apt-get install -y wordnet-base` or set {WORDNET_DIR_ENV}"
        )
    if root not in nltk.data.path:
        nltk.data.path.append(root)
    try:
        with warnings.catch_warnings():  # "multilingual functions are not available": expected, no OMW
            warnings.simplefilter("ignore", UserWarning)
            return _DebianWordNetReader(root, None)
    except (OSError, ValueError, AssertionError) as exc:
        raise LexiconError(f"cannot read WordNet in {root}: {exc}") from None


@cache
def _wordnet_concepts(vocab: tuple[str, ...], pos: tuple[str, ...], root: str) -> tuple[Concept, ...]:
    reader = _open_wordnet(root)
    synonyms, antonyms = _links(reader, vocab, frozenset(pos))
    parent = {w: w for w in vocab}  # union-find over the vocabulary

    def find(w: str) -> str:
        while parent[w] != w:
            w = parent[w]
        return w

    for a, b in synonyms | antonyms:
        parent[find(a)] = find(b)
    groups: dict[str, list[str]] = {}
    for w in vocab:
        groups.setdefault(find(w), []).append(w)
    concepts = []
    for words in sorted(sorted(g) for g in groups.values() if len(g) > 1):
        pairs = tuple(
            (i, j) for i in range(len(words)) for j in range(i + 1, len(words))
            if frozenset((words[i], words[j])) in antonyms
        )
        concepts.append(Concept(tuple(words), pairs))
    return tuple(concepts)


def _links(reader, vocab: tuple[str, ...], pos: frozenset[str]) -> tuple[set[frozenset], set[frozenset]]:
    """Synonym pairs (a shared synset) and antonym pairs among `vocab`.

    `a` and `b` are antonyms when a lemma `a` has an antonym lemma whose synset holds
    `b` (WordNet puts big in large.a.01, whose lemma "large" is small's antonym).
    """
    known = set(vocab)
    synonyms: set[frozenset] = set()
    antonyms: set[frozenset] = set()
    for word in vocab:
        name = word.replace(" ", "_")
        for synset in reader.synsets(name):
            if synset.pos() not in pos:
                continue
            for lemma in synset.lemmas():
                other = lemma.name().replace("_", " ").lower()
                if other in known and other != word:
                    synonyms.add(frozenset((word, other)))
                if lemma.name().lower() != name:
                    continue
                for opposite in lemma.antonyms():
                    for other in opposite.synset().lemma_names():
                        other = other.replace("_", " ").lower()
                        if other in known and other != word:
                            antonyms.add(frozenset((word, other)))
    return synonyms, antonyms
