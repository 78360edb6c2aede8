"""Parsers by name: the three built-ins, plus any a user registers (spaCy, Stanza, ...)."""
from __future__ import annotations

from typing import Callable

from gscan_ros.errors import CommandError, quoted
from gscan_ros.language.constituency import ConstituencyParser
from gscan_ros.language.dependency import DependencyParser
from gscan_ros.language.lexicon import Lexicon
from gscan_ros.language.parser import Parser
from gscan_ros.language.semantic import SemanticParser

ParserFactory = Callable[[Lexicon], Parser]

_FACTORIES: dict[str, ParserFactory] = {
    SemanticParser.name: SemanticParser,
    ConstituencyParser.name: ConstituencyParser,
    DependencyParser.name: DependencyParser,
}
# The three parsers of Kuo et al. (2021), whatever else is registered later.
BUILTIN_PARSERS: tuple[str, ...] = tuple(_FACTORIES)
DEFAULT_PARSER = SemanticParser.name


def register_parser(name: str, factory: ParserFactory) -> None:
    """Make `get_parser(name, lexicon)` return `factory(lexicon)`; replaces an earlier entry."""
    if not name or not name.isidentifier():
        raise ValueError(f"parser name must be an identifier, got {name!r}")
    _FACTORIES[name] = factory


def available_parsers() -> tuple[str, ...]:
    return tuple(_FACTORIES)


def get_parser(name: str, lexicon: Lexicon | None = None) -> Parser:
    """A new parser `name` using `lexicon` for word modules (None: no shared concepts)."""
    try:
        factory = _FACTORIES[name]
    except KeyError:
        raise CommandError(f"unknown parser {quoted(name)}; available: {', '.join(_FACTORIES)}") from None
    return factory(lexicon if lexicon is not None else Lexicon.none())
