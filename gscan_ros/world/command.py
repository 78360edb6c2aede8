"""The gSCAN command frame: verb, manner and referring expression (LauraRuis/groundedSCAN `grammar.py`, `LogicalForm`).

This is the planner's minimal reading of a command. `split_command` accepts the
dataset's comma-joined form and plain space-joined text; the user-facing
tokenizer with its richer errors lives in `gscan_ros.language` and builds on it.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Sequence

from gscan_ros.errors import CommandError, quoted
from gscan_ros.world.types import (
    ADVERBS,
    COLOR_ADJECTIVES,
    INTRANSITIVE_VERBS,
    NOUNS,
    SIZE_ADJECTIVES,
    TRANSITIVE_VERBS,
)

_SEPARATORS = re.compile(r"[\s,]+")


def split_command(text: str) -> tuple[str, ...]:
    """gSCAN tokens of a command; "while spinning"/"while zigzagging" become one token.

    Accepts "walk to a red circle while spinning" and the dataset's
    "walk,to,a,red,circle,while spinning". Lower-cases; does not check the words.
    """
    words = [w for w in _SEPARATORS.split(text.strip().lower()) if w]
    tokens: list[str] = []
    i = 0
    while i < len(words):
        if words[i] == "while" and i + 1 < len(words):
            tokens.append(f"while {words[i + 1]}")
            i += 2
        else:
            tokens.append(words[i])
            i += 1
    return tuple(tokens)


@dataclass(frozen=True)
class CommandFrame:
    """What a gSCAN command asks for. Absent parts are None.

    `verb` walk|push|pull; `manner` one of the four adverbs; `color`, `size`
    ("small"/"big", relative to the objects of the same name) and `shape` describe the referent.
    """

    verb: str
    manner: str | None
    color: str | None
    size: str | None
    shape: str

    @classmethod
    def from_tokens(cls, tokens: Sequence[str]) -> "CommandFrame":
        """Read gSCAN's adverb grammar (docs/language.md, "Grammars"); raises CommandError on anything else.

        Form: `walk to a` | `push a` | `pull a`, then [COLOR] [SIZE] NOUN (color
        before size, each at most once), then at most one adverb.
        """
        toks = tuple(tokens)
        text = " ".join(toks)
        if not toks:
            raise CommandError("empty command")
        verb = toks[0]
        if verb in INTRANSITIVE_VERBS:
            prefix = (verb, "to", "a")
        elif verb in TRANSITIVE_VERBS:
            prefix = (verb, "a")
        else:
            raise CommandError(f"command {quoted(text)}: expected a verb (walk, push, pull) first, got {quoted(verb)}")
        if toks[: len(prefix)] != prefix:
            raise CommandError(f"command {quoted(text)}: expected it to start with {' '.join(prefix)!r}")
        rest = list(toks[len(prefix):])
        manner = rest.pop() if rest and rest[-1] in ADVERBS else None
        if not rest or rest[-1] not in NOUNS:
            raise CommandError(f"command {quoted(text)}: expected a noun ({', '.join(NOUNS)}) before the adverb/end")
        shape = rest.pop()
        color = rest.pop(0) if rest and rest[0] in COLOR_ADJECTIVES else None
        size = rest.pop(0) if rest and rest[0] in SIZE_ADJECTIVES else None
        if rest:
            raise CommandError(
                f"command {text!r}: unexpected {rest[0]!r}; the noun takes at most a color then a size "
                f"({', '.join(COLOR_ADJECTIVES)}; {', '.join(SIZE_ADJECTIVES)})"
            )
        return cls(verb, manner, color, size, shape)

    @classmethod
    def parse(cls, command: str | Sequence[str]) -> "CommandFrame":
        """From text (split with `split_command`) or an already split token sequence."""
        return cls.from_tokens(split_command(command) if isinstance(command, str) else command)

    def tokens(self) -> tuple[str, ...]:
        head = (self.verb, "to", "a") if self.verb in INTRANSITIVE_VERBS else (self.verb, "a")
        optional = (self.color, self.size)
        return head + tuple(w for w in optional if w) + (self.shape,) + ((self.manner,) if self.manner else ())

    @property
    def text(self) -> str:
        """Space-joined tokens, the `Episode.command` form."""
        return " ".join(self.tokens())

    @property
    def referred_target(self) -> str:
        """The dataset's `referred_target`: size-color-noun with empty parts kept (docs/data.md, "dataset.txt")."""
        return f"{self.size or ''} {self.color or ''} {self.shape}"

    @property
    def object_name(self) -> str:
        """The name objects are looked up by: the noun, or color + noun (docs/world.md, "Planner")."""
        return f"{self.color} {self.shape}" if self.color else self.shape
