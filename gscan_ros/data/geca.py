"""GECA data augmentation of a gSCAN train split (`gscan-ros augment --method geca`, docs/data.md "GECA").

GECA, "good-enough compositional data augmentation" (Andreas, ACL 2020; jacobandreas/geca
`data/builder.py` and `compose.py` with the retrieval model), works on token sequences:
a *fragment* is a token, a *template* a sequence with up to two fragments replaced by
placeholders (every occurrence of each); fragments that fill a common template are
substitutable, and another template of one filled with the other is a proposal. Ruis et
al. (2020) trained their seq2seq baseline on a train split GECA had augmented by 10,000
examples (their training log loads 377,933 = 367,933 + 10,000).

The sequence is the command, a separator and the actions, in one vocabulary ("walk",
"push" and "pull" are one token on both sides), with GECA's SCAN settings: one-token
fragments, two per template, two substitutes tried per template. Where gSCAN is not SCAN
(docs/data.md gives the reasons and the measurements):

- a proposal must be a new (command, actions) pair, and a placeholder on one side of
  the separator suffices (GECA wants one on each);
- it is grounded, since GECA makes no situation: the route its actions walk places agent
  and target (at the agent cell of the template's example when the route fits from
  there), the target is what the command describes, the distractors are drawn as the
  generator draws them, and the planner must give exactly the proposal's actions;
- a proposal of a kind one of the dataset's hold-out splits claims (a red square target,
  a "pull ... while spinning", ...) is not added, unless asked for.

Dropped proposals are counted by reason. Templates are grouped by a 64-bit BLAKE2 key of
their bytes, so the ~4 million (pair, filler) entries of a full train split are ~50 MB of
arrays (a full run peaks near 300 MB); one generator seeded by `--seed` orders the
templates and draws the substitutes and situations, so the output is a function of the
input and the seed.
"""
from __future__ import annotations

import hashlib
import json
import os
import time
from array import array
from collections import Counter
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Iterator, NamedTuple

import numpy as np

from gscan_ros.data.commands import Command, parse_command
from gscan_ros.data.dataset import DATASET_FILE, DatasetHeader, Example, example_line, read_header, write_dataset_json
from gscan_ros.data.io import select_bags
from gscan_ros.data.sampling import ObjectSpec, Placement, agent_cells, possible_targets, sample_situations
from gscan_ros.data.splits import HOLD_OUT_RULES, held_out_splits
from gscan_ros.errors import CommandError, DatasetFormatError, GscanError, InvalidActionError
from gscan_ros.world import Action, demonstrate
from gscan_ros.world.command import split_command
from gscan_ros.world.planner import resolve_target
from gscan_ros.world.types import (
    Heading,
    Position,
    Situation,
    WorldObject,
    direction_between,
    manhattan,
)

AUGMENT_METHODS = ("geca",)
"""The methods of `gscan-ros augment` (its `--method`; an experiment plan's dataset `augment`)."""
TRAIN = "train"
LENGTH_SPLIT = "target_lengths"
RELEASED_ADDED_EXAMPLES = 10_000
"""Examples Ruis et al. added: their GECA training log loads 377,933, the base split has 367,933."""
HOLD_OUT_SPLITS = frozenset([*(rule.split for rule in HOLD_OUT_RULES), LENGTH_SPLIT])
"""Splits of examples the train split is built without (compositional B-H, length I)."""
VARIANTS = 2
"""Substitutes tried per template (GECA's `variants` flag)."""

_SEPARATOR = 253
_PLACEHOLDERS = (254, 255)  # a template's first and second placeholder
_MAX_TOKENS = _SEPARATOR  # token codes 0..252


class _Origin(NamedTuple):
    """The layout of a pair's first train example: agent cell, target object, grid size."""

    agent: Position
    target: WorldObject
    grid_size: int


