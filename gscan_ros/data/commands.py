"""The 675 gSCAN commands of the `adverb` grammar (LauraRuis/groundedSCAN `grammar.py`) and their dataset fields.

The grammar (ROOT -> VP; VP -> VP RB once; VP -> VV_intrans 'to' DP | VV_trans DP;
DP -> 'a' NP; NP -> JJ NP at most twice; NP -> NN) with the rule that two adjectives
never share a category, and colors come before sizes, yields exactly
3 verbs x 3 nouns x 15 adjective choices x 5 adverb choices = 675 commands. Rather
than enumerating templates we enumerate those slots directly, in one fixed order, and
derive the strings the released data stores with each example: the comma-joined
command and meaning, the depth-first constituency derivation and `referred_target`
(size-color-noun, empty parts kept).
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass
from functools import cached_property
from typing import Iterable

from gscan_ros.errors import CommandError, quoted
from gscan_ros.world.command import CommandFrame, split_command
from gscan_ros.world.types import (
    ADVERBS,
    COLOR_ADJECTIVES,
    INTRANSITIVE_VERBS,
    NOUNS,
    SIZE_ADJECTIVES,
    TRANSITIVE_VERBS,
)

# Phrase-structure rules as the released `grammar` header and derivations spell them.
RULE_ROOT = "ROOT -> VP"
RULE_VP_ADVERB = "VP -> VP RB"
RULE_VP_INTRANSITIVE = "VP -> VV_intrans 'to' DP"
RULE_VP_TRANSITIVE = "VP -> VV_trans DP"
RULE_DP = "DP -> 'a' NP"
RULE_NP_ADJECTIVE = "NP -> JJ NP"
RULE_NP_NOUN = "NP -> NN"
PHRASE_RULES = (
    RULE_ROOT,
    RULE_VP_ADVERB,
    RULE_VP_INTRANSITIVE,
    RULE_VP_TRANSITIVE,
    RULE_DP,
    RULE_NP_ADJECTIVE,
    RULE_NP_NOUN,
)
# Preterminal names of the lexical rules ("VV_intransitive -> walk").
LEXICAL_CATEGORIES = (
    ("VV_intransitive", INTRANSITIVE_VERBS),
    ("VV_transitive", TRANSITIVE_VERBS),
    ("RB", ADVERBS),
    ("NN", NOUNS),
    ("JJ", COLOR_ADJECTIVES + SIZE_ADJECTIVES),
)


def grammar_string() -> str:
    """The `grammar` header field: every rule followed by ';' (phrase rules, then lexicon)."""
    lexical = [f"{cat} -> {word}" for cat, words in LEXICAL_CATEGORIES for word in words]
    return "".join(f"{rule};" for rule in (*PHRASE_RULES, *lexical))


@dataclass(frozen=True)
class Command:
    """One gSCAN command as its grammatical slots; empty strings mark unused slots."""

    verb: str
    noun: str
    color: str = ""
    size: str = ""
    adverb: str = ""

    @property
    def transitive(self) -> bool:
        return self.verb in TRANSITIVE_VERBS

    @cached_property
    def frame(self) -> CommandFrame:
        """The planner's view of the command (for `gscan_ros.world.demonstrate`)."""
        return CommandFrame(self.verb, self.adverb or None, self.color or None, self.size or None, self.noun)

    @cached_property
    def tokens(self) -> tuple[str, ...]:
        """gSCAN tokens ("while spinning" is one token): the frame's."""
        return self.frame.tokens()

    @property
    def text(self) -> str:
        """Space-joined tokens, the command form used across gscan_ros."""
        return self.frame.text

    @property
    def json_text(self) -> str:
        """Comma-joined tokens, the `command` (and `meaning`) field of dataset.txt."""
        return ",".join(self.tokens)

    @property
    def referred_target(self) -> str:
        """`referred_target` field: size, color, noun joined by spaces, empty parts kept."""
        return self.frame.referred_target

    @cached_property
    def derivation(self) -> str:
        """Depth-first constituency derivation "<rules>;<lexicon>" as in released data (docs/data.md, "Commands").

        Rules are listed children-before-parent; the lexicon lists symbols in the order
        they are first met, a preterminal's rules most recent first (hence
        "NT:JJ -> small:JJ -> red" for "red small").
        """
        adjectives = [w for w in (self.color, self.size) if w]
        rules = [RULE_NP_NOUN] + [RULE_NP_ADJECTIVE] * len(adjectives) + [RULE_DP]
        rules.append(RULE_VP_TRANSITIVE if self.transitive else RULE_VP_INTRANSITIVE)
        if self.adverb:
            rules.append(RULE_VP_ADVERB)
        rules.append(RULE_ROOT)

        verb_category = "VV_transitive" if self.transitive else "VV_intransitive"
        lexicon = [f"T:{self.verb}", f"NT:{verb_category} -> {self.verb}"]
        lexicon += [] if self.transitive else ["T:to"]
        lexicon.append("T:a")
        if adjectives:
            lexicon.append(f"T:{adjectives[0]}")
            lexicon.append("NT:" + ":".join(f"JJ -> {w}" for w in reversed(adjectives)))
            lexicon += [f"T:{w}" for w in adjectives[1:]]
        lexicon += [f"T:{self.noun}", f"NT:NN -> {self.noun}"]
        if self.adverb:
            lexicon += [f"T:{self.adverb}", f"NT:RB -> {self.adverb}"]
        return ",".join(rules) + ";" + ",".join(lexicon)


def _enumerate() -> tuple[Command, ...]:
    """All commands: adverb-free first, then per adverb; within, verb, color, size, noun."""
    return tuple(
        Command(verb=verb, noun=noun, color=color, size=size, adverb=adverb)
        for adverb, verb, color, size, noun in itertools.product(
            ("",) + ADVERBS,
            INTRANSITIVE_VERBS + TRANSITIVE_VERBS,
            ("",) + COLOR_ADJECTIVES,
            ("",) + SIZE_ADJECTIVES,
            NOUNS,
        )
    )


COMMANDS: tuple[Command, ...] = _enumerate()
ALL_COMMANDS: tuple[str, ...] = tuple(c.text for c in COMMANDS)
_BY_TOKENS = {c.tokens: c for c in COMMANDS}


def parse_command(command: str | Iterable[str]) -> Command:
    """The Command for a space-joined, comma-joined or tokenized gSCAN command.

    Raises CommandError for anything outside the 675 commands.
    """
    tokens = split_command(command) if isinstance(command, str) else tuple(command)
    try:
        return _BY_TOKENS[tokens]
    except KeyError:
        raise CommandError(f"not a gSCAN command: {quoted(' '.join(tokens))}") from None
