"""Experiment plans: the plan YAML, its datasets (`DataRecipe`) and its runs (`RunSpec`).

A plan (YAML, `configs/experiments/paper.yaml`) names datasets (generator flags) and runs
(training config, dataset, seeds, `--set` overrides, test splits); a `defaults:` block of
overrides is merged into every run, so the shared recipe and budget are one edit. Each
`runs:` entry expands into one run per seed, named `<entry>_s<seed>`, in seed rounds.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Sequence

from gscan_ros.data.splits import SPLIT_KINDS, TEST_SPLITS
from gscan_ros.errors import GscanError, quoted, shortened
from gscan_ros.experiments.paper_figures import COLUMN_TITLES
from gscan_ros.outputs import file_in_the_way
from gscan_ros.user_files import parse_yaml, read_yaml

# Keys the runner sets itself, never the plan's `defaults:` / `set:`.
RUNNER_KEYS = ("seed", "threads")


class PlanError(GscanError):
    """A plan file that is malformed; the message names the bad key."""


@dataclass(frozen=True)
class DataRecipe:
    """A dataset: `generate` flags (and an `augment` method for its train split), or `path`
    to an existing dataset used as it is."""

    name: str
    split_kind: str = "compositional"
    examples: int | None = None  # None: --full
    k_shot: int = 1
    seed: int = 0
    grid_size: int | None = None
    num_resampling: int | None = None
    percentage_train: float | None = None
    percentage_dev: float | None = None
    cut_off_target_length: int | None = None
    path: str | None = None
    augment: str | None = None  # a `gscan-ros augment --method`
    augment_seed: int | None = None  # its --seed; None: `seed`
    keep_held_out: bool | tuple[str, ...] = False  # its --keep-held-out: additions of those held-out
    # splits' kinds stay (True: of every one)

    def __post_init__(self):
        if self.augment is not None and self.augment_seed is None:
            object.__setattr__(self, "augment_seed", self.seed)

    def flags(self) -> list[str]:
        """`gscan-ros generate` arguments (besides --out, --workers, --quiet)."""
        out = ["--split-kind", self.split_kind, "--seed", str(self.seed), "--format", "mcap"]
        out += ["--full"] if self.examples is None else ["--examples", str(self.examples)]
        if self.split_kind == "compositional":
            out += ["--k-shot", str(self.k_shot)]
        for key in ("grid_size", "num_resampling", "percentage_train", "percentage_dev", "cut_off_target_length"):
            value = getattr(self, key)
            if value is not None:
                out += [f"--{key.replace('_', '-')}", str(value)]
        return out

    def augment_flags(self) -> list[str]:
        """`gscan-ros augment` arguments (besides --data, --out, --quiet); none without `augment`."""
        if self.augment is None:
            return []
        out = ["--method", self.augment, "--seed", str(self.augment_seed)]
        if self.keep_held_out:
            out += ["--keep-held-out", *([] if self.keep_held_out is True else self.keep_held_out)]
        return out

    def directory(self, data_root: Path) -> Path:
        """`path`, or `<data_root>/<name>-<hash of the flags>` (new flags, new folder; a
        recipe without `augment` hashes its generate flags alone, as before there was one)."""
        if self.path is not None:
            return Path(self.path)
        digest = hashlib.sha256(json.dumps(self.flags() + self.augment_flags()).encode()).hexdigest()[:8]
        return data_root / f"{self.name}-{digest}"

    def record(self) -> dict:
        """What results.json says about the data."""
        keys = ("name", "split_kind", "examples", "k_shot", "seed", "cut_off_target_length", "path", "augment",
                "augment_seed", "keep_held_out")
        out = {k: getattr(self, k) for k in keys}
        if isinstance(self.keep_held_out, tuple):
            out["keep_held_out"] = list(self.keep_held_out)
        return out


@dataclass(frozen=True)
class RunSpec:
    """One training run of a plan: entry `entry` of `runs:` at seed `seed`."""

    index: int
    name: str
    entry: str
    column: str
    title: str
    paper_column: str | None
    config: Path
    data: DataRecipe
    seed: int
    overrides: tuple[str, ...]
    splits: tuple[str, ...]
    eval_max_examples: int  # a seeded subset of this many episodes per test split; 0 = all

    def train_overrides(self, threads: int) -> list[str]:
        return [*self.overrides, f"seed={self.seed}", f"threads={threads}"]


@dataclass
class Plan:
    path: Path
    results: Path
    data_root: Path
    eval_batch_size: int  # every run's evaluation batch (each run's own example cap is on its RunSpec)
    datasets: dict[str, DataRecipe]
    runs: list[RunSpec]

    def share(self, worker: tuple[int, int] | None, only: tuple[str, ...] = ()) -> list[RunSpec]:
        """Worker i of N takes the runs whose index % N == i (every run without a worker);
        `only` keeps the runs named there (a `runs:` entry name, for all its seeds in plan
        order, or a run name like 'semantic_s1') in the order named, so a user sets what
        trains next — PlanError for a name the plan does not have."""
        runs = _named(self.runs, only, str(self.path)) if only else list(self.runs)
        if worker is None:
            return runs
        i, n = worker
        return [r for r in runs if r.index % n == i]


_TOP_KEYS = ("results", "data_root", "defaults", "evaluation", "datasets", "runs", "first")
_DATASET_KEYS = {"split_kind": str, "examples": (int, str), "k_shot": int, "seed": int, "grid_size": int,
                 "num_resampling": int, "percentage_train": float, "percentage_dev": float,
                 "cut_off_target_length": int, "path": str, "augment": str, "augment_seed": int,
                 "keep_held_out": (bool, list)}
_RUN_KEYS = ("name", "column", "title", "paper", "config", "data", "seeds", "set", "splits", "max_eval_examples")
_EVAL_KEYS = ("max_examples", "batch_size")


def load_plan(path: str | Path, results: str | Path | None = None, data_root: str | Path | None = None) -> Plan:
    """Parse and check a plan; PlanError (one line, naming the key) on anything wrong.
    Relative paths in the plan are relative to the working directory (the repository
    root). `results` / `data_root` replace the plan's."""
    path = Path(path)
    where = f"plan {path}"
    doc = read_yaml(path, where, PlanError)
    if not isinstance(doc, dict):
        raise PlanError(f"{where} must be a mapping with keys {list(_TOP_KEYS)}")
    _known(doc, _TOP_KEYS, where, "")
    defaults = _overrides(doc.get("defaults") or {}, where, "defaults")
    evaluation = doc.get("evaluation") or {}
    _mapping(evaluation, where, "evaluation")
    _known(evaluation, _EVAL_KEYS, where, "evaluation.")
    max_examples = _int(evaluation.get("max_examples", 0), where, "evaluation.max_examples", 0)
    batch_size = _int(evaluation.get("batch_size", 1024), where, "evaluation.batch_size", 1)
    datasets = {name: _dataset(name, spec, where)
                for name, spec in _mapping(doc.get("datasets"), where, "datasets").items()}
    if not datasets:
        raise PlanError(f"{where}: datasets must name at least one dataset")
    entries = doc.get("runs")
    if not isinstance(entries, list) or not entries:
        raise PlanError(f"{where}: runs must be a non-empty list of runs")
    parsed = []
    for i, entry in enumerate(entries):
        key = f"runs[{i}]"
        _mapping(entry, where, key)
        _known(entry, _RUN_KEYS, where, f"{key}.")
        for required in ("name", "config", "data", "seeds"):
            if required not in entry:
                raise PlanError(f"{where}: {key}.{required} is missing")
        name = _text(entry["name"], where, f"{key}.name")
        if not name.replace("_", "").replace("-", "").isalnum():
            raise PlanError(f"{where}: {key}.name must be letters, digits, '_' or '-', got {quoted(name)}")
        config = Path(_text(entry["config"], where, f"{key}.config"))
        if not config.is_file():
            raise PlanError(f"{where}: {key}.config {quoted(str(config))} is not a file")
        data = _text(entry["data"], where, f"{key}.data")
        if data not in datasets:
            raise PlanError(f"{where}: {key}.data {quoted(data)} is not in datasets "
                            f"({shortened(', '.join(map(str, datasets)))})")
        seeds = entry["seeds"]
        if not (isinstance(seeds, list) and seeds and all(isinstance(s, int) and not isinstance(s, bool)
                                                          and s >= 0 for s in seeds)) or len(set(seeds)) < len(seeds):
            raise PlanError(f"{where}: {key}.seeds must be a list of distinct integers >= 0, got {quoted(seeds)}")
        column = _text(entry.get("column", name), where, f"{key}.column")
        paper = entry.get("paper", column if column in COLUMN_TITLES else None)
        if paper is not None and (not isinstance(paper, str) or paper not in COLUMN_TITLES):
            raise PlanError(f"{where}: {key}.paper must be one of {list(COLUMN_TITLES)}, got {quoted(paper)}")
        title = _text(entry.get("title", COLUMN_TITLES.get(column, column)), where, f"{key}.title")
        kind = datasets[data].split_kind
        splits = entry.get("splits", list(TEST_SPLITS[kind]))
        if not (isinstance(splits, list) and splits and all(isinstance(s, str) and s in TEST_SPLITS[kind]
                                                            for s in splits)) or len(set(splits)) < len(splits):
            raise PlanError(f"{where}: {key}.splits must be a list of distinct {kind} test splits "
                            f"{list(TEST_SPLITS[kind])}, got {quoted(splits)}")
        overrides = defaults + _overrides(entry.get("set") or {}, where, f"{key}.set")
        eval_max = _int(entry.get("max_eval_examples", max_examples), where, f"{key}.max_eval_examples", 0)
        parsed.append((name, column, title, paper, config, datasets[data], seeds, tuple(overrides), tuple(splits),
                       eval_max))
    runs = _expand(parsed, where)
    first = doc.get("first") or []
    if not (isinstance(first, list) and all(isinstance(n, str) for n in first)):
        raise PlanError(f"{where}: first must be a list of run or runs[] entry names, got {quoted(first)}")
    if first:
        taken = _named(runs, first, where)
        names = {r.name for r in taken}
        runs = [replace(r, index=i) for i, r in enumerate(taken + [r for r in runs if r.name not in names])]
    results = results or _text(doc.get("results", "results"), where, "results")
    data_root = data_root or _text(doc.get("data_root", "data_gen/experiments"), where, "data_root")
    for key, folder in (("results", results), ("data_root", data_root)):
        blocking = file_in_the_way(folder)
        if blocking is not None:
            raise PlanError(f"{where}: {key} must be a folder, but {quoted(str(blocking))} is a file")
    return Plan(path=path, results=Path(results), data_root=Path(data_root), eval_batch_size=batch_size,
                datasets=datasets, runs=runs)