@dataclass
class GecaReport:
    """What `augment` did: the examples added, the proposals dropped (by reason), the work."""

    added: list[Example]
    requested: int
    seed: int
    held_out: list[str]  # the dataset's hold-out splits
    keep_held_out: list[str] = field(default_factory=list)  # those whose kinds' proposals are added
    train_examples: int = 0
    grid_size: int = 0  # of the train situations
    train_pairs: int = 0  # distinct (command, actions) pairs of the train split
    templates: int = 0
    templates_tried: int = 0
    dropped: Counter = field(default_factory=Counter)
    held_out_kinds: Counter = field(default_factory=Counter)  # grounded proposals, by hold-out split claiming them
    seconds: float = 0.0

    def record(self) -> dict:
        """The summary the output's header keeps (`gscan_ros.augmentation`)."""
        return {
            "method": "geca", "seed": self.seed, "requested": self.requested, "added": len(self.added),
            "held_out": self.held_out, "keep_held_out": self.keep_held_out,
            "train_pairs": self.train_pairs, "templates": self.templates, "templates_tried": self.templates_tried,
            "dropped": dict(sorted(self.dropped.items())), "held_out_kinds": dict(sorted(self.held_out_kinds.items())),
        }


class _Corpus:
    """The distinct (command, actions) pairs of a train split as byte strings (one code per
    token, the separator between command and actions), and one origin per pair."""

    def __init__(self) -> None:
        self.codes: dict[str, int] = {}
        self.words: list[str] = []
        self.index: dict[bytes, int] = {}
        self.sequences: list[bytes] = []
        self.origins: list[_Origin] = []
        self.examples = 0
        self.longest = 0  # actions of the longest target

    @classmethod
    def of(cls, train: Iterable[Example]) -> "_Corpus":
        corpus = cls()
        for example in train:
            corpus.add(example)
        if not corpus.sequences:
            raise DatasetFormatError(f"the dataset has no {TRAIN} examples to augment")
        return corpus

    def add(self, example: Example) -> None:
        self.examples += 1
        self.longest = max(self.longest, len(example.target_commands))
        sequence = self._encode(example.tokens) + bytes([_SEPARATOR]) + self._encode(
            [a.token for a in example.target_commands])
        if sequence in self.index:
            return
        self.index[sequence] = len(self.sequences)
        self.sequences.append(sequence)
        situation = example.situation
        target = situation.target_object or resolve_target(situation, example.tokens)
        self.origins.append(_Origin(situation.agent_position, target, situation.grid_size))

    def _encode(self, tokens) -> bytes:
        out = bytearray()
        for token in tokens:
            code = self.codes.get(token)
            if code is None:
                if len(self.words) == _MAX_TOKENS:
                    raise DatasetFormatError(f"the train split has more than {_MAX_TOKENS} distinct tokens; "
                                             "GECA here is for gSCAN's vocabulary")
                code = self.codes[token] = len(self.words)
                self.words.append(token)
            out.append(code)
        return bytes(out)

    def decode(self, sequence: bytes) -> tuple[list[str], list[str]]:
        cut = sequence.index(_SEPARATOR)
        return [self.words[c] for c in sequence[:cut]], [self.words[c] for c in sequence[cut + 1:]]


def _fillers(sequence: bytes) -> Iterator[bytes]:
    """The fillers GECA's one-token fragments give a sequence: every token, and every
    ordered pair of tokens (a, b) with an occurrence of b after one of a (b takes the
    second placeholder)."""
    cut = sequence.index(_SEPARATOR)
    first: dict[int, int] = {}
    last: dict[int, int] = {}
    for position, code in enumerate(sequence):
        if position != cut:
            first.setdefault(code, position)
            last[code] = position
    tokens = sorted(first, key=first.__getitem__)
    for a in tokens:
        yield bytes([a])
    for a in tokens:
        for b in tokens:
            if a != b and last[b] > first[a]:
                yield bytes([a, b])


