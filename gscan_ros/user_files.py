"""Bounded readers of user files (docs/reliability.md, "Bounded memory").

A file a user hands over (a training config, an experiment plan, a bag's
`metadata.yaml`, a run's results.json) is measured before it is read, and a YAML
document before it is built, so a huge or hostile file costs one `GscanError` line
naming the file and the bound, never gigabytes. Checkpoints have their own check of
the zip, in `gscan_ros.model.checkpoint`.
"""
from __future__ import annotations

import hashlib
import json
import os

import yaml

from gscan_ros.errors import QUOTE_CHARS, GscanError, shortened

MAX_YAML_BYTES = 256 << 10
"""Largest YAML file, and largest YAML document once its aliases are written out, unless
a reader names its own bound: configs are a few kB, the paper's plan 12 kB (bag metadata,
which grows with topics and split files, has `bag_metadata.MAX_METADATA_BYTES`)."""
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
            # In pieces: also bounds what has no size (a pipe, /dev/zero), and a large bound
            # costs no buffer of its size for a small file.
            chunks, size = [], 0
            while size <= limit and (chunk := f.read(1 << 16)):
                chunks.append(chunk)
                size += len(chunk)
    except OSError as exc:
        raise error(f"cannot read {what}: {exc.strerror}") from None
    if size > limit:
        raise error(f"{what} is larger than {limit:,} bytes")
    data = b"".join(chunks)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise error(f"{what} is not UTF-8 text (byte {exc.start})") from None


def read_yaml(path: str | os.PathLike, what: str, error: type[GscanError], limit: int = MAX_YAML_BYTES):
    """The YAML document in `path`, within `limit` bytes and MAX_YAML_DEPTH; `error` with
    one line naming `what` when the file cannot be read, is not UTF-8 or not YAML, or
    goes beyond a bound."""
    return parse_yaml(read_text(path, what, error, limit), what, error, limit)


def read_json(path: str | os.PathLike, what: str, error: type[GscanError]):
    """The JSON document in `path`, within MAX_JSON_BYTES; `error` naming `what` otherwise."""
    text = read_text(path, what, error, MAX_JSON_BYTES)
    try:
        return json.loads(text)
    except ValueError as exc:  # JSONDecodeError, or an integer beyond Python's digit limit
        raise error(f"{what} is not valid JSON: {exc}") from None
    except RecursionError:
        raise error(f"{what} is not valid JSON: nested too deeply") from None


def file_sha256(path: str | os.PathLike) -> str:
    """The SHA-256 of a file's bytes, read in chunks: names the exact weights an
    evaluation scored (a path says nothing once the file is replaced)."""
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def parse_yaml(text: str, what: str, error: type[GscanError], limit: int = MAX_YAML_BYTES):
    """The YAML document `text` (a file's, or one `--set` value), bounded as `read_yaml`'s:
    measured event by event (`_check_bounds`) before anything is built, then loaded as
    plain data (a SafeLoader, libyaml's when installed: bag metadata runs to MiBs)."""
    try:
        _check_bounds(text, limit)
        return yaml.load(text, Loader=_LOADER)
    except _Unbounded as exc:
        raise error(f"{what} {exc}") from None
    except yaml.YAMLError as exc:
        reason = " ".join(str(exc).split())  # PyYAML quotes undefined aliases and tags whole
        raise error(f"{what} is not valid YAML: {shortened(reason, 4 * QUOTE_CHARS)}") from None
    except ValueError as exc:  # an integer beyond Python's digit limit
        raise error(f"{what} holds an unreadable value: {exc}") from None


class _Loader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):
    """The SafeLoader (libyaml's when installed), refusing a mapping that repeats a key,
    which PyYAML would settle silently for the last one (`batch_size` set twice)."""

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key, _ in node.value:
            if isinstance(key, yaml.ScalarNode) and key.tag != "tag:yaml.org,2002:merge":
                if key.value in seen:
                    raise yaml.constructor.ConstructorError(None, None, f"key {key.value!r} appears twice",
                                                            key.start_mark)
                seen.add(key.value)
        return super().construct_mapping(node, deep)


_LOADER = _Loader


class _Unbounded(Exception):
    """A YAML document beyond MAX_YAML_DEPTH or its size bound (its message completes
    "<what> ...")."""


def _check_bounds(text: str, limit: int) -> None:
    """Refuse a document that nests deeper than MAX_YAML_DEPTH or, with every alias
    written out, exceeds `limit` characters (`_Unbounded`), from its parse events alone.

    An alias makes a node stand for the whole node it refers to, so a 300-byte document
    ("billion laughs") can stand for gigabytes, which any consumer that walks it (an
    error message, `json.dumps`, `str`) then allocates. Refusing anchors outright would
    refuse their honest use (one `set:` block shared by the runs of a plan); instead the
    document, with every alias written out, must stay within `limit`, the bound of a file
    without aliases. Each anchored node's size is counted once, so measuring costs time
    linear in the file. Sizes: a scalar its text (1 when empty), a collection 1 plus its
    children's. Syntax errors are left to the loader that follows.
    """
    open_nodes: list[list] = []  # [written size so far, anchor] of each collection being read
    anchors: dict[str, int] = {}

    def close(size: int, anchor: str | None) -> None:
        if size > limit:
            raise _Unbounded(f"expands beyond {limit:,} characters through its aliases")
        if anchor is not None:
            anchors[anchor] = size
        if open_nodes:
            open_nodes[-1][0] += size

    for event in yaml.parse(text, Loader=_LOADER):
        if isinstance(event, (yaml.ScalarEvent, yaml.AliasEvent, yaml.CollectionStartEvent)) \
                and len(open_nodes) == MAX_YAML_DEPTH:
            raise _Unbounded(f"nests deeper than {MAX_YAML_DEPTH} levels")
        if isinstance(event, yaml.CollectionStartEvent):
            open_nodes.append([1, event.anchor])
        elif isinstance(event, yaml.CollectionEndEvent):
            close(*open_nodes.pop())
        elif isinstance(event, yaml.ScalarEvent):
            close(max(len(event.value), 1), event.anchor)
        elif isinstance(event, yaml.AliasEvent):
            if any(anchor == event.anchor for _, anchor in open_nodes):
                raise _Unbounded("holds an alias inside the node it refers to (an infinite document)")
            close(anchors.get(event.anchor, 1), None)  # an undefined alias: the loader says so