def _expand(entries: list[tuple], where: str) -> list[RunSpec]:
    """Runs in seed rounds: every entry's first seed, then every entry's second seed ...,
    so a partial plan (or each worker's first runs) covers every column once first."""
    runs: list[RunSpec] = []
    names: set[str] = set()
    for position in range(max(len(e[6]) for e in entries)):
        for name, column, title, paper, config, data, seeds, overrides, splits, eval_max in entries:
            if position >= len(seeds):
                continue
            run_name = f"{name}_s{seeds[position]}"
            if run_name in names:
                raise PlanError(f"{where}: run {quoted(run_name)} appears twice (runs[].name must be unique)")
            names.add(run_name)
            runs.append(RunSpec(index=len(runs), name=run_name, entry=name, column=column, title=title,
                                paper_column=paper, config=config, data=data, seed=seeds[position],
                                overrides=overrides, splits=splits, eval_max_examples=eval_max))
    return runs


def _named(runs: list[RunSpec], names: Sequence[str], where: str) -> list[RunSpec]:
    """The runs `names` names (an entry name stands for all its seeds, in plan order),
    in the order named; a run named twice keeps its first place. PlanError for a name
    the plan does not have."""
    unknown = sorted(set(names) - {r.entry for r in runs} - {r.name for r in runs})
    if unknown:
        raise PlanError(f"{where}: no run or runs[] entry named {shortened(', '.join(map(repr, unknown)))}")
    named: dict[str, RunSpec] = {}
    for name in names:
        named.update((r.name, r) for r in runs if name in (r.entry, r.name) and r.name not in named)
    return list(named.values())