@dataclass
class _Templates:
    """Every (pair, filler) entry grouped by template: entries sorted by template key,
    `starts[g]:starts[g + 1]` the entries of template g (distinct fillers, since the pairs are)."""

    pairs: np.ndarray  # int32 per entry
    fillers: np.ndarray  # int32 per entry, into `filler_bytes`
    starts: np.ndarray  # int64, one per template plus the end
    filler_bytes: list[bytes]

    @classmethod
    def build(cls, corpus: _Corpus) -> "_Templates":
        filler_ids: dict[bytes, int] = {}
        tables: list[bytes] = []
        keys, pairs, fillers = array("Q"), array("i"), array("i")
        for pair, sequence in enumerate(corpus.sequences):
            for filler in _fillers(sequence):
                fid = filler_ids.get(filler)
                if fid is None:
                    fid = filler_ids[filler] = len(tables)
                    tables.append(bytes.maketrans(filler, bytes(_PLACEHOLDERS[:len(filler)])))
                digest = hashlib.blake2b(sequence.translate(tables[fid]), digest_size=8).digest()
                keys.append(int.from_bytes(digest, "little"))
                pairs.append(pair)
                fillers.append(fid)
        keys_np = np.frombuffer(keys, dtype=np.uint64)
        order = np.argsort(keys_np, kind="stable")
        sorted_keys = keys_np[order]
        starts = np.flatnonzero(np.r_[True, sorted_keys[1:] != sorted_keys[:-1]])
        return cls(
            pairs=np.frombuffer(pairs, dtype=np.int32)[order],
            fillers=np.frombuffer(fillers, dtype=np.int32)[order],
            starts=np.r_[starts, len(order)],
            filler_bytes=list(filler_ids),
        )

    def __len__(self) -> int:
        return len(self.starts) - 1

    def group(self, template: int) -> slice:
        return slice(int(self.starts[template]), int(self.starts[template + 1]))

    def substitutes(self) -> list[frozenset[int]]:
        """Per filler, the fillers it shares a template with (GECA: substitutable fragments)."""
        out: list[set[int]] = [set() for _ in self.filler_bytes]
        sizes = np.diff(self.starts)
        for start, size in zip(self.starts[:-1][sizes > 1].tolist(), sizes[sizes > 1].tolist()):
            group = self.fillers[start:start + size].tolist()
            for filler in group:
                out[filler].update(group)
        return [frozenset(s - {f}) for f, s in enumerate(out)]


def augment(train: Iterable[Example], examples: int = RELEASED_ADDED_EXAMPLES, seed: int = 0,
            held_out: Iterable[str] = (), keep_held_out: bool | Iterable[str] = False) -> GecaReport:
    """Up to `examples` new train examples by GECA, each in a situation where the planner
    gives exactly its actions; fewer when the templates run out (the report says).

    `held_out` names the dataset's hold-out splits (`splits.HOLD_OUT_RULES`, and
    `target_lengths`: longer than any train target); a proposal of a kind one of them
    claims is dropped, unless `keep_held_out` keeps every split that claims it (True: all).
    """
    held_out = frozenset(held_out)
    return _generate(_Corpus.of(train), examples, seed, held_out, kept_splits(keep_held_out, held_out))


def kept_splits(keep_held_out: bool | Iterable[str], held_out: frozenset[str],
                of: str = "the dataset", setting: str = "--keep-held-out") -> frozenset[str]:
    """The hold-out splits whose kinds are added: all of `held_out` (those `of`) for True,
    none for False, else the named ones; GscanError, naming `setting`, for a name that is
    not one of `held_out`."""
    if isinstance(keep_held_out, bool):
        return held_out if keep_held_out else frozenset()
    keep = frozenset(keep_held_out)
    unknown = sorted(keep - held_out)
    if unknown:
        raise GscanError(f"{setting} {' '.join(unknown)}: not a hold-out split of {of} "
                         f"(those are: {', '.join(sorted(held_out)) or 'none'})")
    return keep


