"""Generate a gSCAN dataset: commands x target objects x layouts -> planned examples -> splits.

Pipeline (as LauraRuis/groundedSCAN `dataset.py`):

1. layouts (`sample_placements`) per target object, from the seed;
2. candidates: every command, every object it can refer to, every layout of that
   object; for the compositional splits the hold-out rules are decided here and
   candidates matching several rules are dropped before any planning;
3. chunks: one per command, planned with `gscan_ros.world.demonstrate` in worker
   processes, each with its own seed stream (seed, command index), so the output is
   byte-identical for any number of workers; examples are serialised in the workers
   and parked in a scratch file, keeping only small per-example arrays in memory;
4. splits (`gscan_ros.data.splits`), then dataset.txt (or one bag per split and the
   dataset manifest), built in a staging folder inside the output folder and moved into
   place only once complete, under the output's lock (`gscan_ros.outputs`).

A subset (`max_examples`) is a sample of each split of the same-seed full set: the
full set's split draws, then a seeded share of each split
(`gscan_ros.data.splits.sample_splits`), less the sampled test examples the full set
discards as duplicates of train (`_subset`).

Defaults reproduce the released compositional split sizes: with 5 resamplings the
per-direction layout counts (17 straight, 41 diagonal) give exactly the released
B-H counts, and a 10 % random test + 1 % dev give the released train (367,933 with
the one k-shot example) and dev (3,716) counts.
"""
from __future__ import annotations

import hashlib
import json
import multiprocessing
import os
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import BinaryIO, Callable, Iterator

import numpy as np

from gscan_ros import __version__
from gscan_ros.data.bag_metadata import bag_owned_files
from gscan_ros.data.commands import COMMANDS, Command
from gscan_ros.data.dataset import DATASET_FILE, DatasetHeader, Example, is_dataset_file, write_dataset_json
from gscan_ros.data.io import DATASET_MANIFEST, MANIFEST_FORMAT, is_bag, is_manifest, write_manifest
from gscan_ros.data.sampling import (
    ALL_OBJECTS,
    OTHER_OBJECTS_SAMPLE_PERCENTAGE,
    ObjectSpec,
    Placement,
    possible_targets,
    sample_placements,
    sample_situations,
)
from gscan_ros.data.splits import (
    K_SHOT_SPLIT,
    SPLIT_KINDS,
    SPLIT_NAMES,
    SplitResult,
    assign_compositional,
    assign_length,
    discard_equivalent,
    held_out_splits,
    sample_splits,
)
from gscan_ros.errors import GscanError
from gscan_ros.outputs import claimed, refuse_links, scratch
from gscan_ros.world import Action, demonstrate
from gscan_ros.world.types import SUPPORTED_GRID_SIZES

FORMATS = ("txt", "mcap")
# Independent seed streams derived from the one CLI seed.
_STREAM_PLACEMENTS, _STREAM_SUBSET, _STREAM_SPLITS, _STREAM_OBJECTS = range(4)
_DROPPED = -1
_TOKENS = {a: a.token for a in Action}