def _dataset(name, spec, where: str) -> DataRecipe:
    key = f"datasets.{shortened(str(name))}"
    _mapping(spec, where, key)
    _known(spec, tuple(_DATASET_KEYS), where, f"{key}.")
    values = {}
    for field_name, value in spec.items():
        kinds = _DATASET_KEYS[field_name]
        kinds = (int, float) if kinds is float else kinds if isinstance(kinds, tuple) else (kinds,)
        if not isinstance(value, kinds) or (isinstance(value, bool) and bool not in kinds):
            raise PlanError(f"{where}: {key}.{field_name} has the wrong type: {quoted(value)}")
        values[field_name] = value
    if "path" in values:  # a given dataset: the keys that generate one would be ignored
        generating = sorted(set(values) - {"path", "split_kind", "augment", "augment_seed", "keep_held_out"})
        if generating:
            raise PlanError(f"{where}: {key} is given by path; {', '.join(f'{key}.{k}' for k in generating)} "
                            f"would generate one (drop them, or drop path)")
    kind = values.get("split_kind", "compositional")
    if kind not in SPLIT_KINDS:
        raise PlanError(f"{where}: {key}.split_kind must be one of {list(SPLIT_KINDS)}, got {quoted(kind)}")
    examples = values.pop("examples", "full")
    if examples != "full" and not (isinstance(examples, int) and examples > 0):
        raise PlanError(f"{where}: {key}.examples must be 'full' or a positive integer, got {quoted(examples)}")
    for int_key in ("k_shot", "seed", "augment_seed"):
        if values.get(int_key, 0) < 0:
            raise PlanError(f"{where}: {key}.{int_key} must be >= 0, got {quoted(values[int_key])}")
    _augment_keys(values, where, key)
    recipe = DataRecipe(name=str(name), examples=None if examples == "full" else examples, **values)
    if recipe.path is None:  # what `generate` would refuse, refused before any run starts
        from gscan_ros.data.generate import GenerationConfig

        optional = {k: getattr(recipe, k) for k in ("num_resampling", "percentage_train", "percentage_dev",
                                                     "cut_off_target_length", "grid_size")
                    if getattr(recipe, k) is not None}
        try:
            k_shot = recipe.k_shot if recipe.split_kind == "compositional" else None  # `flags()` passes it so
            GenerationConfig(seed=recipe.seed, split_kind=recipe.split_kind, max_examples=recipe.examples,
                             k_shot=k_shot, **optional).resolved()
        except GscanError as error:
            raise PlanError(f"{where}: {key}: {error}") from None
    return recipe