def _generate(corpus: _Corpus, examples: int, seed: int, held_out: frozenset[str],
              keep: frozenset[str]) -> GecaReport:
    start = time.perf_counter()
    templates = _Templates.build(corpus)
    substitutes = templates.substitutes()
    report = GecaReport(added=[], requested=examples, seed=seed, held_out=sorted(held_out),
                        keep_held_out=sorted(keep),
                        train_examples=corpus.examples, grid_size=corpus.origins[0].grid_size,
                        train_pairs=len(corpus.sequences), templates=len(templates))
    productive = np.array([bool(s) for s in substitutes])[templates.fillers]
    has_substitute = np.logical_or.reduceat(productive, templates.starts[:-1])
    candidates = np.flatnonzero(has_substitute)
    filler_tokens = [set(f) for f in templates.filler_bytes]
    rng = np.random.default_rng(seed)
    proposed: set[bytes] = set()
    for template in rng.permutation(candidates).tolist():
        if len(report.added) == examples:
            break
        report.templates_tried += 1
        entries = templates.group(template)
        own = set(templates.fillers[entries].tolist())
        # GECA's `overlap`: a substitute must not fill this template already, nor share a
        # token with each of its fillers.
        choices = sorted(b for b in set().union(*(substitutes[a] for a in own)) - own
                         if not all(filler_tokens[b] & filler_tokens[a] for a in own))
        rng.shuffle(choices)
        for substitute in choices[:VARIANTS]:
            entry = entries.start + int(rng.integers(entries.stop - entries.start))
            pair, filler = int(templates.pairs[entry]), int(templates.fillers[entry])
            table = bytes.maketrans(templates.filler_bytes[filler], templates.filler_bytes[substitute])
            sequence = corpus.sequences[pair].translate(table)
            if sequence in corpus.index or sequence in proposed:
                report.dropped["not new"] += 1
                continue
            proposed.add(sequence)
            grounded = _grounded(rng, *corpus.decode(sequence), corpus.origins[pair], report.dropped)
            if grounded is None:
                continue
            kinds = _held_out_kinds(*grounded, held_out, corpus.longest)
            report.held_out_kinds.update(kinds)
            if not keep.issuperset(kinds):
                report.dropped["kind of a held-out split"] += 1
                continue
            report.added.append(grounded[1])
            if len(report.added) == examples:
                break
    report.seconds = time.perf_counter() - start
    return report


def _held_out_kinds(command: Command, example: Example, held_out: frozenset[str], longest: int) -> list[str]:
    """The splits of `held_out` whose rule claims the example (its command, target and
    direction; `target_lengths`: more actions than the longest train target)."""
    situation = example.situation
    target = ObjectSpec(situation.target_object.size, situation.target_object.color, command.noun)
    kinds = [k for k in held_out_splits(command, target, situation.direction_to_target) if k in held_out]
    if LENGTH_SPLIT in held_out and len(example.target_commands) > longest:
        kinds.append(LENGTH_SPLIT)
    return kinds


def _grounded(rng: np.random.Generator, tokens: list[str], actions: list[str], origin: _Origin,
              dropped: Counter) -> tuple[Command, Example] | None:
    """The proposal's command and an example of it in a situation where the planner gives
    exactly its actions, or None (counted in `dropped`): not a gSCAN command, no layout
    on the grid for its route, or the planner does something else there."""
    try:
        command = parse_command(tokens)
        target_commands = tuple(Action.from_token(a) for a in actions)
    except (CommandError, InvalidActionError):
        dropped["not a gSCAN command"] += 1
        return None
    placement = _placement(rng, _route(target_commands), origin)
    if placement is None:
        dropped["no layout for its route"] += 1
        return None
    situation = _situation(rng, command, placement, origin)
    if tuple(demonstrate(situation, command.frame)) != target_commands:
        dropped["planner disagrees"] += 1
        return None
    return command, Example(tokens=command.tokens, situation=situation, target_commands=target_commands,
                            meaning=command.json_text, derivation=command.derivation,
                            verb_in_command=command.verb, manner=command.adverb,
                            referred_target=command.referred_target)


