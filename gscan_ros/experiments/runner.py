"""`Runner`: brings every run of a plan (or of one worker's share) to "done", restartably.

1. the dataset is generated once under the data root (`generate --format mcap`, then the
   decode-once caches of train and dev are built), guarded by a lock file; `recipe.json`
   marks it complete;
2. the run is trained in `<results>/<run>/` (`train`, `--resume` from `last.pt`, or the
   `last.prev.pt` before it, when it has one); a run is trained when metrics.jsonl's last
   "end" reached the budget;
3. `model.pt` is evaluated closed loop on the run's test splits (`evaluate`) and
   `<run>/results.json` gets the splits plus the run's metadata (an evaluation of the
   same weights finished before a stop is kept, `finished_evaluation`).

Runs that only need evaluating go first, then half-trained ones, then new ones
(`state.work_order`). Each step is a `gscan-ros` subprocess, so a killed runner loses at most the updates since
the last checkpoint. All state comes from the files: a run's `.lock` (an flock, and the
host, runner PID and child PID) keeps two runners from training it at once and is free
once both processes are gone; a run whose config.yaml no longer matches the plan, or
that trained on another dataset folder, is "stale" and left alone unless `restart_stale`;
then it is retrained in `<run>/.retrain/`, its old results kept (and reported) until the
retrain is evaluated and moved into place (`state.promote_retrain`). A retrain under way
resumes like any run.
"""
from __future__ import annotations

import concurrent.futures
import json
import os
import shutil
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from gscan_ros.data.io import DATASET_MANIFEST
from gscan_ros.experiments.locks import FileLock
from gscan_ros.experiments.plan import DataRecipe, Plan, RunSpec, resolve_config
from gscan_ros.experiments.state import (
    DATASET_DONE,
    LOCK,
    PROMOTING,
    RETRAIN,
    STATES,
    ExperimentError,
    RunState,
    archive_attempt,
    dataset_state,
    promote_retrain,
    run_state,
    trained_updates,
    training_left,
    work_dir,
    work_order,
)
from gscan_ros.outputs import replace_durably
from gscan_ros.runtime import mkl_shim_env
from gscan_ros.training.metrics_log import finished_end, read_events
from gscan_ros.user_files import file_sha256, read_json

CLI = (sys.executable, "-m", "gscan_ros.cli")
GENERATE_LOG = "generate.log"  # a dataset folder's log: the generate (and augment) commands' output
EVAL_SCRATCH = ".evaluation"
POLL_S = 5.0


def finished_evaluation(scratch: Path, model: Path, data_dir: Path, spec: RunSpec) -> dict | None:
    """The results an `evaluate` left in `scratch` when they score these very weights
    (`checkpoint_sha256`) on the run's splits, data and example cap: a runner stopped after
    the evaluation but before it wrote results.json need not decode it all again."""
    if not (scratch / "results.json").is_file():
        return None
    try:
        evaluation = read_json(scratch / "results.json", f"{scratch}/results.json", ExperimentError)
        same = (evaluation.get("checkpoint_sha256") == file_sha256(model)
                and evaluation.get("data") == str(data_dir)
                and evaluation.get("max_examples") == spec.eval_max_examples
                and sorted(evaluation["splits"]) == sorted(spec.splits))
    except (ExperimentError, OSError, TypeError, KeyError, AttributeError):  # unreadable or not ours: decode again
        return None
    return evaluation if same else None