def _augment_keys(values: dict, where: str, key: str) -> None:
    """`augment` names a method of `gscan-ros augment` and applies to generated data only;
    `augment_seed` and `keep_held_out` go with it."""
    from gscan_ros.data.geca import AUGMENT_METHODS, HOLD_OUT_SPLITS, kept_splits

    keep = values.get("keep_held_out")
    if isinstance(keep, list):
        if not keep or not all(isinstance(name, str) for name in keep):
            raise PlanError(f"{where}: {key}.keep_held_out must be true, false or a list of hold-out splits "
                            f"({', '.join(sorted(HOLD_OUT_SPLITS))}), got {quoted(keep)}")
        try:
            kept = kept_splits(keep, HOLD_OUT_SPLITS, of="any dataset", setting=f"{where}: {key}.keep_held_out")
        except GscanError as error:
            raise PlanError(str(error)) from None
        values["keep_held_out"] = tuple(sorted(kept))
    method = values.get("augment")
    if method is None:
        for dependent in ("augment_seed", "keep_held_out"):
            if dependent in values:
                raise PlanError(f"{where}: {key}.{dependent} needs {key}.augment")
        return
    if method not in AUGMENT_METHODS:
        raise PlanError(f"{where}: {key}.augment must be one of {list(AUGMENT_METHODS)}, got {quoted(method)}")
    if "path" in values:
        raise PlanError(f"{where}: {key}.augment applies to a generated dataset; a path: dataset is used as it is")


def _overrides(block, where: str, key: str) -> list[str]:
    """A mapping of config keys (`model:` nested or `model.x` dotted) as `--set` items."""
    _mapping(block, where, key)
    items = []
    for name, value in block.items():
        if name == "model" and isinstance(value, dict):
            items += [f"model.{k}={_yaml_text(v)}" for k, v in value.items()]
            continue
        if name in RUNNER_KEYS:
            raise PlanError(f"{where}: {key}.{name} is set by the runner (seeds: per run; threads: --threads)")
        items.append(f"{name}={_yaml_text(value)}")
    return items


def _yaml_text(value) -> str:
    """`value` as text that `--set` (YAML) reads back unchanged: plain when it already
    does (attention+state), else JSON (a quoted '1', a list, text that is no YAML)."""
    if isinstance(value, str):
        try:
            if parse_yaml(value, "", PlanError) == value:
                return value
        except PlanError:
            pass
    return json.dumps(value)


def _mapping(value, where: str, key: str) -> dict:
    if not isinstance(value, dict):
        raise PlanError(f"{where}: {key} must be a mapping, got {quoted(value)}")
    return value


def _known(mapping: dict, known: tuple, where: str, prefix: str) -> None:
    unknown = sorted(str(k) for k in mapping if k not in known)
    if unknown:
        raise PlanError(f"{where}: unknown key {prefix}{shortened(unknown[0])} (known: {', '.join(known)})")


def _text(value, where: str, key: str) -> str:
    if not isinstance(value, str) or not value:
        raise PlanError(f"{where}: {key} must be a non-empty string, got {quoted(value)}")
    return value


def _int(value, where: str, key: str, low: int) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or value < low:
        raise PlanError(f"{where}: {key} must be an integer >= {low}, got {quoted(value)}")
    return value


def resolve_config(plan: Plan, spec: RunSpec, threads: int = 0):
    """The run's TrainConfig (config file + defaults + set + seed); PlanError names the run."""
    from gscan_ros.training.config import TrainConfig

    try:
        return TrainConfig.load(spec.config, spec.train_overrides(threads))
    except GscanError as exc:
        raise PlanError(f"plan {plan.path}: run {spec.name}: {exc}") from None