def _route(actions: tuple[Action, ...]) -> tuple[int, int]:
    """(rows, columns) from the agent to the target the actions walk to: the agent's
    displacement before its first push or pull (a gSCAN agent walks onto the target's cell
    and starts facing east), on an unbounded grid: whether it fits is `_placement`'s question."""
    heading, row, col = Heading.EAST, 0, 0
    for action in actions:
        if action in (Action.PUSH, Action.PULL):
            break
        if action is Action.WALK:
            row, col = row + heading.delta[0], col + heading.delta[1]
        elif action is Action.TURN_LEFT:
            heading = Heading((heading - 1) % 4)
        elif action is Action.TURN_RIGHT:
            heading = Heading((heading + 1) % 4)
    return row, col


def _placement(rng: np.random.Generator, route: tuple[int, int], origin: _Origin) -> Placement | None:
    """Agent and target cells for a route on the origin's grid: the origin's agent cell when
    the route fits from there, else a uniform one it fits from; None if it fits nowhere."""
    if route == (0, 0):
        return None
    d_row, d_col = route
    rows, cols = agent_cells(origin.grid_size, d_row, d_col)
    if not rows or not cols:
        return None
    agent = origin.agent
    if agent.row not in rows or agent.col not in cols:
        agent = Position(rows[int(rng.integers(len(rows)))], cols[int(rng.integers(len(cols)))])
    target = Position(agent.row + d_row, agent.col + d_col)
    return Placement(agent, target, direction_between(agent, target), manhattan(agent, target))


def _situation(rng: np.random.Generator, command: Command, placement: Placement, origin: _Origin) -> Situation:
    """A situation for `command` at `placement`: the target the command describes (unnamed
    attributes kept from the origin's target, the size nearest to it among those the
    command allows) and distractors drawn as the generator draws them."""
    sizes = sorted({spec.size for spec in possible_targets(command)}, key=lambda s: (abs(s - origin.target.size), s))
    target = ObjectSpec(sizes[0], command.color or origin.target.color, command.noun)
    return sample_situations(rng, command, target, (placement,), grid_size=origin.grid_size)[0]


# ---------------------------------------------------------------------------------------
# Datasets on disk
# ---------------------------------------------------------------------------------------
def augment_dataset(data: str | os.PathLike, out_dir: str | os.PathLike, *, examples: int = RELEASED_ADDED_EXAMPLES,
                    seed: int = 0, keep_held_out: bool | Iterable[str] = False, overwrite: bool = False,
                    progress: bool = False) -> GecaReport:
    """Write `out_dir/dataset.txt`: the dataset at `data` (dataset.txt or bags) with its train
    split followed by the GECA examples, every other split as it was. Proposals of a kind
    that one of the input's hold-out splits claims are dropped unless `keep_held_out` keeps
    every split claiming them (True: all; or split names, checked before the input is read
    against every hold-out split and after against the input's).

    The output must not be the input's folder, and an existing dataset.txt there is
    replaced only with `overwrite`. The splits are staged in a scratch folder of
    `out_dir` during one pass over the input, so memory holds only the train pairs.
    """
    from gscan_ros.outputs import check_targets, claimed, scratch

    start = time.perf_counter()
    if not isinstance(keep_held_out, bool):
        keep_held_out = kept_splits(keep_held_out, HOLD_OUT_SPLITS, of="any dataset")
    out_dir = Path(out_dir)
    source = Path(data)
    if (source if source.is_dir() else source.parent).resolve() == out_dir.resolve():
        raise GscanError(f"--out {out_dir} is the folder of the input dataset; write the augmented one elsewhere")
    target = out_dir / DATASET_FILE
    if out_dir.is_dir() and select_bags(out_dir) is not None:
        raise GscanError(f"--out {out_dir} holds a bag dataset; write the augmented dataset.txt elsewhere")
    with claimed(out_dir), claimed(target):  # the folder too: a killed writer's scratch in it is removed
        check_targets([target], overwrite=overwrite)
        with scratch(out_dir, "augment") as stage:
            splits: dict[str, Path] = {}
            names: dict[str, int] = {}  # every split of the input, in its order (empty ones too)
            with ExitStack() as files:
                counts: Counter = Counter()
                corpus = _Corpus.of(_staged(_dataset_lines(data, progress, names), stage, splits, counts, files))
            for name in names:
                if name not in splits:  # an empty split: copied as it is, and it claims its kinds
                    splits[name] = stage / f"{len(splits)}.jsonl"
                    splits[name].touch()
            splits = {name: splits[name] for name in [*names, *(s for s in splits if s not in names)]}
            held_out = frozenset(splits) & HOLD_OUT_SPLITS
            report = _generate(corpus, examples, seed, held_out, kept_splits(keep_held_out, held_out))
            if examples and not report.added:  # a plain copy would pass for an augmented dataset
                raise GscanError(f"{data}: no GECA example could be made ({report.templates} templates from "
                                 f"{report.train_pairs} train pairs, {report.templates_tried} tried); nothing written")
            lines = {split: _lines(path, report.added if split == TRAIN else ()) for split, path in splits.items()}
            sizes = {name: counts.get(name, 0) for name in splits}
            write_dataset_json(target, _header(data, report, sizes), lines)
    report.seconds = time.perf_counter() - start
    return report