def augment_base(directory: Path) -> Path:
    """The scratch folder beside an `augment` recipe's dataset folder that holds the
    generated dataset it augments, until the augmented one is complete."""
    return directory.with_name(f".{directory.name}.base")


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
        return [run_state(self.run_dir(s), s, self.configs[s.name], self.plan.data_root) for s in self.share]

    def status_lines(self, states: list[RunState]) -> list[str]:
        """A summary line, the datasets, and one line per run."""
        counts = {s: sum(st.status == s for st in states) for s in STATES}
        left = len(states) - counts["done"] - counts["running"]
        lines = [f"{len(states)} runs: {counts['done']} done, {counts['running']} running, {left} left "
                 f"({', '.join(f'{counts[s]} {s}' for s in ('evaluate', 'resume', 'new', 'stale') if counts[s])})"]
        seconds, unknown = training_left(states)
        if seconds or unknown:
            no_rate = f"; no rate yet for {len(unknown)}: {' '.join(unknown)}" if unknown else ""
            lines.append(f"  training left: ~{seconds / 3600:.0f} core-hours at the rates these runs logged, "
                         f"one thread each{no_rate}")
        recipes = {s.data.name: s.data for s in self.share}
        names = max(map(len, recipes), default=0)
        for name, recipe in recipes.items():
            lines.append(f"  data {name:{names}s} {dataset_state(recipe, self.plan.data_root):24s} "
                         f"{recipe.directory(self.plan.data_root)}")
        width = max((len(st.spec.name) for st in states), default=0)
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
        for st in states:
            if st.status == "done":
                self._relabel(st.spec)
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

    def _relabel(self, spec: RunSpec) -> None:
        """A done run's labels follow the plan (`column`, `title`, `paper`): the report reads
        them from results.json, and an entry renamed in the plan needs no retraining."""
        run_dir = self.run_dir(spec)
        path = run_dir / "results.json"
        want = {"column": spec.column, "title": spec.title, "paper_column": spec.paper_column}
        doc = read_json(path, str(path), ExperimentError)
        if all(doc.get(key) == value for key, value in want.items()):
            return
        lock = FileLock(run_dir / LOCK)
        if not lock.acquire():
            return
        try:
            tmp = run_dir / "results.json.tmp"
            tmp.write_text(json.dumps({**doc, **want}, indent=2) + "\n")
            replace_durably(tmp, path)
        finally:
            lock.release()
        self.echo(f"{spec.name}: labels set from the plan (column {spec.column!r}, title {spec.title!r})")

    def _updates(self) -> int:
        """Updates trained so far over the share (each run counted up to its budget)."""
        return sum(min(trained_updates(read_events(work_dir(self.run_dir(s)) / "metrics.jsonl")),
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
            state = run_state(run_dir, spec, cfg, self.plan.data_root, ignore_lock=True)
            if state.status == "done":
                return True
            if state.status == "stale" and not self.restart_stale:  # it went stale while queued (another runner)
                return False
            data_dir = self._dataset(spec.data)
            work = run_dir / RETRAIN if state.retrain or state.status == "stale" else run_dir
            if state.status == "stale":  # a new retrain: a marker a finished promotion left is no promotion
                (run_dir / PROMOTING).unlink(missing_ok=True)
            if state.status in ("new", "resume", "stale"):
                where = f", in {RETRAIN}/" if work != run_dir else ""
                start = (f"from its last checkpoint, updates logged to {state.updates}"  # last.pt may be older
                         if state.status == "resume" else "from update 0")  # new and stale runs start over
                self.echo(f"train {spec.name} ({state.status}{where}, {start} of {cfg.max_updates})")
                self._train(spec, work, data_dir, lock, resume=state.status == "resume", archive_into=run_dir)
            if not state.promote:
                self.echo(f"evaluate {spec.name} on {', '.join(spec.splits)}")
                self._evaluate(spec, cfg, work, data_dir, lock)
            if work != run_dir:
                archive = promote_retrain(run_dir)
                if archive is not None:
                    self.echo(f"{spec.name}: retrained; the stale run's files moved to {archive}")
            self.echo(f"done {spec.name}")
            return True
        finally:
            lock.release()

    def _train(self, spec: RunSpec, run_dir: Path, data_dir: Path, lock: FileLock, resume: bool,
               archive_into: Path) -> None:
        cmd = [*CLI, "train", "--config", str(spec.config), "--data", str(data_dir), "--out", str(run_dir), "--quiet"]
        for item in spec.train_overrides(self.threads):
            cmd += ["--set", item]
        if resume:
            cmd.append("--resume")
        else:
            archive = archive_attempt(run_dir, into=archive_into)
            if archive is not None:
                self.echo(f"{spec.name}: the earlier attempt's files moved to {archive}")
        self._call(cmd, run_dir / "train.log", lock)

    def _evaluate(self, spec: RunSpec, cfg, run_dir: Path, data_dir: Path, lock: FileLock) -> None:
        scratch, model = run_dir / EVAL_SCRATCH, run_dir / "model.pt"
        evaluation = finished_evaluation(scratch, model, data_dir, spec)
        if evaluation is None:
            cmd = [*CLI, "evaluate", "--checkpoint", str(model), "--data", str(data_dir),
                   "--splits", *spec.splits, "--out", str(scratch), "--threads", str(self.threads), "--quiet",
                   "--overwrite", "--no-predictions", "--batch-size", str(self.plan.eval_batch_size),
                   "--max-examples", str(spec.eval_max_examples)]
            self._call(cmd, run_dir / "evaluate.log", lock)
            evaluation = read_json(scratch / "results.json", f"{scratch}/results.json", ExperimentError)
        else:
            self.echo(f"{spec.name}: kept the finished evaluation of this model.pt in {scratch}")
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
                           "episodes": evaluation.get("episodes"), "seconds": evaluation.get("seconds"),
                           "checkpoint_sha256": evaluation.get("checkpoint_sha256")},
            "splits": evaluation["splits"],
        }
        tmp = run_dir / "results.json.tmp"
        tmp.write_text(json.dumps(doc, indent=2) + "\n")
        replace_durably(tmp, run_dir / "results.json")
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
            warm = ("import sys\nfrom gscan_ros.errors import GscanError\n"
                    "from gscan_ros.training.trainer import split_cache\n"
                    "try:\n    for split in sys.argv[2:]:\n        split_cache(sys.argv[1], split)\n"
                    "except GscanError as exc:\n    sys.exit(f'error: {exc}')\n")
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