@dataclass(frozen=True)
class GenerationConfig:
    """What to generate; `None` fields take the split kind's default (`resolved()`)."""

    seed: int = 0
    split_kind: str = "compositional"
    max_examples: int | None = None  # None: the full dataset; N: N of its examples, split by split
    num_resampling: int | None = None
    percentage_train: float | None = None  # 1 - random test fraction
    percentage_dev: float = 0.01
    k_shot: int | None = None  # cautiously examples moved into train (compositional only; default 1)
    cut_off_target_length: int | None = None  # length split only: longer targets are held out (default 15)
    grid_size: int | None = None
    other_objects_sample_percentage: float = OTHER_OBJECTS_SAMPLE_PERCENTAGE

    def resolved(self) -> "GenerationConfig":
        if self.split_kind not in SPLIT_KINDS:
            raise GscanError(f"unknown split kind {self.split_kind!r}; choose from {', '.join(SPLIT_KINDS)}")
        defaults = _DEFAULTS[self.split_kind]
        # An option of the other split kind would be recorded in the header and do nothing.
        if self.split_kind == "compositional" and self.cut_off_target_length is not None:
            raise GscanError("--cut-off-target-length applies to --split-kind length only")
        if self.split_kind == "length" and self.k_shot is not None:
            raise GscanError("--k-shot applies to --split-kind compositional only")
        out = replace(
            self,
            k_shot=(1 if self.k_shot is None else self.k_shot) if self.split_kind == "compositional" else None,
            cut_off_target_length=((15 if self.cut_off_target_length is None else self.cut_off_target_length)
                                   if self.split_kind == "length" else None),
            num_resampling=defaults["num_resampling"] if self.num_resampling is None else self.num_resampling,
            percentage_train=defaults["percentage_train"] if self.percentage_train is None else self.percentage_train,
            grid_size=defaults["grid_size"] if self.grid_size is None else self.grid_size,
        )
        if out.grid_size not in SUPPORTED_GRID_SIZES:
            raise GscanError(f"grid size {out.grid_size} is not supported "
                             f"({SUPPORTED_GRID_SIZES[0]} to {SUPPORTED_GRID_SIZES[-1]})")
        if out.max_examples is not None and out.max_examples < 1:
            raise GscanError(f"--examples must be positive, got {out.max_examples}")
        if out.split_kind == "compositional" and out.max_examples is not None and out.max_examples < out.k_shot:
            raise GscanError(f"--examples must be at least --k-shot ({out.k_shot}): a subset keeps every "
                             f"k-shot example, got {out.max_examples}")
        if out.num_resampling < 1:
            raise GscanError(f"num_resampling must be >= 1, got {out.num_resampling}")
        if not (0.0 < out.percentage_train <= 1.0 and 0.0 <= out.percentage_dev < 1.0):
            raise GscanError("percentage_train must be in (0, 1] and percentage_dev in [0, 1)")
        return out


# Both kinds' defaults reproduce the released split sizes. Compositional (A-H): a 6x6
# grid, 5 resamplings, 10 % test (module docstring). Length (I): no adverbs, a 12x12
# grid, 5 resamplings and a 20 % test: 720 (command, target) pairs x 592 layouts =
# 426,240 candidates, of which those longer than the cut-off (15) are held out and the
# rest split 80/20 then 99/1, the released train/dev/test/target_lengths counts
# (docs/data.md gives the arithmetic).
_DEFAULTS = {
    "compositional": {"num_resampling": 5, "percentage_train": 0.9, "grid_size": 6},
    "length": {"num_resampling": 5, "percentage_train": 0.8, "grid_size": 12},
}


@dataclass
class GenerationReport:
    path: Path
    split_sizes: dict[str, int]
    candidates: int
    generated: int
    dropped_multiple_rules: int
    discarded_equivalent: int
    seconds: float
    header: DatasetHeader = field(repr=False)


# ---------------------------------------------------------------------------------------
# Planning candidates
# ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Chunk:
    """The candidates of one command: targets x layouts, label per candidate."""

    command_index: int
    targets: tuple[ObjectSpec, ...]
    labels: np.ndarray  # int8[targets, layouts]: split index (0 = pool), or _DROPPED


def _plan(config: GenerationConfig, placements: dict[ObjectSpec, tuple[Placement, ...]]) -> list[_Chunk]:
    chunks = []
    for ci, command in enumerate(COMMANDS):
        if config.split_kind == "length" and command.adverb:
            continue  # the released split I has no adverbs (vocabularies 17/8)
        targets = possible_targets(command)
        labels = np.stack([_labels(config, command, t, placements[t]) for t in targets])
        chunks.append(_Chunk(ci, targets, labels))
    return chunks


