"""What a parser is (`Parser`), the base of the built-in grammar parsers, and graph assembly.

Any object with a `name` and `parse(command) -> CommandGraph` is a parser; that is all
the model and the nodes rely on, so a spaCy or Stanza parser can be plugged in through
`gscan_ros.language.register_parser` (for dependency output, `graph_from_dependencies`
does the conversion, dummy root included).
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from functools import lru_cache
from typing import ClassVar, Protocol, Sequence, runtime_checkable

from gscan_ros.errors import CommandError
from gscan_ros.language.canonical import canonicalize
from gscan_ros.language.graph import CommandGraph, GraphEdge, GraphNode
from gscan_ros.language.lexicon import Lexicon


@runtime_checkable
class Parser(Protocol):
    """A command parser: raises CommandError for input it cannot parse."""

    name: str

    def parse(self, command: str) -> CommandGraph: ...


class GrammarParser(ABC):
    """A built-in parser: canonicalize, then build the graph of the canonical tokens (cached).

    Canonicalization (`canonical.canonicalize`: determiners, WordNet synonyms, adjective
    order) comes first, so a paraphrase gets exactly its canonical command's graph, with
    the typed text kept in `graph.typed`. Parsing is a pure function of the tokens and
    the lexicon, so its outcome is memoized per parser instance on the canonical token
    tuple in one bounded LRU: the graph (immutable), or the message of the CommandError,
    so a repeated ungrammatical command costs no parse either.
    """

    name: ClassVar[str]

    def __init__(self, lexicon: Lexicon | None = None, cache_size: int = 2048) -> None:
        self.lexicon = lexicon if lexicon is not None else Lexicon.none()
        self._cached_outcome = lru_cache(maxsize=cache_size)(self._graph_or_error)

    def parse(self, command: str) -> CommandGraph:
        canonical = canonicalize(command)
        outcome = self._cached_outcome(canonical.tokens)
        if isinstance(outcome, str):
            raise CommandError(outcome)
        return outcome.with_typed(canonical.typed)

    def _graph_or_error(self, tokens: tuple[str, ...]) -> CommandGraph | str:
        try:
            return self._graph(tokens)
        except CommandError as error:
            return str(error)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(lexicon={self.lexicon!r})"

    @abstractmethod
    def _graph(self, tokens: tuple[str, ...]) -> CommandGraph:
        """The graph of a tokenized command; CommandError if it is not in the grammar."""


class GraphAssembler:
    """Collects nodes and edges; a node's arity is its number of children (slots in order)."""

    def __init__(self) -> None:
        self._nodes: dict[int, GraphNode] = {}
        self._edges: list[GraphEdge] = []
        self._next = 0

    def reserve(self) -> int:
        """A fresh node id (reserve parents before children for root-first numbering)."""
        self._next += 1
        return self._next - 1

    def add(self, node_id: int, word: str, module: str, children: Sequence[tuple[str, int]] = (), head: int = 0) -> int:
        """Add node `node_id`; `children` are (arc label, child id) in slot order."""
        self._nodes[node_id] = GraphNode(node_id, word, module, len(children), head)
        self._edges += [GraphEdge(node_id, child, label, slot) for slot, (label, child) in enumerate(children)]
        return node_id

    def build(self, command: str, parser: str, root: int) -> CommandGraph:
        nodes = [self._nodes[i] for i in sorted(self._nodes)]
        edges = sorted(self._edges, key=lambda e: (e.parent, e.slot))
        return CommandGraph.build(command, parser, nodes, edges, root)
