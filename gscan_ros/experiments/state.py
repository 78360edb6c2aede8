"""Where each run of a plan stands, from its files alone: its lock, metrics.jsonl,
config.yaml, its checkpoints and results.json (`STATES`), and the order the runner works in.

A run whose config.yaml no longer matches the plan (`training.config.config_changes`: the
budget and the machine may change), that trained or was evaluated on another dataset
folder than the plan's, or that finished without its weights (model.pt) is "stale". A
stale run is retrained (`--restart-stale`) in `<run>/.retrain/`, beside its old files,
which stay in place (and in the report) until the retrained run is evaluated; then
`promote_retrain` moves them to `.replaced/` and the retrained files into `<run>/`.
"""
from __future__ import annotations

import os
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

from gscan_ros.errors import GscanError
from gscan_ros.experiments.locks import FileLock
from gscan_ros.experiments.plan import DataRecipe, RunSpec
from gscan_ros.training.metrics_log import finished_end, read_events
from gscan_ros.user_files import file_sha256, read_json, read_yaml

STATES = ("done", "evaluate", "running", "resume", "new", "stale")
LOCK = ".lock"
DATASET_DONE = "recipe.json"
# Where a restarted run's earlier attempt is kept (hidden: the report reads only live runs).
REPLACED = ".replaced"
# Where a stale run is retrained, beside the files it replaces once evaluated (hidden too).
RETRAIN = ".retrain"
# Marks a retrained run whose files are being moved into place (`promote_retrain`).
PROMOTING = ".promoting"


class ExperimentError(GscanError):
    """A run or dataset of a plan that could not be brought to completion."""


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
    retrain: bool = False  # trains and evaluates in <run>/.retrain/ (a stale run's retrain)
    promote: bool = False  # a retrain trained and evaluated: only its move into <run>/ is left


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
    """Keys where the run's config.yaml differs from the plan's config
    (`training.config.config_changes`); empty for a run without config.yaml. `events` are
    the run's metrics.jsonl records when the caller has read them already."""
    from gscan_ros.training.config import config_changes as saved_config_changes

    path = run_dir / "config.yaml"
    if not path.is_file():
        return []
    saved = read_yaml(path, str(path), ExperimentError) or {}
    if events is None:
        events = read_events(run_dir / "metrics.jsonl")
    return saved_config_changes(saved, cfg, events)


def data_change(data_dir: Path, events: list[dict], results: dict | None) -> str | None:
    """How the dataset folders the run trained on (its metrics.jsonl `start` records) and
    was evaluated on (results.json) differ from the plan's `data_dir`, compared by folder
    name (`<dataset>-<hash of its flags>`, whatever the data root); None when they do not,
    or when the run's files do not name one (runs from before the `start` records did)."""
    used = [e["data"] for e in events if e.get("event") == "start" and e.get("data")]
    used += [((results or {}).get("data") or {}).get("dir")]
    others = sorted({Path(d).name for d in used if d} - {data_dir.name})
    return f"data changed: {', '.join(others)} -> {data_dir.name}" if others else None


def run_state(run_dir: Path, spec: RunSpec, cfg, data_root: Path, ignore_lock: bool = False) -> RunState:
    """Where a run stands, from its files alone; `data_root` holds the plan's datasets. A
    retrain under way in `<run>/.retrain/` is the run's state (the old files wait there)."""
    holder = None if ignore_lock else FileLock(run_dir / LOCK).holder()
    if holder is not None:
        work = work_dir(run_dir)
        events = read_events(work / "metrics.jsonl")
        return RunState(spec, "running", trained_updates(events), cfg.max_updates,
                        _holder_text(holder, run_dir / LOCK), seconds_per_update(events, cfg.batch_size),
                        retrain=work != run_dir)
    staging = run_dir / RETRAIN
    if not staging.is_dir():
        return _files_state(run_dir, spec, cfg, data_root)
    state = _files_state(staging, spec, cfg, data_root)
    state.retrain = True
    if (run_dir / PROMOTING).exists() or state.status == "done":
        state.status, state.promote = "evaluate", True
        state.detail = f"retrained in {RETRAIN}/: its files move in place of the stale run's"
    elif state.status == "stale":
        state.detail = f"the retrain in {RETRAIN}/ is stale too: {state.detail}"
    else:
        state.detail = (f"retrain in {RETRAIN}/" + (" starts over" if state.status == "new" else "")
                        + "; the stale run's results stay until it is evaluated")
    return state


def work_dir(run_dir: Path) -> Path:
    """The folder the run trains in: `<run>/.retrain/` while a retrain is under way."""
    staging = run_dir / RETRAIN
    return staging if staging.is_dir() else run_dir


