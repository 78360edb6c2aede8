"""Bounded readers of user files (docs/reliability.md, "Bounded memory").

A file a user hands over (a training config, an experiment plan, a bag's
`metadata.yaml`, a run's results.json) is measured before it is read, and a YAML
document before it is built, so a huge or hostile file costs one `GscanError` line
naming the file and the bound, never gigabytes. Checkpoints have their own check of
the zip, in `gscan_ros.model.checkpoint`.
"""
from __future__ import annotations

import json
import os

import yaml

from gscan_ros.errors import QUOTE_CHARS, GscanError, shortened

MAX_YAML_BYTES = 256 << 10
"""Largest YAML file, and largest YAML document once its aliases are written out: configs
and bag metadata are a few kB, the paper's plan 12 kB (PyYAML parses ~100 kB a second)."""
MAX_YAML_DEPTH = 32
"""Deepest nesting of a YAML document (bag metadata, the deepest we read, nests 9 levels)."""
MAX_JSON_BYTES = 16 << 20
"""Largest JSON file read whole: a run's results.json or a situation, a few kB."""


def read_text(path: str | os.PathLike, what: str, error: type[GscanError], limit: int) -> str:
    """The UTF-8 text of `path`; `error` naming `what` when it cannot be read, is not UTF-8
    or holds more than `limit` bytes (refused before it is read)."""
    try:
        with open(path, "rb") as f:
            if os.fstat(f.fileno()).st_size > limit:
                raise error(f"{what} is larger than {limit:,} bytes")
            data = f.read(limit + 1)  # also bounds what has no size (a pipe, /dev/zero)
    except OSError as exc:
        raise error(f"cannot read {what}: {exc.strerror}") from None
    if len(data) > limit:
        raise error(f"{what} is larger than {limit:,} bytes")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise error(f"{what} is not UTF-8 text (byte {exc.start})") from None


def read_yaml(path: str | os.PathLike, what: str, error: type[GscanError]):
    """The YAML document in `path`, within MAX_YAML_BYTES and MAX_YAML_DEPTH; `error` with
    one line naming `what` when the file cannot be read, is not UTF-8 or not YAML, or
    goes beyond a bound."""
    return parse_yaml(read_text(path, what, error, MAX_YAML_BYTES), what, error)


def read_json(path: str | os.PathLike, what: str, error: type[GscanError]):
    """The JSON document in `path`, within MAX_JSON_BYTES; `error` naming `what` otherwise."""
    text = read_text(path, what, error, MAX_JSON_BYTES)
    try:
        return json.loads(text)
    except ValueError as exc:  # JSONDecodeError, or an integer beyond Python's digit limit
        raise error(f"{what} is not valid JSON: {exc}") from None
    except RecursionError:
        raise error(f"{what} is not valid JSON: nested too deeply") from None


def parse_yaml(text: str, what: str, error: type[GscanError]):
    """The YAML document `text` (a file's, or one `--set` value), bounded as `read_yaml`'s."""
    try:
        return yaml.load(text, Loader=_BoundedLoader)  # a SafeLoader: plain data only
    except _Unbounded as exc:
        raise error(f"{what} {exc}") from None
    except yaml.YAMLError as exc:
        reason = " ".join(str(exc).split())  # PyYAML quotes undefined aliases and tags whole
        raise error(f"{what} is not valid YAML: {shortened(reason, 4 * QUOTE_CHARS)}") from None
    except ValueError as exc:  # an integer beyond Python's digit limit
        raise error(f"{what} holds an unreadable value: {exc}") from None


class _Unbounded(Exception):
    """A YAML document beyond MAX_YAML_DEPTH or MAX_YAML_BYTES (its message completes
    "<what> ...")."""


class _BoundedLoader(yaml.SafeLoader):
    """A SafeLoader that measures each node as it is composed, before anything is built.

    An alias makes a node stand for the whole node it refers to, so a 300-byte document
    ("billion laughs") can stand for gigabytes, which any consumer that walks it (an
    error message, `json.dumps`, `str`) then allocates. Refusing anchors outright would
    refuse their honest use (one `set:` block shared by the runs of a plan); instead the
    document, with every alias written out, must stay within MAX_YAML_BYTES, the bound
    of a file without aliases. The size of a node is counted once (composition shares
    it), so measuring costs time linear in the file.
    """

    def __init__(self, stream) -> None:
        super().__init__(stream)
        self._depth = 0
        self._sizes: dict[int, int] = {}  # id(node) -> characters with its aliases written out

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            node = super().compose_node(parent, index)
            if id(node) not in self._sizes:
                raise _Unbounded("holds an alias inside the node it refers to (an infinite document)")
            return node
        if self._depth == MAX_YAML_DEPTH:
            raise _Unbounded(f"nests deeper than {MAX_YAML_DEPTH} levels")
        self._depth += 1
        node = super().compose_node(parent, index)
        self._depth -= 1
        size = self._sizes[id(node)] = _written_size(node, self._sizes)
        if size > MAX_YAML_BYTES:
            raise _Unbounded(f"expands beyond {MAX_YAML_BYTES:,} characters through its aliases")
        return node


def _written_size(node: yaml.Node, sizes: dict[int, int]) -> int:
    """Characters of `node` written out, at most its length in a file without aliases:
    a scalar its text (1 when empty), a collection 1 plus its children's (known already)."""
    if isinstance(node, yaml.ScalarNode):
        return max(len(node.value), 1)
    children = node.value if isinstance(node, yaml.SequenceNode) else [n for pair in node.value for n in pair]
    return 1 + sum(sizes[id(child)] for child in children)