def _labels(config: GenerationConfig, command: Command, target: ObjectSpec,
            layouts: tuple[Placement, ...]) -> np.ndarray:
    if config.split_kind == "length":
        return np.zeros(len(layouts), dtype=np.int8)
    by_direction = {}
    for direction in {p.direction for p in layouts}:
        rules = held_out_splits(command, target, direction)
        by_direction[direction] = _DROPPED if len(rules) > 1 else (SPLIT_NAMES.index(rules[0]) if rules else 0)
    return np.array([by_direction[p.direction] for p in layouts], dtype=np.int8)


def _tasks(chunks: list[_Chunk], selected: np.ndarray) -> list[tuple[int, tuple[ObjectSpec, ...], np.ndarray]]:
    """(command index, targets, mask) of each chunk with a selected candidate; `selected`
    runs over the candidates that are not dropped, in generation order."""
    tasks, start = [], 0
    for c in chunks:
        kept = c.labels != _DROPPED
        mask = np.zeros_like(kept)
        mask[kept] = selected[start:start + int(kept.sum())]
        start += int(kept.sum())
        if mask.any():
            tasks.append((c.command_index, c.targets, mask))
    return tasks


# ---------------------------------------------------------------------------------------
# Workers
# ---------------------------------------------------------------------------------------
@dataclass
class _ChunkResult:
    data: bytes  # the example JSON lines, "\n"-terminated
    line_lengths: np.ndarray  # int64, bytes per line incl. "\n"
    keys: np.ndarray  # uint64 equivalence hash (command, target sequence, target cell)
    target_lengths: np.ndarray  # int32


_WORKER_STATE: dict = {}


def _init_worker(config: GenerationConfig, placements: dict) -> None:
    _WORKER_STATE["config"] = config
    _WORKER_STATE["placements"] = placements


def _run_chunk(task: tuple[int, tuple[ObjectSpec, ...], np.ndarray, bool]) -> _ChunkResult:
    """Plan the candidates `mask` of one command; their JSON lines only if `serialise`."""
    command_index, targets, mask, serialise = task
    config: GenerationConfig = _WORKER_STATE["config"]
    placements = _WORKER_STATE["placements"]
    command = COMMANDS[command_index]
    rng = np.random.default_rng([config.seed, _STREAM_OBJECTS, command_index])
    fixed = {
        "command": command.json_text,
        "meaning": command.json_text,
        "derivation": command.derivation,
    }
    tail = {"verb_in_command": command.verb, "manner": command.adverb, "referred_target": command.referred_target}
    lines, keys, lengths = [], [], []
    for t, target in enumerate(targets):
        situations = sample_situations(rng, command, target, placements[target], select=mask[t],
                                       grid_size=config.grid_size,
                                       sample_percentage=config.other_objects_sample_percentage)
        for situation in situations:
            actions = demonstrate(situation, command.frame)
            target_text = ",".join([_TOKENS[a] for a in actions])
            cell = situation.target_object.position
            if serialise:
                example = dict(fixed, situation=situation.to_json(), target_commands=target_text, **tail)
                lines.append(json.dumps(example, separators=(",", ":")))
            digest = hashlib.blake2b(f"{command.json_text}|{target_text}|{cell.row},{cell.col}".encode(),
                                     digest_size=8).digest()
            keys.append(int.from_bytes(digest, "little"))
            lengths.append(len(actions))
    encoded = [line.encode() + b"\n" for line in lines]
    return _ChunkResult(
        data=b"".join(encoded),
        line_lengths=np.array([len(e) for e in encoded], dtype=np.int64),
        keys=np.array(keys, dtype=np.uint64),
        target_lengths=np.array(lengths, dtype=np.int32),
    )


_ChunkRunner = Callable[[list], Iterator[_ChunkResult]]


