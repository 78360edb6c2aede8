"""gSCAN `dataset.txt`: header, examples, a streaming reader and a writer.

The format is what LauraRuis/groundedSCAN's `dataset.py` (`save_dataset`) writes.

The released compositional file is ~2 GB of ONE JSON object, so the reader never
loads it whole: `_JsonStream` walks the two outer levels (top-level keys, then
`examples` -> split -> list) itself and hands each example to the C decoder
(`json.JSONDecoder.raw_decode`) on a sliding 1 MiB text buffer. Memory stays at one
buffer plus one example whatever the file size.

The original writer puts `examples` before the vocabulary keys; ours writes every
header key first and one example per line, which any JSON reader accepts and keeps
`read_header` instant. Malformed input raises `DatasetFormatError` naming the
example and field, e.g. ``example 17 of split 'train': field
'situation.agent_position.row': expected an integer string, got 'x'``.
"""
from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Iterable, Iterator, Mapping

from gscan_ros.data.commands import grammar_string
from gscan_ros.data.episode import Episode
from gscan_ros.errors import DatasetFormatError, GscanError, InvalidActionError, SituationError, quoted
from gscan_ros.world.types import (
    ADVERBS,
    COLOR_ADJECTIVES,
    GRID_SIZE,
    INTRANSITIVE_VERBS,
    NOUNS,
    SIZE_ADJECTIVES,
    SIZES,
    TRANSITIVE_VERBS,
    Action,
    Situation,
)

DATASET_FILE = "dataset.txt"
VOCABULARY_KEYS = (
    "intransitive_verbs", "transitive_verbs", "nouns", "adverbs", "color_adjectives", "size_adjectives",
)
# (key, type) of the scalar header keys, in the released order.
_HEADER_SCALARS = (
    ("grid_size", int), ("type_grammar", str), ("grammar", str), ("min_object_size", int),
    ("max_object_size", int), ("max_recursion", int), ("percentage_train", (int, float)),
)
_HEADER_KEYS = ("grid_size", "type_grammar", *VOCABULARY_KEYS)  # required; read_header stops once seen
_OPTIONAL_TEXT_FIELDS = ("meaning", "derivation", "verb_in_command", "manner", "referred_target")


def _identity_vocabulary(words: Iterable[str]) -> dict[str, str]:
    """{word: semantic word}; the default gSCAN vocabulary maps every word to itself."""
    return {w: w for w in words}


@dataclass
class DatasetHeader:
    """Everything in dataset.txt except `examples`; unknown keys survive in `extra`."""

    grid_size: int = GRID_SIZE
    type_grammar: str = "adverb"
    grammar: str = field(default_factory=grammar_string)
    min_object_size: int = SIZES[0]
    max_object_size: int = SIZES[-1]
    max_recursion: int = 1
    percentage_train: float = 0.9
    vocabulary: dict[str, dict[str, str]] = field(default_factory=lambda: {
        "intransitive_verbs": _identity_vocabulary(INTRANSITIVE_VERBS),
        "transitive_verbs": _identity_vocabulary(TRANSITIVE_VERBS),
        "nouns": _identity_vocabulary(NOUNS),
        "adverbs": _identity_vocabulary(ADVERBS),
        "color_adjectives": _identity_vocabulary(COLOR_ADJECTIVES),
        "size_adjectives": _identity_vocabulary(SIZE_ADJECTIVES),
    })
    extra: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict:
        out = {key: getattr(self, key) for key, _ in _HEADER_SCALARS}
        out.update(self.vocabulary)
        out.update(self.extra)
        return out

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> "DatasetHeader":
        """Parse the header keys; raises DatasetFormatError naming a bad or missing key."""
        header = cls(vocabulary={}, extra={})
        for key, kind in _HEADER_SCALARS:
            if key not in d:
                if key in _HEADER_KEYS:
                    raise DatasetFormatError(f"header: missing key {key!r}")
                continue  # optional in old files; keep the default
            value = d[key]
            if isinstance(value, bool) or not isinstance(value, kind):
                raise DatasetFormatError(f"header: key {key!r}: unexpected value {quoted(value)}")
            setattr(header, key, value)
        for key in VOCABULARY_KEYS:
            value = d.get(key, {})
            if not isinstance(value, dict):
                raise DatasetFormatError(f"header: key {key!r}: expected an object, got {type(value).__name__}")
            header.vocabulary[key] = value
        header.extra = {k: v for k, v in d.items()
                        if k not in dict(_HEADER_SCALARS) and k not in VOCABULARY_KEYS and k != "examples"}
        return header


