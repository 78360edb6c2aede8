"""Experiment plans: many training runs, their datasets and their evaluation, restartable.

A plan (YAML, `configs/experiments/paper.yaml`) names datasets (generator flags) and runs
(training config, dataset, seeds, `--set` overrides, test splits); a `defaults:` block of
overrides is merged into every run, so the shared recipe and budget are one edit.
`Runner` brings every run of the plan (or of one worker's share) to "done":

1. the dataset is generated once under the data root (`generate --format mcap`, then the
   decode-once caches of train and dev are built), guarded by a lock file; `recipe.json`
   marks it complete;
2. the run is trained in `<results>/<run>/` (`train`, `--resume` from `last.pt` when it
   has one); a run is trained when metrics.jsonl's last "end" reached the budget;
3. `model.pt` is evaluated closed loop on the run's test splits (`evaluate`) and
   `<run>/results.json` gets the splits plus the run's metadata.

Runs that only need evaluating go first, then half-trained ones, then new ones
(`work_order`). Each step is a `gscan-ros` subprocess, so a killed runner loses at most the updates since
the last checkpoint. All state comes from the files: a run's `.lock` (host, runner PID,
child PID) keeps two runners from training it at once and is stale once both processes
are gone; a run whose config.yaml no longer matches the plan is "stale" and left alone
unless `restart_stale`.
"""
from __future__ import annotations

import concurrent.futures
import hashlib
import json
import os
import shutil
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Sequence

from gscan_ros.data.io import DATASET_MANIFEST
from gscan_ros.data.splits import SPLIT_KINDS, TEST_SPLITS
from gscan_ros.errors import GscanError, quoted, shortened
from gscan_ros.model.runtime import mkl_shim_env
from gscan_ros.training.metrics_log import read_events
from gscan_ros.user_files import parse_yaml, read_json, read_yaml

CLI = (sys.executable, "-m", "gscan_ros.cli")
# Config keys that may change without making a run stale: the budget and the machine.
UNTRACKED_KEYS = ("max_updates", "max_minutes", "threads")
# Keys the runner sets itself, never the plan's `defaults:` / `set:`.
RUNNER_KEYS = ("seed", "threads")
STATES = ("done", "evaluate", "running", "resume", "new", "stale")
LOCK = ".lock"
DATASET_DONE = "recipe.json"
GENERATE_LOG = "generate.log"  # a dataset folder's log: the generate (and augment) commands' output
EVAL_SCRATCH = ".evaluation"
# Where a restarted run's earlier attempt is kept (hidden: the report reads only live runs).
REPLACED = ".replaced"
POLL_S = 5.0


class PlanError(GscanError):
    """A plan file that is malformed; the message names the bad key."""


class ExperimentError(GscanError):
    """A run or dataset of a plan that could not be brought to completion."""


# ------------------------------------------------------------------------------ plan
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
        return [] if self.augment is None else ["--method", self.augment, "--seed", str(self.augment_seed)]

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
                "augment_seed")
        return {k: getattr(self, k) for k in keys}


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
    eval_max_examples: int
    eval_batch_size: int
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
                 "cut_off_target_length": int, "path": str, "augment": str, "augment_seed": int}
_RUN_KEYS = ("name", "column", "title", "paper", "config", "data", "seeds", "set", "splits", "max_eval_examples")
_EVAL_KEYS = ("max_examples", "batch_size")


