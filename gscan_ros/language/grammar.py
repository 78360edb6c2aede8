"""The gSCAN command language as two nltk CFGs over gSCAN tokens, and the 675 commands.

- `gscan_grammar()` restates the generator's grammar (LauraRuis/groundedSCAN `grammar.py`): ROOT -> VP,
  VP -> VP RB (once), VP -> VV_intrans 'to' DP | VV_trans DP, DP -> 'a' NP,
  NP -> JJ NP | NN. gSCAN limits NP -> JJ NP to two uses, never repeats an adjective
  category and puts colors before sizes; those limits are written into the rules
  (NP -> JJ_color NP_size | NP_size ...), so the CFG derives exactly the 675 commands
  and `nltk.parse.generate` enumerates them without filtering.
- `phrase_grammar()` covers the same language with English phrase structure as an
  off-the-shelf constituency parser would analyse it (S, VP, PP, NP, ADVP, SBAR; flat
  NP and VP as in the paper's Fig. 2a). Preterminals use Penn tags with a hyphenated
  subcategory ("JJ-COLOR"); the part before the hyphen is the tag.

Both are built with `CFG.fromstring` from the vocabulary tables (quirk Q5, docs/model.md: the original
loaded a grammar file through `nltk.data.load`, which nltk 3.10 refuses).
"""
from __future__ import annotations

from functools import cache

from nltk.grammar import CFG
from nltk.parse.chart import BottomUpLeftCornerChartParser
from nltk.parse.generate import generate
from nltk.tree import Tree

from gscan_ros.errors import CommandError, quoted
from gscan_ros.world.types import (
    ADVERBS,
    COLOR_ADJECTIVES,
    INTRANSITIVE_VERBS,
    NOUNS,
    SIZE_ADJECTIVES,
    TRANSITIVE_VERBS,
)

# Adverbs that are one word in English ("cautiously") vs subordinate clauses ("while spinning").
MANNER_ADVERBS: tuple[str, ...] = tuple(a for a in ADVERBS if " " not in a)
CLAUSE_ADVERBS: tuple[str, ...] = tuple(a for a in ADVERBS if " " in a)


def _words(words: tuple[str, ...]) -> str:
    return " | ".join(f"'{w}'" for w in words)


def gscan_grammar_text() -> str:
    """gSCAN's own grammar (category names as in the generator), limits made explicit."""
    return f"""
        ROOT -> VP
        VP -> VP_plain RB | VP_plain
        VP_plain -> VV_intrans 'to' DP | VV_trans DP
        DP -> 'a' NP
        NP -> JJ_color NP_size | NP_size
        NP_size -> JJ_size NP_noun | NP_noun
        NP_noun -> NN
        VV_intrans -> {_words(INTRANSITIVE_VERBS)}
        VV_trans -> {_words(TRANSITIVE_VERBS)}
        RB -> {_words(ADVERBS)}
        JJ_color -> {_words(COLOR_ADJECTIVES)}
        JJ_size -> {_words(SIZE_ADJECTIVES)}
        NN -> {_words(NOUNS)}
    """


def phrase_grammar_text() -> str:
    """English phrase structure of the same language (flat NP and VP, like Fig. 2a)."""
    return f"""
        S -> VP
        VP -> VB-INTRANS PP | VB-INTRANS PP ADVP | VB-INTRANS PP SBAR
        VP -> VB-TRANS NP | VB-TRANS NP ADVP | VB-TRANS NP SBAR
        PP -> TO NP
        NP -> DT NN | DT JJ-COLOR NN | DT JJ-SIZE NN | DT JJ-COLOR JJ-SIZE NN
        ADVP -> RB
        SBAR -> {_words(CLAUSE_ADVERBS)}
        VB-INTRANS -> {_words(INTRANSITIVE_VERBS)}
        VB-TRANS -> {_words(TRANSITIVE_VERBS)}
        TO -> 'to'
        DT -> 'a'
        JJ-COLOR -> {_words(COLOR_ADJECTIVES)}
        JJ-SIZE -> {_words(SIZE_ADJECTIVES)}
        NN -> {_words(NOUNS)}
        RB -> {_words(MANNER_ADVERBS)}
    """


@cache
def gscan_grammar() -> CFG:
    return CFG.fromstring(gscan_grammar_text())


@cache
def phrase_grammar() -> CFG:
    return CFG.fromstring(phrase_grammar_text())


@cache
def _chart_parser(grammar: CFG) -> BottomUpLeftCornerChartParser:
    return BottomUpLeftCornerChartParser(grammar)


def parse_tree(grammar: CFG, tokens: tuple[str, ...]) -> Tree:
    """The (unique) derivation of `tokens`; CommandError if the grammar rejects them.

    Both grammars are unambiguous, so the first chart parse is the parse.
    """
    try:
        tree = next(iter(_chart_parser(grammar).parse(tokens)), None)
    except ValueError as exc:  # a token the grammar has no rule for
        raise CommandError(f"{quoted(' '.join(tokens))} is not in the gSCAN command grammar ({exc})") from None
    if tree is None:
        raise CommandError(
            f"{quoted(' '.join(tokens))} is not in the gSCAN command grammar "
            "(expected e.g. 'walk to a red small circle cautiously' or 'push a big square')"
        )
    return tree


@cache
def all_commands() -> tuple[str, ...]:
    """The 675 gSCAN commands (space-joined tokens), enumerated from `gscan_grammar()`."""
    return tuple(" ".join(tokens) for tokens in generate(gscan_grammar()))