@dataclass(frozen=True)
class Example:
    """One dataset example: command tokens, initial situation, gold actions, metadata."""

    tokens: tuple[str, ...]  # gSCAN tokens, "while spinning" is one token
    situation: Situation
    target_commands: tuple[Action, ...]
    meaning: str | None = None  # comma-joined semantic words (= command for the default vocabulary)
    derivation: str | None = None
    verb_in_command: str | None = None
    manner: str | None = None
    referred_target: str | None = None

    @property
    def command(self) -> str:
        """Space-joined command, e.g. "walk to a red small circle while spinning"."""
        return " ".join(self.tokens)

    def to_json(self) -> dict:
        out = {"command": ",".join(self.tokens)}
        if self.meaning is not None:
            out["meaning"] = self.meaning
        if self.derivation is not None:
            out["derivation"] = self.derivation
        out["situation"] = self.situation.to_json()
        out["target_commands"] = ",".join(a.token for a in self.target_commands)
        for key in ("verb_in_command", "manner", "referred_target"):
            if getattr(self, key) is not None:
                out[key] = getattr(self, key)
        return out

    @classmethod
    def from_json(cls, d: Any) -> "Example":
        """Parse one example dict; raises DatasetFormatError("field '...': ...")."""
        if not isinstance(d, dict):
            raise DatasetFormatError(f"expected an object, got {type(d).__name__}")
        command = _required_text(d, "command")
        tokens = tuple(command.split(","))
        # One word per token; a two-word adverb ("while spinning") is the one token with a space.
        if not command or any(not t or t != t.strip() or (" " in t and t not in ADVERBS) for t in tokens):
            raise DatasetFormatError(f"field 'command': expected comma-joined tokens, got {quoted(command)}")
        try:
            situation = Situation.from_json(_required(d, "situation"))
        except SituationError as exc:
            raise DatasetFormatError(_field_message(str(exc))) from None
        target = _required_text(d, "target_commands")
        try:
            actions = tuple(Action.from_token(t) for t in target.split(",")) if target else ()
        except InvalidActionError as exc:
            raise DatasetFormatError(f"field 'target_commands': {exc}") from None
        if Action.EOS in actions:
            raise DatasetFormatError("field 'target_commands': '<eos>' is not a gSCAN action")
        optional = {}
        for key in _OPTIONAL_TEXT_FIELDS:
            value = d.get(key)
            if value is not None and not isinstance(value, str):
                raise DatasetFormatError(f"field {key!r}: expected a string, got {type(value).__name__}")
            optional[key] = value
        return cls(tokens=tokens, situation=situation, target_commands=actions, **optional)

    def to_episode(self, split: str = "train", example_id: int | None = None) -> Episode:
        meta = {k: getattr(self, k) for k in ("derivation", "verb_in_command", "manner", "referred_target")
                if getattr(self, k) is not None}
        return Episode(command=self.command, situation=self.situation, actions=self.target_commands,
                       split=split, example_id=example_id, meta=meta)


def _required(d: dict, key: str) -> Any:
    if key not in d:
        raise DatasetFormatError(f"field {key!r}: missing")
    return d[key]


def _required_text(d: dict, key: str) -> str:
    value = _required(d, key)
    if not isinstance(value, str):
        raise DatasetFormatError(f"field {key!r}: expected a string, got {type(value).__name__}")
    return value


def _field_message(situation_error: str) -> str:
    """"situation.x.y: problem" (world's SituationError) -> "field 'situation.x.y': problem"."""
    path, sep, problem = situation_error.partition(": ")
    if sep and path.startswith("situation") and " " not in path:
        return f"field {path!r}: {problem}"
    return f"field 'situation': {situation_error}"


# ---------------------------------------------------------------------------------------
# Streaming reader
# ---------------------------------------------------------------------------------------
_WHITESPACE = re.compile(r"[ \t\n\r]*")
_CHUNK_CHARS = 1 << 20
_MAX_VALUE_CHARS = 1 << 28  # one example (or header value) larger than this is not gSCAN