def load_plan(path: str | Path, results: str | Path | None = None, data_root: str | Path | None = None) -> Plan:
    """Parse and check a plan; PlanError (one line, naming the key) on anything wrong.
    Relative paths in the plan are relative to the working directory (the repository
    root). `results` / `data_root` replace the plan's."""
    from gscan_ros.training.paper_figures import COLUMN_TITLES

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
        if paper is not None and paper not in COLUMN_TITLES:
            raise PlanError(f"{where}: {key}.paper must be one of {list(COLUMN_TITLES)}, got {quoted(paper)}")
        title = _text(entry.get("title", COLUMN_TITLES.get(column, column)), where, f"{key}.title")
        kind = datasets[data].split_kind
        splits = entry.get("splits", list(TEST_SPLITS[kind]))
        if not (isinstance(splits, list) and splits and all(s in TEST_SPLITS[kind] for s in splits)):
            raise PlanError(f"{where}: {key}.splits must be a list of {kind} test splits "
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
    return Plan(path=path, results=Path(results), data_root=Path(data_root), eval_max_examples=max_examples,
                eval_batch_size=batch_size, datasets=datasets, runs=runs)


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
        kinds = (int, float) if kinds is float else kinds
        if not isinstance(value, kinds) or isinstance(value, bool):
            raise PlanError(f"{where}: {key}.{field_name} has the wrong type: {quoted(value)}")
        values[field_name] = value
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
    return DataRecipe(name=str(name), examples=None if examples == "full" else examples, **values)


def _augment_keys(values: dict, where: str, key: str) -> None:
    """`augment` names a method of `gscan-ros augment` and applies to generated data only;
    `augment_seed` goes with it."""
    from gscan_ros.data.geca import AUGMENT_METHODS

    method = values.get("augment")
    if method is None:
        if "augment_seed" in values:
            raise PlanError(f"{where}: {key}.augment_seed needs {key}.augment")
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


# ------------------------------------------------------------------------------ locks
def _process_start(pid: int) -> str | None:
    """The process's start time in clock ticks since boot (Linux), to tell a live PID
    from a reused one; None where /proc is unavailable."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return None


def _alive(pid: int | None, started: str | None) -> bool:
    if not pid:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return started is None or _process_start(pid) in (None, started)


class FileLock:
    """An exclusive lock file holding {"host", "pid", "started", "child", "child_started"}.

    Created atomically (a complete file is hard-linked into place), so a reader never sees
    it half written. It is held while the runner or its current child process lives; a lock
    from another host counts as held (its processes cannot be checked from here)."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.held = False

    def holder(self) -> dict | None:
        """The live holder's record, or None when free or stale."""
        try:
            info = json.loads(self.path.read_text())
        except FileNotFoundError:
            return None
        except (OSError, ValueError):
            return {"host": "?", "pid": None, "unreadable": True}
        if info.get("host") != socket.gethostname():
            return info
        live = _alive(info.get("pid"), info.get("started")) or _alive(info.get("child"), info.get("child_started"))
        return info if live else None

    def acquire(self) -> bool:
        """Take the lock (breaking a stale one); False while someone else holds it."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        for _ in range(2):
            tmp = self._write_tmp(None)
            try:
                os.link(tmp, self.path)
                self.held = True
                return True
            except FileExistsError:
                if self.holder() is not None:
                    return False
                self.path.unlink(missing_ok=True)
            finally:
                tmp.unlink()
        return False

    def set_child(self, pid: int | None) -> None:
        """Record the subprocess now working for the holder."""
        os.replace(self._write_tmp(pid), self.path)

    def release(self) -> None:
        if self.held:
            self.path.unlink(missing_ok=True)
            self.held = False

    def _write_tmp(self, child: int | None) -> Path:
        tmp = self.path.with_name(f"{self.path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
        pid = os.getpid()
        tmp.write_text(json.dumps({"host": socket.gethostname(), "pid": pid, "started": _process_start(pid),
                                   "child": child, "child_started": child and _process_start(child)}))
        return tmp


# ------------------------------------------------------------------------------ state
def finished_end(events: list[dict], cfg) -> dict | None:
    """The last "end" event when it closed the training (budget reached, target reached, or
    out of its time budget) and no later start reopened it; else None."""
    for event in reversed(events):
        kind = event.get("event")
        if kind == "start":
            return None
        if kind == "end":
            out_of_time = cfg.max_minutes and event.get("elapsed_s", 0) >= cfg.max_minutes * 60
            return event if event["step"] >= cfg.max_updates or event.get("reached_target") or out_of_time else None
    return None


def trained_updates(events: list[dict]) -> int:
    return max((int(e.get("step", 0)) for e in events), default=0)


@dataclass
class RunState:
    spec: RunSpec
    status: str  # one of STATES
    updates: int  # latest logged update
    max_updates: int
    detail: str = ""


def config_changes(run_dir: Path, cfg, events: list[dict] | None = None) -> list[str]:
    """Keys where the run's config.yaml differs from the plan's config: budget and threads
    aside, model settings compared with their defaults filled in, keys only one side has
    (a field added to TrainConfig since) ignored. Empty for a run without config.yaml.
    `events` are the run's metrics.jsonl records when the caller has read them already."""
    path = run_dir / "config.yaml"
    if not path.is_file():
        return []
    old = read_yaml(path, str(path), ExperimentError) or {}
    new = cfg.to_dict()
    keys = sorted((set(old) & set(new)) - set(UNTRACKED_KEYS) - {"model"})
    changed = [k for k in keys if old[k] != new[k]]
    if events is None:
        events = read_events(run_dir / "metrics.jsonl")
    if "screen_seeds" in changed and _screen_kept(events, new["screen_seeds"]):
        changed.remove("screen_seeds")
    old_model, new_model = _model_settings(old), cfg.model_config().to_dict()
    if old_model is None:
        return changed + ["model"]
    return changed + [f"model.{k}" for k in sorted(set(old_model) & set(new_model)) if old_model[k] != new_model[k]]


def _screen_kept(events: list[dict], screen_seeds: int) -> bool:
    """The run's seed screen passed at a candidate that `screen_seeds` candidates also
    reach, so screening with that many would have kept the same seed (the same run)."""
    passed = [e["candidate"] for e in events if e.get("event") == "screen" and e.get("passed")]
    return bool(passed) and passed[0] < max(screen_seeds, 1)


def _model_settings(config: dict) -> dict | None:
    """Every model setting of a saved config.yaml (None if they no longer load)."""
    from gscan_ros.training.config import TrainConfig

    try:
        train = TrainConfig(model_kind=config.get("model_kind", "compositional"), model=dict(config.get("model") or {}))
        return train.model_config().to_dict()
    except GscanError:
        return None


def run_state(run_dir: Path, spec: RunSpec, cfg, plan: Plan, ignore_lock: bool = False) -> RunState:
    """Where a run stands, from its files alone."""
    events = read_events(run_dir / "metrics.jsonl")
    state = RunState(spec, "new", trained_updates(events), cfg.max_updates)
    holder = None if ignore_lock else FileLock(run_dir / LOCK).holder()
    if holder is not None:
        state.status, state.detail = "running", _holder_text(holder, run_dir / LOCK)
        return state
    changed = config_changes(run_dir, cfg, events)
    end = finished_end(events, cfg)
    if changed:
        state.status, state.detail = "stale", f"config changed: {', '.join(changed)}"
    elif end is not None and _evaluated(run_dir, spec, end):
        state.status = "done"
    elif end is not None:
        state.status = "evaluate"
    elif (run_dir / "last.pt").exists():
        state.status = "resume"
    elif state.updates:
        state.detail = f"no last.pt: starts over, these logged updates kept in {REPLACED}/"
    return state


def archive_attempt(run_dir: Path) -> Path | None:
    """Move an earlier attempt's files (a start whose checkpoints were lost, or a stale run
    being restarted) into `<run>/.replaced/<UTC time>_<updates>upd/`, so a restart loses no
    logged curve or result; None when there is nothing to move."""
    from gscan_ros.training.trainer import RunFiles

    files = RunFiles(run_dir).existing() + [p for p in (run_dir / "results.json", run_dir / "train.log",
                                                         run_dir / "evaluate.log") if p.exists()]
    if not files:
        return None
    updates = trained_updates(read_events(run_dir / "metrics.jsonl"))
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    archive = run_dir / REPLACED / f"{stamp}_{updates}upd"
    suffix = 1
    while archive.exists():
        suffix += 1
        archive = run_dir / REPLACED / f"{stamp}_{updates}upd_{suffix}"
    archive.mkdir(parents=True)
    for path in files:
        path.rename(archive / path.name)
    return archive


def _evaluated(run_dir: Path, spec: RunSpec, end: dict) -> bool:
    try:
        doc = read_json(run_dir / "results.json", f"{run_dir}/results.json", ExperimentError)
    except ExperimentError:
        return False
    ev = doc.get("evaluation") or {}
    return (doc.get("updates") == end["step"] and ev.get("splits") == list(spec.splits)
            and ev.get("max_examples") == spec.eval_max_examples)


def work_order(states: list[RunState]) -> list[RunState]:
    """Cheapest finish first: runs that only need evaluating, then half-trained ones, then
    new ones (plan order within each), so a stop costs the least unfinished work and a
    trained run's results never wait behind a whole training."""
    rank = {"evaluate": 0, "resume": 1, "stale": 1, "new": 2}
    return sorted(states, key=lambda st: rank.get(st.status, 0))


def dataset_state(recipe: DataRecipe, data_root: Path) -> str:
    directory = recipe.directory(data_root)
    if recipe.path is not None:
        return "given" if directory.exists() else "missing (path)"
    if (directory / DATASET_DONE).exists():
        return "ready"
    holder = FileLock(directory / LOCK).holder()
    return f"generating ({_holder_text(holder, directory / LOCK)})" if holder else "to generate"


def augment_base(directory: Path) -> Path:
    """The scratch folder beside an `augment` recipe's dataset folder that holds the
    generated dataset it augments, until the augmented one is complete."""
    return directory.with_name(f".{directory.name}.base")


def _holder_text(holder: dict, path: Path) -> str:
    if holder.get("unreadable"):
        return f"{path} is unreadable; delete it if no runner works here"
    return f"pid {holder.get('pid')} on {holder.get('host')}"


# ------------------------------------------------------------------------------ runner
@dataclass
class Outcome:
    done: list[str] = field(default_factory=list)
    failed: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)  # running elsewhere or stale


