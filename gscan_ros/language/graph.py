"""CommandGraph: the parse of a command as a labeled DAG, the network's wiring plan.

Every parser (semantic, constituency, dependency, or a user's own) produces one. Each
node becomes a recurrent word module keyed by `module`; a node's children feed its
attention in `slot` order, which the parser derives from the arc label (paper §3.2:
"arc labels determine the arbitrary but consistent order"). Concept groups from the
lexicon share one module; `head` picks the word's attention head inside it.

`command` is the canonical gSCAN command the graph was built for; `typed`, when the
command arrived in another form ("Push the small blue cylinder"), is that text. It is
provenance, not structure: graphs that differ only in `typed` are equal, and the JSON
carries it as an optional key (absent in older JSON).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from functools import cached_property

from gscan_ros.errors import GraphError

SCHEMA_VERSION = 1
DUMMY_ROOT_WORD = "<root>"

# Size bounds, checked before anything is allocated from a graph's sizes: a graph arrives
# from the network, and a 300-byte message with "arity": 50000000 must be a GraphError,
# not gigabytes. gSCAN's parses stay far below them (at most 7 nodes, arity 3).
MAX_GRAPH_JSON_CHARS = 128 * 1024
MAX_NODES = 64
MAX_ARITY = 8  # children (argument slots) of one node
MAX_EDGES = MAX_NODES * MAX_ARITY  # every edge fills one slot
MAX_HEADS = 64  # attention heads of one shared concept module
MAX_NAME_CHARS = 64  # word, module key, arc label, parser name
MAX_COMMAND_CHARS = 1000


@dataclass(frozen=True)
class GraphNode:
    id: int
    word: str  # surface word / phrase label, e.g. "red", "while spinning", "NP"
    module: str  # module key shared by every node using the same parameters, e.g. "NP_2"
    arity: int  # number of children (argument slots)
    head: int = 0  # attention head inside a shared concept module


@dataclass(frozen=True)
class GraphEdge:
    parent: int
    child: int
    label: str  # arc label, e.g. "arg", "obj", "amod", "advmod"
    slot: int  # argument position in the parent, 0..parent.arity-1


@dataclass(frozen=True)
class CommandGraph:
    """Immutable parse graph. Build with `CommandGraph.build(...)`, which validates."""

    command: str
    parser: str
    nodes: tuple[GraphNode, ...]
    edges: tuple[GraphEdge, ...]
    root: int
    typed: str | None = field(default=None, compare=False)  # the command as typed, if not `command`

    @classmethod
    def build(cls, command: str, parser: str, nodes, edges, root: int, typed: str | None = None) -> "CommandGraph":
        graph = cls(command, parser, tuple(nodes), tuple(edges), root, None if typed == command else typed)
        graph.validate()
        return graph

    def with_typed(self, typed: str) -> "CommandGraph":
        """This graph, remembering that its command was typed as `typed` (bounded like `command`)."""
        if typed == (self.typed or self.command):
            return self
        _check_length("typed", typed, MAX_COMMAND_CHARS)
        return replace(self, typed=None if typed == self.command else typed)

    # ----------------------------------------------------------------- structure
    def children(self, node_id: int) -> tuple[int, ...]:
        """Child ids of `node_id` in slot order."""
        return self._children[node_id]

    @cached_property
    def _children(self) -> dict[int, tuple[int, ...]]:
        by_parent: dict[int, list[GraphEdge]] = {n.id: [] for n in self.nodes}
        for e in self.edges:
            by_parent[e.parent].append(e)
        return {p: tuple(e.child for e in sorted(es, key=lambda e: e.slot)) for p, es in by_parent.items()}

    def node(self, node_id: int) -> GraphNode:
        return self._by_id[node_id]

    @cached_property
    def _by_id(self) -> dict[int, GraphNode]:
        return {n.id: n for n in self.nodes}

    def postorder(self) -> tuple[int, ...]:
        """Node ids, children before parents (each node once, even if shared)."""
        return self._postorder

    @cached_property
    def _postorder(self) -> tuple[int, ...]:
        order: list[int] = []
        seen: set[int] = set()

        def visit(n: int) -> None:
            if n in seen:
                return
            seen.add(n)
            for c in self.children(n):
                visit(c)
            order.append(n)

        visit(self.root)
        return tuple(order)

    def levels(self) -> tuple[tuple[int, ...], ...]:
        """Node ids grouped by height (leaves = level 0); a level only needs earlier ones."""
        height: dict[int, int] = {}
        for n in self.postorder():
            cs = self.children(n)
            height[n] = 1 + max(height[c] for c in cs) if cs else 0
        out: list[list[int]] = [[] for _ in range(max(height.values()) + 1)]
        for n in self.postorder():
            out[height[n]].append(n)
        return tuple(tuple(level) for level in out)

    def modules(self) -> tuple[str, ...]:
        """Module keys used by this graph, sorted."""
        return tuple(sorted({n.module for n in self.nodes}))

    # -------------------------------------------------------------- validation
    def validate(self) -> None:
        """Raise GraphError unless it is within the size bounds, ids are unique, arities match
        slots, and it is a rooted DAG."""
        self._check_bounds()
        ids = [n.id for n in self.nodes]
        if not self.nodes:
            raise GraphError("graph has no nodes")
        if len(set(ids)) != len(ids):
            raise GraphError(f"duplicate node ids in {ids}")
        known = set(ids)
        if self.root not in known:
            raise GraphError(f"root {self.root} is not a node id")
        for n in self.nodes:
            if not n.word or not n.module:
                raise GraphError(f"node {n.id} has an empty word or module key")
        slots: dict[int, list[int]] = {i: [] for i in ids}
        for e in self.edges:
            if e.parent not in known or e.child not in known:
                raise GraphError(f"edge {e.parent}->{e.child} refers to an unknown node")
            if not e.label:
                raise GraphError(f"edge {e.parent}->{e.child} has an empty arc label")
            slots[e.parent].append(e.slot)
        for n in self.nodes:
            if sorted(slots[n.id]) != list(range(n.arity)):
                raise GraphError(
                    f"node {n.id} ({n.word!r}) has arity {n.arity} but child slots {sorted(slots[n.id])}"
                )
        # Acyclic and everything reachable from the root.
        state: dict[int, int] = {}

        def dfs(n: int) -> None:
            state[n] = 1
            for c in self.children(n):
                if state.get(c) == 1:
                    raise GraphError(f"cycle through node {c}")
                if c not in state:
                    dfs(c)
            state[n] = 2

        dfs(self.root)
        unreachable = known - set(state)
        if unreachable:
            raise GraphError(f"nodes {sorted(unreachable)} are not reachable from root {self.root}")

    def _check_bounds(self) -> None:
        _check_count("nodes", len(self.nodes), MAX_NODES)
        _check_count("edges", len(self.edges), MAX_EDGES)
        _check_length("command", self.command, MAX_COMMAND_CHARS)
        if self.typed is not None:
            _check_length("typed", self.typed, MAX_COMMAND_CHARS)
        _check_length("parser", self.parser, MAX_NAME_CHARS)
        for i, n in enumerate(self.nodes):
            _check_range(f"nodes[{i}].arity", n.arity, MAX_ARITY)
            _check_range(f"nodes[{i}].head", n.head, MAX_HEADS - 1)
            _check_length(f"nodes[{i}].word", n.word, MAX_NAME_CHARS)
            _check_length(f"nodes[{i}].module", n.module, MAX_NAME_CHARS)
        for i, e in enumerate(self.edges):
            _check_range(f"edges[{i}].slot", e.slot, MAX_ARITY - 1)
            _check_length(f"edges[{i}].label", e.label, MAX_NAME_CHARS)

    # --------------------------------------------------------------- JSON wire
    def to_dict(self) -> dict:
        d = {
            "schema_version": SCHEMA_VERSION,
            "command": self.command,
            "parser": self.parser,
            "root": self.root,
            "nodes": [
                {"id": n.id, "word": n.word, "module": n.module, "arity": n.arity, "head": n.head}
                for n in self.nodes
            ],
            "edges": [
                {"parent": e.parent, "child": e.child, "label": e.label, "slot": e.slot} for e in self.edges
            ],
        }
        if self.typed is not None:
            d["typed"] = self.typed
        return d

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), separators=(",", ":"))

    @classmethod
    def from_dict(cls, d: dict) -> "CommandGraph":
        if not isinstance(d, dict):
            raise GraphError("command graph JSON must be an object")
        version = d.get("schema_version")
        if version != SCHEMA_VERSION:
            raise GraphError(f"unsupported command graph schema_version {version!r} (expected {SCHEMA_VERSION})")
        try:
            _check_count("nodes", len(_list(d, "nodes")), MAX_NODES)
            _check_count("edges", len(_list(d, "edges")), MAX_EDGES)
            nodes = [
                GraphNode(int(n["id"]), str(n["word"]), str(n["module"]), int(n["arity"]), int(n.get("head", 0)))
                for n in d["nodes"]
            ]
            edges = [GraphEdge(int(e["parent"]), int(e["child"]), str(e["label"]), int(e["slot"])) for e in d["edges"]]
            typed = d.get("typed")
            if typed is not None and not isinstance(typed, str):
                raise GraphError(f"command graph typed: expected a string, got {type(typed).__name__}")
            return cls.build(str(d["command"]), str(d["parser"]), nodes, edges, int(d["root"]), typed)
        except GraphError:
            raise
        except (KeyError, TypeError, ValueError) as exc:
            raise GraphError(f"malformed command graph JSON: {type(exc).__name__}: {exc}") from None

    @classmethod
    def from_json(cls, text: str) -> "CommandGraph":
        if isinstance(text, (str, bytes)) and len(text) > MAX_GRAPH_JSON_CHARS:
            raise GraphError(
                f"command graph JSON has {len(text)} characters, more than the maximum of {MAX_GRAPH_JSON_CHARS}"
            )
        try:
            d = json.loads(text)
        except (json.JSONDecodeError, TypeError) as exc:
            raise GraphError(f"command graph is not valid JSON: {exc}") from None
        except RecursionError:
            raise GraphError("command graph JSON is nested too deeply") from None
        return cls.from_dict(d)

    # ------------------------------------------------------------------ display
    def pretty(self) -> str:
        """Indented tree, root first (shared nodes printed under each parent)."""
        lines: list[str] = []

        def show(n: int, depth: int, label: str) -> None:
            node = self.node(n)
            extra = f" [{node.module}" + (f" head {node.head}" if node.head else "") + "]"
            lines.append("  " * depth + (f"{label}: " if label else "") + node.word + extra)
            for e in sorted((e for e in self.edges if e.parent == n), key=lambda e: e.slot):
                show(e.child, depth + 1, e.label)

        show(self.root, 0, "")
        return "\n".join(lines)


def _list(d: dict, key: str) -> list:
    value = d[key]
    if not isinstance(value, list):
        raise GraphError(f"command graph {key}: expected a list, got {type(value).__name__}")
    return value


def _check_count(field: str, count: int, limit: int) -> None:
    if count > limit:
        raise GraphError(f"command graph has {count} {field}, more than the maximum of {limit}")


def _check_range(field: str, value: int, limit: int) -> None:
    if not 0 <= value <= limit:
        raise GraphError(f"command graph {field} is {value}, outside 0..{limit}")


def _check_length(field: str, text: str, limit: int) -> None:
    if len(text) > limit:
        raise GraphError(f"command graph {field} has {len(text)} characters, more than the maximum of {limit}")