class _JsonStream:
    """Incremental reader of the dataset.txt layout over a text file.

    `raw_decode` on a buffer that ends mid-value fails near the buffer's end, or
    succeeds on the head of a cut number ("0" of "0.95"); both cases refill and
    retry. A failure well inside the buffer is a real syntax error.
    """

    def __init__(self, f: IO[str]):
        self._f = f
        self._buf = ""
        self._pos = 0
        self._consumed = 0  # characters dropped from the front of the buffer
        self._eof = False
        self._decoder = json.JSONDecoder()

    @property
    def offset(self) -> int:
        return self._consumed + self._pos

    def _fill(self) -> bool:
        if self._eof:
            return False
        data = self._f.read(_CHUNK_CHARS)
        if not data:
            self._eof = True
            return False
        self._consumed += self._pos
        self._buf = self._buf[self._pos:] + data
        self._pos = 0
        return True

    def peek(self) -> str:
        """Next non-whitespace character ("" at end of file), not consumed."""
        while True:
            self._pos = _WHITESPACE.match(self._buf, self._pos).end()
            if self._pos < len(self._buf):
                return self._buf[self._pos]
            if not self._fill():
                return ""

    def expect(self, allowed: str, what: str) -> str:
        char = self.peek()
        if not char or char not in allowed:
            found = repr(char) if char else "end of file"
            raise DatasetFormatError(f"invalid JSON at character {self.offset}: expected {what}, found {found}")
        self._pos += 1
        return char

    def value(self) -> Any:
        """Decode the next complete JSON value."""
        self.peek()
        while True:
            try:
                obj, end = self._decoder.raw_decode(self._buf, self._pos)
            except json.JSONDecodeError as exc:
                near_end = exc.pos >= len(self._buf) - 1024 or exc.msg.startswith("Unterminated")
                if near_end and self._grow():
                    continue
                raise DatasetFormatError(
                    f"invalid JSON at character {self._consumed + exc.pos}: {exc.msg}") from None
            cut_number = isinstance(obj, (int, float)) and len(self._buf) - end < 64  # "0" of "0.95"
            if (end == len(self._buf) or cut_number) and self._grow():
                continue
            self._pos = end
            return obj

    def _grow(self) -> bool:
        if len(self._buf) - self._pos > _MAX_VALUE_CHARS:
            raise DatasetFormatError(f"value at character {self.offset} is larger than {_MAX_VALUE_CHARS} characters")
        return self._fill()

    def key(self) -> str:
        key = self.value()
        if not isinstance(key, str):
            raise DatasetFormatError(f"invalid JSON at character {self.offset}: expected an object key")
        self.expect(":", "':'")
        return key


def dataset_file(path: str | os.PathLike) -> Path:
    """The dataset.txt at `path` (the file, or the folder holding it); DatasetFormatError if none."""
    path = Path(path)
    if path.is_dir():
        path = path / DATASET_FILE
    if not path.is_file():
        raise DatasetFormatError(f"no dataset file at {path}")
    return path


def split_sizes(header: Mapping[str, Any]) -> dict[str, int] | None:
    """The examples per split a dataset.txt header declares (`gscan_ros.split_sizes`, written
    by `generate` and `augment` before the examples), or None (the original generator's
    files, and ours before 2026-12-07, declare none)."""
    record = header.get("gscan_ros")
    sizes = record.get("split_sizes") if isinstance(record, dict) else None
    if not isinstance(sizes, dict) or not all(isinstance(n, int) for n in sizes.values()):
        return None
    return sizes


def _walk(path: Path, header: dict, wanted: frozenset[str] | None, header_only: bool = False,
          sizes: dict[str, int] | None = None) -> Iterator[tuple[str, int, Any]]:
    """Yield (split, index, raw example) of wanted splits; fill `header` on the way, and
    `sizes` (examples per split, wanted or not) when given.

    With `header_only`, stop at `examples` when the header is already complete.
    """
    with open(path, encoding="utf-8") as f:
        stream = _JsonStream(f)
        try:
            stream.expect("{", "'{' (dataset.txt is one JSON object)")
            if stream.peek() == "}":
                stream.expect("}", "'}'")
            else:
                while True:
                    key = stream.key()
                    if key == "examples":
                        if header_only and all(k in header for k in _HEADER_KEYS):
                            return  # our own layout: everything needed came first
                        declared = split_sizes(header)
                        if wanted and declared is not None:  # refused now, not after streaming the file
                            from gscan_ros.data.splits import require_splits

                            require_splits(sorted(wanted), declared, path)
                        yield from _walk_examples(stream, wanted, {} if sizes is None else sizes)
                    else:
                        header[key] = stream.value()
                    if stream.expect(",}", "',' or '}'") == "}":
                        break
            if stream.peek():
                raise DatasetFormatError(f"invalid JSON at character {stream.offset}: data after the top-level object")
        except UnicodeDecodeError as exc:
            raise DatasetFormatError(f"{path}: not UTF-8 text ({exc.reason})") from None
        except DatasetFormatError as exc:  # named by the file, as a run reads several
            if str(exc).startswith(str(path)):
                raise
            raise DatasetFormatError(f"{path}: {exc}") from None


def _walk_examples(stream: _JsonStream, wanted: frozenset[str] | None,
                   sizes: dict[str, int]) -> Iterator[tuple[str, int, Any]]:
    stream.expect("{", "'{' after \"examples\"")
    if stream.peek() == "}":
        stream.expect("}", "'}'")
        return
    while True:
        split = stream.key()
        stream.expect("[", f"'[' starting split {split!r}")
        index = 0
        if stream.peek() == "]":
            stream.expect("]", "']'")
        else:
            while True:
                try:
                    raw = stream.value()
                except DatasetFormatError as exc:
                    raise DatasetFormatError(f"example {index} of split {split!r}: {exc}") from None
                if wanted is None or split in wanted:
                    yield split, index, raw
                index += 1
                if stream.expect(",]", f"',' or ']' in split {split!r}") == "]":
                    break
        sizes[split] = index
        if stream.expect(",}", "',' or '}' after a split") == "}":
            return


