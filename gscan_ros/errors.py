"""One exception family for the whole project.

Every error a user can cause (bad action, malformed dataset, unknown word, bad
checkpoint) derives from `GscanError`, so CLIs and nodes can report it as one line
without a traceback, and tests can assert the documented type. A message that quotes
what the user gave quotes it through `quoted`, so it stays one short line.
"""
import reprlib
from collections.abc import Sized

QUOTE_CHARS = 80
"""How much of a user's value an error message quotes."""

_REPR = reprlib.Repr()
_REPR.maxlevel = 3  # with reprlib's 6 items per container: at most 6**3 items looked at


def shortened(text: str, limit: int = QUOTE_CHARS) -> str:
    """`text`, or its first `limit` characters and how long it was (a name or a message
    that comes from a user's file)."""
    return text if len(text) <= limit else f"{text[:limit]}… ({len(text):,} characters)"


def quoted(value: object) -> str:
    """`repr(value)`, cut to about QUOTE_CHARS characters and then saying how big the value was.

    reprlib looks at a bounded part of a container, so quoting a 50 MB string or a
    YAML alias bomb costs no more than quoting a short value.
    """
    if isinstance(value, (str, bytes)):
        if len(value) <= QUOTE_CHARS:
            return repr(value)
        unit = "characters" if isinstance(value, str) else "bytes"
        return f"{value[:QUOTE_CHARS]!r}… ({len(value):,} {unit})"
    text = _REPR.repr(value)
    if len(text) <= QUOTE_CHARS and "..." not in text:  # reprlib's mark of what it left out
        return text
    size = f" ({len(value):,} items)" if isinstance(value, Sized) else ""
    return (text if len(text) <= QUOTE_CHARS else f"{text[:QUOTE_CHARS]}…") + size


class GscanError(Exception):
    """Base class of every user-facing error of gscan_ros."""


class InvalidActionError(GscanError):
    """An action that is unknown or cannot be executed in the current world state."""


class SituationError(GscanError):
    """A situation (or its gSCAN JSON) that is malformed or inconsistent."""


class DatasetFormatError(GscanError):
    """A dataset.txt / bag whose content does not follow the gSCAN format."""


class CommandError(GscanError):
    """A command that cannot be tokenized or parsed (unknown word, empty, too long ...)."""


class GraphError(GscanError):
    """A CommandGraph (or its JSON) that violates the graph invariants."""


class CheckpointError(GscanError):
    """A checkpoint that cannot be loaded or does not match the config/vocabulary."""


class LexiconError(GscanError):
    """WordNet data missing or unusable."""
