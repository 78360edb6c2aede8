"""CommandGraph: the parse of a command as a labeled DAG, the network's wiring plan.

Every parser (semantic, constituency, dependency, or a user's own) produces one. Each
node becomes a recurrent word module keyed by `module`; a node's children feed its
attention in `slot` order, which the parser derives from the arc label (paper §3.2:
"arc labels determine the arbitrary but consistent order"). Concept groups from the
lexicon share one module; `head` picks the word's attention head inside it.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cached_property

from gscan_ros.errors import GraphError

SCHEMA_VERSION = 1
DUMMY_ROOT_WORD = "<root>"


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

    @classmethod
    def build(cls, command: str, parser: str, nodes, edges, root: int) -> "CommandGraph":
        graph = cls(command, parser, tuple(nodes), tuple(edges), root)
        graph.validate()
        return graph

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
        """Raise GraphError unless ids are unique, arities match slots, and it is a rooted DAG."""
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
            if n.arity < 0 or n.head < 0:
                raise GraphError(f"node {n.id} has a negative arity or head")
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

    # --------------------------------------------------------------- JSON wire
    def to_dict(self) -> dict:
        return {
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
            nodes = [
                GraphNode(int(n["id"]), str(n["word"]), str(n["module"]), int(n["arity"]), int(n.get("head", 0)))
                for n in d["nodes"]
            ]
            edges = [GraphEdge(int(e["parent"]), int(e["child"]), str(e["label"]), int(e["slot"])) for e in d["edges"]]
            return cls.build(str(d["command"]), str(d["parser"]), nodes, edges, int(d["root"]))
        except GraphError:
            raise
        except (KeyError, TypeError, ValueError) as exc:
            raise GraphError(f"malformed command graph JSON: {type(exc).__name__}: {exc}") from None

    @classmethod
    def from_json(cls, text: str) -> "CommandGraph":
        try:
            d = json.loads(text)
        except (json.JSONDecodeError, TypeError) as exc:
            raise GraphError(f"command graph is not valid JSON: {exc}") from None
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