@contextmanager
def _chunk_runner(config: GenerationConfig, placements: dict, workers: int) -> Iterator[_ChunkRunner]:
    """A function from tasks to chunk results in task order, computed in `workers`
    processes (1: in-process), started once for every pass over the chunks."""
    if workers <= 1:
        _init_worker(config, placements)
        yield lambda tasks: map(_run_chunk, tasks)
        return
    ctx = multiprocessing.get_context("spawn")  # safe whatever threads the parent runs
    with ctx.Pool(workers, initializer=_init_worker, initargs=(config, placements)) as pool:
        yield lambda tasks: pool.imap(_run_chunk, tasks, chunksize=1)


# ---------------------------------------------------------------------------------------
# Driver
# ---------------------------------------------------------------------------------------
def generate_dataset(out_dir: str | os.PathLike, config: GenerationConfig = GenerationConfig(), *,
                     workers: int = 1, fmt: str = "txt", progress: bool = False,
                     overwrite: bool = False) -> GenerationReport:
    """Generate a dataset into `out_dir` (DIR/dataset.txt, or DIR/<split>/ bags and
    DIR/manifest.json for mcap).

    A dataset already in `out_dir` is refused unless `overwrite`. The new one is built in a
    staging folder beside the old one, which is swapped out only once the new one is
    complete (`_install`), so an interrupted or failed run leaves the old dataset as it
    was. One writer at a time (`claimed`); nothing is written before the settings are checked.
    """
    if fmt not in FORMATS:
        raise GscanError(f"unknown format {fmt!r}; choose from {', '.join(FORMATS)}")
    start = time.perf_counter()
    config = config.resolved()
    out_dir = Path(out_dir)
    with claimed(out_dir):
        previous = _previous_dataset(out_dir, overwrite, fmt)
        layout_rng = np.random.default_rng([config.seed, _STREAM_PLACEMENTS])
        placements = {t: sample_placements(layout_rng, config.grid_size, config.num_resampling) for t in ALL_OBJECTS}
        chunks = _plan(config, placements)
        candidates = sum(c.labels.size for c in chunks)
        dropped = sum(int((c.labels == _DROPPED).sum()) for c in chunks)
        labels = np.concatenate([c.labels[c.labels != _DROPPED] for c in chunks]).astype(np.int8)
        if config.split_kind == "compositional":
            _check_k_shot(config.k_shot, int((labels == SPLIT_NAMES.index(K_SHOT_SPLIT)).sum()))
        out_dir.mkdir(parents=True, exist_ok=True)
        with scratch(out_dir, "dataset") as stage:
            store_path = stage / "examples.jsonl"
            with open(store_path, "wb") as store, _chunk_runner(config, placements, workers) as run:
                if config.max_examples is None:
                    everything = _tasks(chunks, np.ones(len(labels), dtype=bool))
                    offsets, keys, lengths = _run_tasks(run, everything, progress, store)
                    result = _assign(config, labels, keys, lengths, dropped)
                else:
                    result, selected = _subset(config, placements, chunks, labels, dropped, run, progress)
                    offsets, _, _ = _run_tasks(run, _tasks(chunks, selected), progress, store)
            header = _header(config, result, generated=len(offsets) - 1, candidates=candidates)
            built = stage / "new"
            built.mkdir()
            if fmt == "txt":
                with open(store_path, "rb") as store:
                    lines = {s: _stored_lines(store, offsets, v) for s, v in result.splits.items()}
                    write_dataset_json(built / DATASET_FILE, header, lines)
            else:
                _write_bags(built, result, store_path, offsets, workers, progress)
                write_manifest(built, {s: len(v) for s, v in result.splits.items()}, header.to_json())
            _install(built, out_dir, previous, trash=stage / "replaced")
    return GenerationReport(
        path=out_dir / DATASET_FILE if fmt == "txt" else out_dir,
        split_sizes={s: len(v) for s, v in result.splits.items()},
        candidates=candidates,
        generated=len(offsets) - 1,
        dropped_multiple_rules=dropped,
        discarded_equivalent=result.discarded_equivalent,
        seconds=time.perf_counter() - start,
        header=header,
    )