def _files_state(run_dir: Path, spec: RunSpec, cfg, data_root: Path) -> RunState:
    from gscan_ros.training.trainer import RunFiles

    events = read_events(run_dir / "metrics.jsonl")
    state = RunState(spec, "new", trained_updates(events), cfg.max_updates,
                     seconds_per_update=seconds_per_update(events, cfg.batch_size))
    results = _results(run_dir)
    reasons = plan_changes(run_dir, spec, cfg, data_root, events, results)
    end = finished_end(events, cfg)
    model = RunFiles(run_dir).model
    if reasons:
        state.status, state.detail = "stale", "; ".join(reasons)
    elif end is not None and not model.is_file():  # trained, but its numbers could not be (re-)checked
        state.status = "stale"
        state.detail = no_weights(evaluated=bool(results))
    elif end is not None and _evaluated(results, spec, end, model):
        state.status = "done"
    elif end is not None:
        state.status = "evaluate"
    elif RunFiles(run_dir).resume_point() is not None:
        state.status = "resume"
    elif model.is_file() or any(e.get("event") == "end" for e in events):
        # Finished to a smaller budget, its training state not kept (committed runs keep only
        # model.pt): starting it over would replace its results, so only --restart-stale does.
        state.status = "stale"
        state.detail = (f"trained to {state.updates} of {cfg.max_updates} updates, without the training state "
                        f"(last.pt) to go on from")
    elif state.updates:
        state.detail = f"no last.pt: starts over, these logged updates kept in {REPLACED}/"
    return state


def no_weights(evaluated: bool = True) -> str:
    """Why a trained run without its model.pt is retrained."""
    return f"no weights (model.pt) to {'re-check its results' if evaluated else 'evaluate'}"


def plan_changes(run_dir: Path, spec: RunSpec, cfg, data_root: Path, events: list[dict] | None = None,
                 results: dict | None = None) -> list[str]:
    """What the run trained with that the plan no longer asks for: its config, its data
    (empty: neither changed). `events`/`results`: its metrics.jsonl records and results.json,
    when the caller has read them."""
    if events is None:
        events = read_events(run_dir / "metrics.jsonl")
    if results is None:
        results = _results(run_dir)
    changed = config_changes(run_dir, cfg, events)
    reasons = [f"config changed: {', '.join(changed)}"] if changed else []
    data = data_change(spec.data.directory(data_root), events, results)
    return reasons + ([data] if data is not None else [])


def archive_attempt(run_dir: Path, into: Path | None = None) -> Path | None:
    """Move an earlier attempt's files (a start whose checkpoints were lost, a stale run
    replaced by its retrain, or a retrain that went stale) into
    `<into>/.replaced/<UTC time>_<updates>upd/` (`into`: the run folder, default `run_dir`),
    so a restart loses no logged curve or result; None when there is nothing to move.
    Every file that is not hidden goes, the analyses written beside the run too (their
    numbers are of the old weights)."""
    files = sorted(p for p in run_dir.iterdir() if not p.name.startswith(".") and p.is_file()) \
        if run_dir.is_dir() else []
    if not files:
        return None
    updates = trained_updates(read_events(run_dir / "metrics.jsonl"))
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    into = into or run_dir
    archive = into / REPLACED / f"{stamp}_{updates}upd"
    suffix = 1
    while archive.exists():
        suffix += 1
        archive = into / REPLACED / f"{stamp}_{updates}upd_{suffix}"
    archive.mkdir(parents=True)
    for path in files:
        path.rename(archive / path.name)
    return archive


def promote_retrain(run_dir: Path) -> Path | None:
    """Put a finished retrain in place of the stale run: the old files go to `.replaced/`
    (`archive_attempt`), then every file of `<run>/.retrain/` moves into `<run>/`. The
    `.promoting` marker, written once the old files are out, lets a move cut short finish
    on the next call without archiving the retrained files it already moved. Returns the
    archive of the old files (None when there were none, or on a call that finishes)."""
    staging, marker = run_dir / RETRAIN, run_dir / PROMOTING
    archive = None
    if not marker.exists():
        archive = archive_attempt(run_dir)
        marker.write_text(f"{archive or ''}\n")
    if staging.is_dir():
        for path in sorted(staging.iterdir()):
            os.replace(path, run_dir / path.name)
        staging.rmdir()
    marker.unlink()
    return archive


def _results(run_dir: Path) -> dict | None:
    """The run's results.json; None when it has none (or none that reads)."""
    try:
        doc = read_json(run_dir / "results.json", f"{run_dir}/results.json", ExperimentError)
    except ExperimentError:
        return None
    return doc if isinstance(doc, dict) else None


def _evaluated(results: dict | None, spec: RunSpec, end: dict, model: Path) -> bool:
    """Whether `results` are of this training's end on the plan's splits and example cap,
    and of these weights where the results name them (results written before the runner
    recorded `checkpoint_sha256` do not): a run retrained by hand is evaluated again."""
    if results is None:
        return False
    ev = results.get("evaluation") or {}
    sha = ev.get("checkpoint_sha256")
    return (results.get("updates") == end["step"] and sorted(ev.get("splits") or ()) == sorted(spec.splits)
            and ev.get("max_examples") == spec.eval_max_examples
            and (sha is None or sha == file_sha256(model)))


def work_order(states: list[RunState]) -> list[RunState]:
    """Cheapest finish first: runs that only need evaluating, then half-trained ones, then
    new and stale ones, which both train from update 0 (plan order within each), so a stop
    costs the least unfinished work and a trained run's results never wait behind a whole
    training."""
    rank = {"evaluate": 0, "resume": 1, "stale": 2, "new": 2}
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