def _dataset_lines(data: str | os.PathLike, progress: bool,
                   names: dict[str, int]) -> Iterator[tuple[str, str, Example | None]]:
    """(split, JSON line, Example for train examples) of every example, in file order:
    dataset.txt lines are the input's own JSON, bag episodes are written as examples.
    `names` gets the input's splits with their sizes, empty ones included."""
    from tqdm import tqdm

    bags = select_bags(data)
    if bags is None:
        from gscan_ros.data.dataset import decode_example, iter_raw_examples

        for split, index, raw in tqdm(iter_raw_examples(data, sizes=names), unit="ex", desc="read",
                                      disable=not progress):
            example = decode_example(split, index, raw) if split == TRAIN else None
            yield split, json.dumps(raw, separators=(",", ":")), example
        return
    from gscan_ros.data.io import bag_splits, iter_episodes

    names.update(bag_splits(data) or {})
    for episode in tqdm(iter_episodes(data), unit="ex", desc="read", disable=not progress):
        tokens = split_command(episode.command)
        meta = episode.meta
        example = Example(tokens=tokens, situation=episode.situation, target_commands=episode.actions,
                          meaning=",".join(tokens), derivation=meta.get("derivation"),
                          verb_in_command=meta.get("verb_in_command"), manner=meta.get("manner"),
                          referred_target=meta.get("referred_target"))
        yield episode.split, example_line(example), example if episode.split == TRAIN else None


def _staged(lines, stage: Path, splits: dict[str, Path], counts: Counter, files: ExitStack) -> Iterator[Example]:
    """Write each line to its split's file in `stage` (recorded in `splits`, counted in
    `counts`, opened on `files`); yield the train examples."""
    handles = {}
    for split, line, example in lines:
        if split not in handles:
            splits[split] = stage / f"{len(splits)}.jsonl"
            handles[split] = files.enter_context(open(splits[split], "w", encoding="utf-8"))
        handles[split].write(line + "\n")
        counts[split] += 1
        if example is not None:
            yield example


def _lines(path: Path, added: list[Example]) -> Iterator[str]:
    with open(path, encoding="utf-8") as staged:
        for line in staged:
            yield line.rstrip("\n")
    for example in added:
        yield example_line(example)


def _header(data: str | os.PathLike, report: GecaReport, sizes: dict[str, int]) -> DatasetHeader:
    """The input's header (dataset.txt) or the default one (bags, with the situations' grid
    size), with the augmentation recorded under `gscan_ros.augmentation`."""
    if select_bags(data) is None:
        header = read_header(data)
    else:
        header = DatasetHeader(grid_size=report.grid_size)
    record = dict(report.record(), source=str(data),
                  train_indices=[report.train_examples, report.train_examples + len(report.added)])
    ours = header.extra.setdefault("gscan_ros", {})
    ours["augmentation"] = record
    ours["split_sizes"] = {**sizes, TRAIN: sizes.get(TRAIN, 0) + len(report.added)}
    return header