def _assign(config: GenerationConfig, labels: np.ndarray, keys: np.ndarray, lengths: np.ndarray,
            dropped: int) -> SplitResult:
    """The splits of the candidates `labels` (generation order), from the seed's split stream."""
    split_rng = np.random.default_rng([config.seed, _STREAM_SPLITS])
    if config.split_kind == "compositional":
        return assign_compositional(split_rng, labels, keys, config.percentage_train, config.percentage_dev,
                                    config.k_shot, dropped)
    return assign_length(split_rng, lengths, keys, config.cut_off_target_length, config.percentage_train,
                         config.percentage_dev)


def _subset(config: GenerationConfig, placements: dict, chunks: list[_Chunk], labels: np.ndarray, dropped: int,
            run: _ChunkRunner, progress: bool) -> tuple[SplitResult, np.ndarray]:
    """The `max_examples` subset: its splits (indices among its examples, generation
    order) and which candidates it holds (`selected`, over `labels`).

    The full set's draws come first. They need no plans but the length split's target
    lengths, and the discard of test duplicates of train draws no random numbers, so
    they are drawn with every key distinct (nothing discarded) and the discard is applied
    to the sampled test examples alone (`_kept_test`).
    """
    lengths = np.zeros(len(labels), dtype=np.int32)
    if config.split_kind == "length":
        _, _, lengths = _run_tasks(run, _tasks(chunks, np.ones(len(labels), dtype=bool)), progress)
    drawn = _assign(config, labels, np.arange(len(labels), dtype=np.uint64), lengths, dropped)
    chosen = sample_splits(np.random.default_rng([config.seed, _STREAM_SUBSET]), drawn, config.max_examples)
    splits = dict(chosen.splits, test=_kept_test(config, placements, chunks, drawn, chosen.splits["test"], run,
                                                 progress))
    selected = np.zeros(len(labels), dtype=bool)
    selected[np.concatenate(list(splits.values()))] = True
    position = np.cumsum(selected) - 1  # candidate index -> index among the subset's examples
    return replace(chosen, splits={s: position[v] for s, v in splits.items()},
                   discarded_equivalent=len(chosen.splits["test"]) - len(splits["test"]),
                   k_shot=tuple(int(position[i]) for i in chosen.k_shot)), selected


def _kept_test(config: GenerationConfig, placements: dict, chunks: list[_Chunk], drawn: SplitResult,
               test: np.ndarray, run: _ChunkRunner, progress: bool) -> np.ndarray:
    """The candidates of `test` that the full set keeps: those equivalent to none of its
    train as drawn against test (before dev and the k-shot examples were drawn from it).
    Equivalent examples share their command and target cell, so only the train
    candidates of the test candidates' (command, target cell) are planned."""
    train = drawn.splits["train"]
    train = np.concatenate([train[:len(train) - len(drawn.k_shot)], drawn.splits["dev"]])
    cell = {t: np.array([p.target.row * config.grid_size + p.target.col for p in layouts])
            for t, layouts in placements.items()}
    group = np.concatenate([c.command_index * config.grid_size ** 2 + np.stack([cell[t] for t in c.targets])
                            [c.labels != _DROPPED] for c in chunks])  # (command, target cell) per candidate
    train = train[np.isin(group[train], group[test])]
    planned = np.zeros(len(group), dtype=bool)
    planned[test] = planned[train] = True
    keys = np.zeros(len(group), dtype=np.uint64)
    _, keys[planned], _ = _run_tasks(run, _tasks(chunks, planned), progress)
    return discard_equivalent(test, train, keys)