class Interrupted(Exception):
    """The runner was told to stop while a step was running."""


class Runner:
    """Brings a plan's runs (one worker's share) to "done", `parallel` at a time, each
    subprocess with `threads` torch threads."""

    def __init__(self, plan: Plan, *, parallel: int = 1, threads: int = 1, worker: tuple[int, int] | None = None,
                 only: tuple[str, ...] = (), restart_stale: bool = False, progress: bool = True,
                 echo: Callable[[str], None] = print):
        self.plan = plan
        self.parallel = parallel
        self.threads = threads
        self.restart_stale = restart_stale
        self.progress = progress
        self.echo = echo
        self.share = plan.share(worker, only)
        self.configs = {spec.name: resolve_config(plan, spec, threads) for spec in self.share}
        self._stop = threading.Event()
        self._children: set[subprocess.Popen] = set()
        self._guard = threading.Lock()
        self._dataset_guards: dict[Path, threading.Lock] = {}

    def run_dir(self, spec: RunSpec) -> Path:
        return self.plan.results / spec.name

    def states(self) -> list[RunState]:
        return [run_state(self.run_dir(s), s, self.configs[s.name], self.plan) for s in self.share]

    def status_lines(self, states: list[RunState]) -> list[str]:
        """A summary line, the datasets, and one line per run."""
        counts = {s: sum(st.status == s for st in states) for s in STATES}
        left = len(states) - counts["done"] - counts["running"]
        lines = [f"{len(states)} runs: {counts['done']} done, {counts['running']} running, {left} left "
                 f"({', '.join(f'{counts[s]} {s}' for s in ('evaluate', 'resume', 'new', 'stale') if counts[s])})"]
        recipes = {s.data.name: s.data for s in self.share}
        names = max(map(len, recipes), default=0)
        for name, recipe in recipes.items():
            lines.append(f"  data {name:{names}s} {dataset_state(recipe, self.plan.data_root):24s} "
                         f"{recipe.directory(self.plan.data_root)}")
        width = max(len(st.spec.name) for st in states)
        for st in states:
            lines.append(f"  {st.status:8s} {st.spec.name:{width}s} {st.updates:>7d}/{st.max_updates:<7d} {st.detail}"
                         .rstrip())
        return lines

    # ---------------------------------------------------------------- the loop
    def run(self) -> Outcome:
        """Work through the share until every run is done, failed or busy elsewhere.
        KeyboardInterrupt (Ctrl-C, or SIGTERM turned into one) stops the children and
        releases the locks; the next call resumes."""
        from tqdm import tqdm

        states = self.states()
        for line in self.status_lines(states):
            self.echo(line)
        outcome = Outcome(done=[st.spec.name for st in states if st.status == "done"])
        todo = []
        for st in work_order(states):
            if st.status == "running" or (st.status == "stale" and not self.restart_stale):
                outcome.skipped.append(st.spec.name)
            elif st.status != "done":
                todo.append(st.spec)
        bar = tqdm(total=sum(st.max_updates for st in states), initial=self._updates(), unit="upd", desc="plan",
                   disable=not self.progress, dynamic_ncols=True)
        pool = concurrent.futures.ThreadPoolExecutor(max_workers=self.parallel)
        futures = {pool.submit(self._execute, spec): spec for spec in todo}
        pending = set(futures)
        try:
            while pending:
                finished, pending = concurrent.futures.wait(pending, timeout=POLL_S)
                for future in finished:
                    spec, error = futures[future], future.exception()
                    if error is not None:
                        outcome.failed.append(spec.name)
                        bar.write(f"FAILED {spec.name}: {error}")
                    else:
                        (outcome.done if future.result() else outcome.skipped).append(spec.name)
                bar.update(max(self._updates() - bar.n, 0))
                running = sum(1 for f in pending if f.running())
                bar.set_postfix_str(f"done {len(outcome.done)}, running {running}, left {len(pending) - running}")
        except KeyboardInterrupt:
            self._stop.set()
            self._terminate_children()
            pool.shutdown(wait=True, cancel_futures=True)
            bar.close()
            raise
        pool.shutdown(wait=True)
        bar.close()
        return outcome

    def _updates(self) -> int:
        """Updates trained so far over the share (each run counted up to its budget)."""
        return sum(min(trained_updates(read_events(self.run_dir(s) / "metrics.jsonl")),
                       self.configs[s.name].max_updates) for s in self.share)

    def _execute(self, spec: RunSpec) -> bool:
        """Train and evaluate one run under its lock; False when another runner holds it."""
        if self._stop.is_set():
            raise Interrupted("stopped")
        run_dir = self.run_dir(spec)
        lock = FileLock(run_dir / LOCK)
        if not lock.acquire():
            return False
        try:
            cfg = self.configs[spec.name]
            state = run_state(run_dir, spec, cfg, self.plan, ignore_lock=True)
            if state.status == "done":
                return True
            data_dir = self._dataset(spec.data)
            if state.status in ("new", "resume", "stale"):
                self.echo(f"train {spec.name} ({state.status}, {state.updates}/{cfg.max_updates} updates)")
                self._train(spec, run_dir, data_dir, lock, resume=state.status == "resume")
            self.echo(f"evaluate {spec.name} on {', '.join(spec.splits)}")
            self._evaluate(spec, cfg, run_dir, data_dir, lock)
            self.echo(f"done {spec.name}")
            return True
        finally:
            lock.release()

    def _train(self, spec: RunSpec, run_dir: Path, data_dir: Path, lock: FileLock, resume: bool) -> None:
        cmd = [*CLI, "train", "--config", str(spec.config), "--data", str(data_dir), "--out", str(run_dir), "--quiet"]
        for item in spec.train_overrides(self.threads):
            cmd += ["--set", item]
        if resume:
            cmd.append("--resume")
        else:
            archive = archive_attempt(run_dir)
            if archive is not None:
                self.echo(f"{spec.name}: the earlier attempt's files moved to {archive}")
        self._call(cmd, run_dir / "train.log", lock)

    def _evaluate(self, spec: RunSpec, cfg, run_dir: Path, data_dir: Path, lock: FileLock) -> None:
        scratch = run_dir / EVAL_SCRATCH
        cmd = [*CLI, "evaluate", "--checkpoint", str(run_dir / "model.pt"), "--data", str(data_dir),
               "--splits", *spec.splits, "--out", str(scratch), "--threads", str(self.threads), "--quiet",
               "--overwrite", "--no-predictions", "--batch-size", str(self.plan.eval_batch_size),
               "--max-examples", str(spec.eval_max_examples)]
        self._call(cmd, run_dir / "evaluate.log", lock)
        evaluation = read_json(scratch / "results.json", f"{scratch}/results.json", ExperimentError)
        end = finished_end(read_events(run_dir / "metrics.jsonl"), cfg)
        if end is None:
            raise ExperimentError(f"{run_dir}/metrics.jsonl has no final 'end' event after training")
        doc = {
            "run": spec.name, "column": spec.column, "title": spec.title, "paper_column": spec.paper_column,
            "seed": spec.seed, "updates": end["step"], "max_updates": cfg.max_updates,
            "reached_target": bool(end.get("reached_target")), "best_dev_exact_match": end.get("best_dev_exact_match"),
            "train_seconds": round(float(end.get("elapsed_s", 0.0)), 1), "model_kind": cfg.model_kind,
            "parser": cfg.parser, "max_train_target_length": cfg.max_train_target_length,
            "config": str(spec.config), "overrides": list(spec.overrides),
            "data": {**spec.data.record(), "dir": str(data_dir)},
            "evaluation": {"splits": list(spec.splits), "max_examples": spec.eval_max_examples,
                           "episodes": evaluation.get("episodes"), "seconds": evaluation.get("seconds")},
            "splits": evaluation["splits"],
        }
        tmp = run_dir / "results.json.tmp"
        tmp.write_text(json.dumps(doc, indent=2) + "\n")
        os.replace(tmp, run_dir / "results.json")
        shutil.rmtree(scratch)

    def _dataset(self, recipe: DataRecipe) -> Path:
        """The recipe's dataset directory, generated first if needed (once across threads
        and runners: a lock file, then recipe.json marks it complete)."""
        directory = recipe.directory(self.plan.data_root)
        if recipe.path is not None:
            if not directory.exists():
                raise ExperimentError(f"dataset {recipe.name}: path {directory} does not exist")
            return directory
        with self._guard:
            guard = self._dataset_guards.setdefault(directory, threading.Lock())
        with guard:
            lock = FileLock(directory / LOCK)
            waiting = False
            while not (directory / DATASET_DONE).exists():
                if lock.acquire():
                    try:
                        self._generate(recipe, directory, lock)
                    finally:
                        lock.release()
                    break
                if not waiting:
                    self.echo(f"waiting for dataset {recipe.name}: {dataset_state(recipe, self.plan.data_root)}")
                    waiting = True
                if self._stop.wait(POLL_S):
                    raise Interrupted("stopped")
        return directory

    def _generate(self, recipe: DataRecipe, directory: Path, lock: FileLock) -> None:
        """Generate the recipe's dataset into `directory`, recipe.json last. An `augment`
        recipe generates its base into a scratch folder beside `directory` (`augment_base`)
        and augments that into `directory`/dataset.txt; after an interruption a base that
        generate finished (its manifest is written last) is augmented as it is, a half-built
        one is generated again."""
        if (directory / DATASET_DONE).exists():
            return
        log = directory / GENERATE_LOG
        ours = {LOCK, GENERATE_LOG}
        leftovers = [p for p in directory.iterdir() if p.name not in ours and not p.name.endswith(".tmp")]
        if leftovers and not log.exists():
            raise ExperimentError(f"dataset folder {directory} holds files the runner did not write "
                                  f"({', '.join(sorted(p.name for p in leftovers)[:3])}); move them away or "
                                  f"give the dataset as `path:` in the plan")
        for scratch in directory.glob(".gscan_generate_*"):  # scratch of a generate of an older version, killed
            shutil.rmtree(scratch)
        augmented = f", then augment {' '.join(recipe.augment_flags())}" if recipe.augment else ""
        self.echo(f"generate dataset {recipe.name} into {directory} ({' '.join(recipe.flags())}{augmented})")
        overwrite = bool(leftovers)  # an interrupted generation of ours (generate.log is ours): replaced
        if recipe.augment is None:
            self._call(self._generate_command(recipe, directory, overwrite), log, lock)
            warm = ("import sys\nfrom gscan_ros.training.trainer import split_cache\n"
                    "for split in sys.argv[2:]:\n    split_cache(sys.argv[1], split)\n")
            self._call([sys.executable, "-c", warm, str(directory), "train", "dev"], log, lock, "decode-once caches")
        else:
            base = augment_base(directory)
            if not (base / DATASET_MANIFEST).is_file():
                self._call(self._generate_command(recipe, base, overwrite=base.exists()), log, lock)
            cmd = [*CLI, "augment", "--data", str(base), "--out", str(directory), *recipe.augment_flags(), "--quiet"]
            if overwrite:
                cmd.append("--overwrite")
            self._call(cmd, log, lock)
            shutil.rmtree(base)
        (directory / DATASET_DONE).write_text(json.dumps({**recipe.record(), "flags": recipe.flags()}, indent=2) + "\n")

    def _generate_command(self, recipe: DataRecipe, out: Path, overwrite: bool) -> list[str]:
        workers = max(1, min(self.parallel * self.threads, len(os.sched_getaffinity(0))))
        cmd = [*CLI, "generate", "--out", str(out), *recipe.flags(), "--workers", str(workers), "--quiet"]
        return cmd + ["--overwrite"] if overwrite else cmd

    def _call(self, cmd: list[str], log: Path, lock: FileLock, what: str = "") -> None:
        """Run one step (a `gscan-ros` subcommand unless `what` says otherwise), output
        appended to `log`; the lock names the child while it runs."""
        if self._stop.is_set():
            raise Interrupted("stopped")
        shown = what or f"gscan-ros {' '.join(cmd[len(CLI):])}"
        what = what or f"gscan-ros {cmd[len(CLI)]}"
        log.parent.mkdir(parents=True, exist_ok=True)
        with open(log, "a") as out:
            out.write(f"# {time.strftime('%Y-%m-%d %H:%M:%S')} {shown}\n")
            out.flush()
            proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                    env=mkl_shim_env())
            with self._guard:
                self._children.add(proc)
                if self._stop.is_set():  # stopped while it started: _terminate_children has its list already
                    proc.terminate()
            try:
                lock.set_child(proc.pid)
                code = proc.wait()
            finally:
                with self._guard:
                    self._children.discard(proc)
        if self._stop.is_set():
            raise Interrupted("stopped")
        if code != 0:
            raise ExperimentError(f"{what} exited with {code}: {_last_line(log)} (log: {log})")

    def _terminate_children(self) -> None:
        with self._guard:
            children = list(self._children)
        for proc in children:
            proc.terminate()
        for proc in children:
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()


def _last_line(log: Path) -> str:
    lines = [line for line in log.read_text(errors="replace").splitlines() if line.strip()]
    return lines[-1].strip() if lines else "(no output)"
