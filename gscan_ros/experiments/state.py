"""Where each run of a plan stands, from its files alone: its lock, metrics.jsonl,
config.yaml, last.pt and results.json (`STATES`), and the order the runner works in.

A run whose config.yaml no longer matches the plan is "stale"; the budget and the
machine (`UNTRACKED_KEYS`) may change without that.
"""
from __future__ import annotations

import statistics
import time
from dataclasses import dataclass
from pathlib import Path

from gscan_ros.errors import GscanError
from gscan_ros.experiments.locks import FileLock
from gscan_ros.experiments.plan import DataRecipe, RunSpec
from gscan_ros.training.metrics_log import read_events
from gscan_ros.user_files import read_json, read_yaml

# Config keys that may change without making a run stale: the budget and the machine.
UNTRACKED_KEYS = ("max_updates", "max_minutes", "threads")
STATES = ("done", "evaluate", "running", "resume", "new", "stale")
LOCK = ".lock"
DATASET_DONE = "recipe.json"
# Where a restarted run's earlier attempt is kept (hidden: the report reads only live runs).
REPLACED = ".replaced"


class ExperimentError(GscanError):
    """A run or dataset of a plan that could not be brought to completion."""


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
    seconds_per_update: float | None = None  # median of the run's logged training windows


def seconds_per_update(events: list[dict], batch_size: int) -> float | None:
    """A run's training time per update: the median over its logged windows of batch size
    / examples per second (validation, checkpoints and evaluation not counted); None
    before its first window. Older logs lack `mean_batch`: the config's batch then."""
    times = [e.get("mean_batch", batch_size) / e["examples_per_s"] for e in events
             if e.get("event") == "train" and e.get("examples_per_s")]
    return statistics.median(times) if times else None


def training_left(states: list[RunState]) -> tuple[float, list[str]]:
    """Seconds of training the unfinished runs still need, one thread each, and the names of
    those with no rate to go by. A run's rate is its own logged one, else the median of its
    entry's runs, else of the runs with its config file on its kind of data (a 12x12
    length split trains slower than 6x6). Rates depend on the machine and its load: an
    estimate, not a promise. A stale run counts from zero, as `--restart-stale` retrains it."""
    by_entry: dict[str, list[float]] = {}
    by_recipe: dict[tuple, list[float]] = {}
    for st in states:
        if st.seconds_per_update is not None:
            by_entry.setdefault(st.spec.entry, []).append(st.seconds_per_update)
            by_recipe.setdefault((st.spec.config, st.spec.data.split_kind), []).append(st.seconds_per_update)
    seconds, unknown = 0.0, []
    for st in states:
        if st.status in ("done", "evaluate"):
            continue
        rates = ([st.seconds_per_update] if st.seconds_per_update is not None
                 else by_entry.get(st.spec.entry) or by_recipe.get((st.spec.config, st.spec.data.split_kind)))
        if not rates:
            unknown.append(st.spec.name)
            continue
        updates = st.max_updates - (0 if st.status == "stale" else min(st.updates, st.max_updates))
        seconds += updates * statistics.median(rates)
    return seconds, unknown


def config_changes(run_dir: Path, cfg, events: list[dict] | None = None) -> list[str]:
    """Keys where the run's config.yaml differs from the plan's config: budget and threads
    aside, model settings compared with their defaults filled in. A field added to
    TrainConfig since the run started counts as its default there (the behaviour the run
    had); keys TrainConfig no longer has are ignored. Empty for a run without config.yaml.
    `events` are the run's metrics.jsonl records when the caller has read them already."""
    path = run_dir / "config.yaml"
    if not path.is_file():
        return []
    old = read_yaml(path, str(path), ExperimentError) or {}
    new = cfg.to_dict()
    defaults = type(cfg)().to_dict()
    keys = sorted(set(new) - set(UNTRACKED_KEYS) - {"model"})
    changed = [k for k in keys if old.get(k, defaults[k]) != new[k]]
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


def run_state(run_dir: Path, spec: RunSpec, cfg, ignore_lock: bool = False) -> RunState:
    """Where a run stands, from its files alone."""
    events = read_events(run_dir / "metrics.jsonl")
    state = RunState(spec, "new", trained_updates(events), cfg.max_updates,
                     seconds_per_update=seconds_per_update(events, cfg.batch_size))
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


def _holder_text(holder: dict, path: Path) -> str:
    if holder.get("unreadable"):
        return f"{path} is unreadable; delete it if no runner works here"
    return f"pid {holder.get('pid')} on {holder.get('host')}"