def _run_tasks(run: _ChunkRunner, tasks: list, progress: bool,
               store: BinaryIO | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plan the tasks' candidates and append their lines to `store`; return per-example
    arrays in generation order: line start offsets in `store` (n + 1), equivalence keys,
    target lengths. Without `store`, plan only (keys and lengths; no lines, no offsets)."""
    from tqdm import tqdm

    serialise = store is not None
    total = sum(int(mask.sum()) for _, _, mask in tasks)
    offsets, keys, lengths = [np.zeros(1, dtype=np.int64)], [np.zeros(0, np.uint64)], [np.zeros(0, np.int32)]
    with tqdm(total=total, unit="ex", desc="generate" if serialise else "plan", disable=not progress) as bar:
        for chunk in run([(*task, serialise) for task in tasks]):
            if serialise:
                store.write(chunk.data)
            offsets.append(chunk.line_lengths)
            keys.append(chunk.keys)
            lengths.append(chunk.target_lengths)
            bar.update(len(chunk.keys))
    return np.cumsum(np.concatenate(offsets)), np.concatenate(keys), np.concatenate(lengths)


def _header(config: GenerationConfig, result: SplitResult, generated: int, candidates: int) -> DatasetHeader:
    train = result.splits["train"]
    record = {
        "version": __version__,
        "config": asdict(config),
        "candidates": candidates,
        "generated": generated,
        "dropped_multiple_rules": result.dropped_multiple_rules,
        "discarded_equivalent": result.discarded_equivalent,
        # The k-shot examples are the last ones of train (quirk Q2, docs/model.md: seeded and recorded).
        "k_shot_train_indices": list(range(len(train) - len(result.k_shot), len(train))),
        # Readers refuse a split the file lacks before streaming it (`dataset.SPLIT_SIZES`).
        "split_sizes": {s: len(v) for s, v in result.splits.items()},
    }
    if config.split_kind == "length":
        record["cut_off_target_length"] = config.cut_off_target_length
    return DatasetHeader(grid_size=config.grid_size, percentage_train=config.percentage_train,
                         extra={"gscan_ros": record})


def _stored_lines(store, offsets: np.ndarray, indices) -> Iterator[str]:
    """The examples `indices` of the line store (offsets: line starts, n + 1), without "\\n"."""
    for i in indices:
        begin, end = int(offsets[i]), int(offsets[i + 1]) - 1
        yield os.pread(store.fileno(), end - begin, begin).decode()


def _write_split_bag(out_dir: Path, split: str, store_path: Path, offsets: np.ndarray, indices,
                     progress: bool = False) -> str:
    from tqdm import tqdm

    from gscan_ros.data.bag import write_bag

    with open(store_path, "rb") as store:
        episodes = (Example.from_json(json.loads(line)).to_episode(split, i)
                    for i, line in enumerate(_stored_lines(store, offsets, indices)))
        write_bag(out_dir / split, tqdm(episodes, total=len(indices), desc=split, unit="ep", disable=not progress))
    return split


def _write_split_job(job: tuple) -> str:
    return _write_split_bag(*job)


def _write_bags(out_dir: Path, result: SplitResult, store_path: Path, offsets: np.ndarray, workers: int,
                progress: bool) -> None:
    """One bag per split; with `workers` > 1 the splits are written in parallel, largest
    first (train is about half of a compositional set, so two workers halve the time)."""
    from tqdm import tqdm

    splits = sorted((s for s, v in result.splits.items() if len(v)), key=lambda s: -len(result.splits[s]))
    if workers <= 1 or len(splits) <= 1:
        for split in splits:
            _write_split_bag(out_dir, split, store_path, offsets, result.splits[split], progress)
        return
    ctx = multiprocessing.get_context("spawn")
    with ctx.Pool(min(workers, len(splits))) as pool, \
            tqdm(total=sum(len(result.splits[s]) for s in splits), unit="ep", desc="bags", disable=not progress) as bar:
        jobs = [(out_dir, s, store_path, offsets, result.splits[s]) for s in splits]
        for split in pool.imap_unordered(_write_split_job, jobs, chunksize=1):
            bar.update(len(result.splits[split]))


def _check_k_shot(k_shot: int, available: int) -> None:
    """k-shot takes examples from adverb_1: refuse more than it holds (never clamp silently)."""
    if not 0 <= k_shot <= available:
        raise GscanError(f"--k-shot must be in [0, {available}] (the {K_SHOT_SPLIT} examples these settings "
                         f"generate), got {k_shot}")


def _previous_dataset(out_dir: Path, overwrite: bool, fmt: str) -> list[Path]:
    """What an earlier `generate` (or a recorder) wrote to `out_dir`: dataset.txt, <split>/
    bags, the manifest, or a bag's own files when `out_dir` is itself a bag (every reader
    would read that bag, not the new dataset); refused without `overwrite`. Something to be
    moved away or written over that is not a dataset's own (`_in_the_way`) is refused
    first, with `overwrite` too, and named: a user's file must never go as an old
    dataset's. A symbolic link where the dataset goes is always refused."""
    if out_dir.exists() and not out_dir.is_dir():
        raise GscanError(f"--out {out_dir} is a file, not a directory")
    targets = [out_dir / name for name in (DATASET_FILE, DATASET_MANIFEST, *SPLIT_NAMES)]
    refuse_links(targets)
    bag = bag_owned_files(out_dir) if is_bag(out_dir) else []
    found = [p for p in targets[:2] if p.is_file()] + [p for p in targets[2:] if is_bag(p)]
    written = targets[:1] if fmt == "txt" else targets[1:]
    for path in dict.fromkeys([*found, *written]):  # what is moved away or written over
        problem = _in_the_way(path)
        if problem:
            raise GscanError(f"{path} {problem}; refusing to overwrite it")
    if (found or bag) and not overwrite:
        names = ", ".join((["a rosbag2 bag"] if bag else []) + [p.name for p in found[:3]])
        names += ", ..." if len(found) > 3 else ""
        raise GscanError(f"--out {out_dir} already holds a dataset ({names}); pass --overwrite to replace it")
    return found + bag