_DATASET_START = re.compile(rb'\s*\{\s*"grid_size"\s*:\s*\d')
_DATASET_START_BYTES = 4096


def is_dataset_file(path: str | os.PathLike) -> bool:
    """Whether the file at `path` begins as every dataset.txt does, ours and the released
    ones (`{"grid_size": <int>`): its first bytes tell a dataset from a user's file of that
    name without reading the rest (GBs for a full set)."""
    try:
        with open(path, "rb") as f:
            return bool(_DATASET_START.match(f.read(_DATASET_START_BYTES)))
    except OSError:
        return False


def read_header(path: str | os.PathLike) -> DatasetHeader:
    """The header of a dataset.txt (or of DIR/dataset.txt) without loading the examples.

    Files written by gscan_ros have the header first and return at once; the original
    writer puts vocabulary keys after the examples, which are then skipped over.
    """
    header: dict = {}
    for _ in _walk(dataset_file(path), header, wanted=frozenset(), header_only=True):
        pass
    return DatasetHeader.from_json(header)


def iter_raw_examples(path: str | os.PathLike, splits: Iterable[str] | None = None, *,
                      sizes: dict[str, int] | None = None) -> Iterator[tuple[str, int, dict]]:
    """(split, index, example dict) in file order, streaming; `splits` filters. `sizes`, when
    given, gets every split's example count in file order (empty splits included)."""
    from gscan_ros.data.splits import require_splits

    wanted = None if splits is None else frozenset(splits)
    sizes = {} if sizes is None else sizes
    file = dataset_file(path)
    yield from _walk(file, {}, wanted, sizes=sizes)
    if wanted is not None:
        require_splits(sorted(wanted), sizes, file)


def iter_examples(path: str | os.PathLike, splits: Iterable[str] | None = None) -> Iterator[tuple[str, int, Example]]:
    """(split, index, Example) in file order, one example in memory at a time."""
    for split, index, raw in iter_raw_examples(path, splits):
        yield split, index, decode_example(split, index, raw, dataset_file(path))


def decode_example(split: str, index: int, raw: dict, path: str | os.PathLike | None = None) -> Example:
    """An example of `iter_raw_examples`; a malformed one is a DatasetFormatError naming it
    (and the file at `path`)."""
    try:
        return Example.from_json(raw)
    except GscanError as exc:
        where = f"{path}: " if path is not None else ""
        raise DatasetFormatError(f"{where}example {index} of split {split!r}: {exc}") from None


# ---------------------------------------------------------------------------------------
# Writer
# ---------------------------------------------------------------------------------------
def write_dataset_json(path: str | os.PathLike, header: DatasetHeader,
                       lines_by_split: Mapping[str, Iterable[str]]) -> Path:
    """Write dataset.txt from pre-serialised example JSON texts (one per line).

    Header keys first, then `examples` with one split after the other; the result is
    one JSON object like the released files. Returns the file path. A header that declares
    its split sizes (`split_sizes`) must declare those written (else a GscanError, and the
    file is not replaced): readers trust them.
    """
    from gscan_ros.outputs import replacing

    path = Path(path)
    if path.is_dir():
        path = path / DATASET_FILE
    fields = header.to_json()
    declared, written = split_sizes(fields), {}
    with replacing(path) as tmp, open(tmp, "w", encoding="utf-8") as out:
        out.write("{\n")
        for key, value in fields.items():
            out.write(f"{json.dumps(key)}: {json.dumps(value)},\n")
        out.write('"examples": {')
        for s, (split, lines) in enumerate(lines_by_split.items()):
            out.write(f'{"," if s else ""}\n{json.dumps(split)}: [')
            written[split] = 0
            for i, line in enumerate(lines):
                out.write(",\n" if i else "\n")
                out.write(line)
                written[split] = i + 1
            out.write("\n]")
        out.write("\n}\n}\n")
        if declared is not None and declared != written:
            raise GscanError(f"{path}: the header declares split sizes {declared}, the examples are {written}")
    return path


def example_line(example: Example) -> str:
    """The compact one-line JSON text of an example, as `write_dataset` writes it."""
    return json.dumps(example.to_json(), separators=(",", ":"))


def write_dataset(path: str | os.PathLike, header: DatasetHeader,
                  examples_by_split: Mapping[str, Iterable[Example]]) -> Path:
    """Write `examples_by_split` (split -> Examples, iterated once) as dataset.txt."""
    return write_dataset_json(path, header, {
        split: (example_line(e) for e in examples) for split, examples in examples_by_split.items()
    })