def _in_the_way(path: Path) -> str | None:
    """Why `path`, where a dataset keeps dataset.txt, its manifest or a split bag, may not
    be replaced (None: absent, or a dataset's own: a dataset.txt that begins as one, a
    manifest that reads as ours, a folder of nothing but a bag's files)."""
    if not path.exists():
        return None
    if path.name in (DATASET_FILE, DATASET_MANIFEST) and not path.is_file():
        return "is not a file"
    if path.name == DATASET_FILE:
        return None if is_dataset_file(path) else 'is not a gSCAN dataset (it does not begin with {"grid_size": ...)'
    if path.name == DATASET_MANIFEST:
        return None if is_manifest(path) else f"is not a gscan_ros dataset manifest (format {MANIFEST_FORMAT})"
    if not path.is_dir():
        return "is not a folder"
    own = bag_owned_files(path) if is_bag(path) else []
    foreign = sorted(p.name for p in path.iterdir() if p not in own)
    return f"holds files that are not {'the bag' if own else 'a bag'}'s ({', '.join(foreign[:3])})" if foreign else None


def _install(built: Path, out_dir: Path, previous: list[Path], trash: Path) -> None:
    """Swap the complete dataset `built` in for `previous`: by renames, the old manifest
    first (the folder reads as incomplete from then on), the new manifest last."""
    trash.mkdir()
    moved_out: list[Path] = []
    moved_in: list[Path] = []
    try:
        for path in sorted(previous, key=lambda p: p.name != DATASET_MANIFEST):
            path.rename(trash / path.name)
            moved_out.append(path)
        for path in sorted(built.iterdir(), key=lambda p: p.name == DATASET_MANIFEST):
            path.rename(out_dir / path.name)
            moved_in.append(out_dir / path.name)
    except BaseException:  # a failed rename: the old dataset goes back, whole (the staging folder is removed)
        for path in reversed(moved_in):
            path.rename(built / path.name)
        for path in reversed(moved_out):
            (trash / path.name).rename(path)
        raise
