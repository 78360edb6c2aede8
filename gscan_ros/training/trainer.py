"""The training loop: teacher forcing on world states, Adam, periodic closed-loop validation.

A run directory holds `config.yaml` (resolved), `metrics.jsonl` (one JSON object per
log line / validation), `learning_curve.png`, `last.pt` (with optimizer + RNG state, for
`--resume`) and `last.prev.pt` (the one before it), `best.pt` (best dev exact match) and
`model.pt` (best.pt without training state: the file to ship or evaluate). One run writes
it at a time (`gscan_ros.outputs`), each file replaced whole and durably.
"""
from __future__ import annotations

import contextlib
import itertools
import logging
import random
import time
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Callable, Iterator

import numpy as np
import torch
import yaml
from tqdm import tqdm

from gscan_ros.analysis.explain import step0_readings, summarize
from gscan_ros.errors import CheckpointError, DatasetFormatError, GscanError
from gscan_ros.language.lexicon import Lexicon
from gscan_ros.model.checkpoint import (
    build_model,
    checkpoint_dict,
    parameter_count,
    previous_checkpoint,
    read_checkpoint,
    restore_model,
    save_checkpoint,
)
from gscan_ros.model.modules import ModuleTable
from gscan_ros.model.policy import Policy
from gscan_ros.outputs import claimed, refuse_links, replacing, write_text
from gscan_ros.runtime import configure_torch, mkl_shim_loaded
from gscan_ros.training import distributed
from gscan_ros.training.batches import EpisodeStore, EpochCursor, iterate_batches, word_repeats
from gscan_ros.training.config import SCREEN_SEED_STRIDE, ConfigError, TrainConfig, config_changes
from gscan_ros.training.evaluate import evaluate_episodes, exact_match_by_group
from gscan_ros.training.evaluation_files import REPORT_FILES
from gscan_ros.training.metrics_log import append_event, finished_end, read_events, rewind
from gscan_ros.training.step import TrainingDiverged, TrainStep

# Seed screening: candidate k of a run with seed s has seed s + SCREEN_SEED_STRIDE k
# (training/config.py), and its maps are read on this many dev episodes.
SCREEN_EPISODES = 300
# What `resume` reads beyond the weights: model.pt, best.pt and step_N.pt hold none of it.
RESUME_STATE = ("optimizer", "cursor", "rng", "best_dev_exact_match")
# What a screened candidate is: the Run attributes that `fresh_start` and training change.
SCREEN_STATE = ("seed", "model", "optimizer", "scheduler", "step", "cursor", "train_step", "policy")

# A run's files, its evaluation's among them (`--overwrite` leaves no old model's scores
# beside the new run's); train.log is the experiment runner's, open while it trains.
RUN_FILES = ("config.yaml", "metrics.jsonl", "learning_curve.png", "last.pt", "last.prev.pt", "best.pt", "model.pt",
             *REPORT_FILES, "evaluate.log")

log = logging.getLogger(__name__)


@dataclass
class RunFiles:
    root: Path

    config = property(lambda self: self.root / "config.yaml")
    metrics = property(lambda self: self.root / "metrics.jsonl")
    curve = property(lambda self: self.root / "learning_curve.png")
    last = property(lambda self: self.root / "last.pt")
    previous = property(lambda self: previous_checkpoint(self.last))
    best = property(lambda self: self.root / "best.pt")
    model = property(lambda self: self.root / "model.pt")

    def resume_point(self) -> Path | None:
        """The checkpoint `--resume` starts from: last.pt, else (lost between the two
        renames of its save) the one before it; None when the run has neither."""
        return next((p for p in (self.last, self.previous) if p.exists()), None)

    def snapshot(self, step: int) -> Path:
        return self.root / f"step_{step}.pt"

    def existing(self) -> list[Path]:
        """The run files (and step snapshots) already in the directory."""
        if not self.root.is_dir():
            return []
        return [self.root / n for n in RUN_FILES if (self.root / n).exists()] + sorted(self.root.glob("step_*.pt"))

    def claim(self, held: contextlib.ExitStack, resume: bool, overwrite: bool) -> None:
        """Take the run directory's lock for as long as `held` lasts, then `check_writable`."""
        held.enter_context(claimed(self.root))
        self.check_writable(resume, overwrite)

    def check_writable(self, resume: bool, overwrite: bool) -> None:
        """Refuse to start a new run over an old one unless told (--resume / --overwrite),
        and a run file that is a symbolic link."""
        if self.root.exists() and not self.root.is_dir():
            raise GscanError(f"run directory {self.root} is a file, not a directory")
        refuse_links(self.root / name for name in RUN_FILES)
        if resume:
            if self.resume_point() is None:
                raise CheckpointError(f"--resume: no checkpoint at {self.last}")
            return
        found = self.existing()
        if found and not overwrite:
            raise GscanError(f"{self.root} already holds a run ({', '.join(p.name for p in found[:3])}); "
                             "pass --resume to continue it or --overwrite to replace it")

    def create(self, resume: bool) -> None:
        """Make the directory; for a new run, remove the old run's files (only those)."""
        if not resume:
            for path in self.existing():
                path.unlink()
        self.root.mkdir(parents=True, exist_ok=True)


def screen_passes(reading: dict) -> bool:
    """A screened candidate passes when its noun-phrase maps peak on the target at least
    half as often as a uniform pick among the objects would. Maps that mark a cell beside
    the target (the slow basin) sit at 0-5 % after 1,000 updates; maps on the target at
    11-51 % (and rising): docs/results.md, "Seed screening"."""
    return reading["localization"] > reading["localization_chance"] / 2


def seed_everything(seed: int) -> dict:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)
    return {"python": seed, "numpy": seed, "torch": seed}


def module_table(parser, lexicon: Lexicon, extra_graphs=()) -> ModuleTable:
    """Modules of every gSCAN command (675) plus the training graphs, so words that never
    occur in training (e.g. 'cautiously' at k=0) still have a (random) module."""
    from gscan_ros.language.grammar import all_commands

    graphs = [parser.parse(c) for c in all_commands()]
    return ModuleTable.from_graphs([*graphs, *extra_graphs], lexicon)


def model_settings(cfg: TrainConfig, store: EpisodeStore) -> dict:
    """The model config with the grid size of the training data (a config that names
    another grid size is a ConfigError)."""
    settings = cfg.model_config().to_dict()
    if store.grid_size is not None:
        if "grid_size" in cfg.model and cfg.model["grid_size"] != store.grid_size:
            raise ConfigError(f"model.grid_size is {cfg.model['grid_size']} but the training data is on a "
                              f"{store.grid_size}x{store.grid_size} grid")
        settings["grid_size"] = store.grid_size
    return settings


def new_model(cfg: TrainConfig, parser, lexicon: Lexicon, store: EpisodeStore):
    if cfg.model_kind == "compositional":
        table = module_table(parser, lexicon, store.graphs)
        return build_model("compositional", model_settings(cfg, store), {"modules": table.to_list()})
    from gscan_ros.model.decoder import command_vocabulary

    return build_model(cfg.model_kind, model_settings(cfg, store), {"tokens": command_vocabulary()})


def iter_split(data: str, split: str) -> Iterator:
    """Episodes of `split` streamed from `data`."""
    from gscan_ros.data.io import iter_episodes

    return iter_episodes(data, [split])


def load_split(data: str, split: str) -> list:
    return list(iter_split(data, split))


def split_cache(data: str, split: str, include_incomplete: bool = False):
    """The decode-once `EpisodeCache` of `split` when `data` is a bag or a directory of
    per-split bags (built on first use, loaded afterwards); None for dataset.txt data
    (`load_split` reads it). Bag data without the split is refused (`select_bags`).
    Recorded episodes that did not end complete only with `include_incomplete`."""
    from gscan_ros.data.io import select_bags

    bags = select_bags(data, [split])
    if bags is None:
        if include_incomplete:
            raise ConfigError(f"include_incomplete keeps recorded episodes that did not end complete; {data} is "
                              f"a dataset.txt, whose examples are all demonstrations")
        return None
    from gscan_ros.data.bag_cache import load_episode_cache

    return load_episode_cache(bags[0], [split], include_incomplete=include_incomplete)


def load_train_store(data: str, cfg: TrainConfig, parser, progress: bool = False) -> EpisodeStore:
    """Teacher-forcing store of the train split: bags from their cache (no replay), else
    Episodes replayed through World. `max_train_target_length` drops longer episodes
    first, then `max_train_examples` keeps the first N."""
    cap = cfg.max_train_target_length
    cache = split_cache(data, cfg.train_split, cfg.include_incomplete)
    if cache is None:
        episodes = iter_split(data, cfg.train_split)
        if cap:
            episodes = (ep for ep in episodes if len(ep.actions) <= cap)
        if cfg.max_train_examples:
            episodes = itertools.islice(episodes, cfg.max_train_examples)
        return EpisodeStore(episodes, parser, progress=progress)
    keep = [i for i in range(len(cache)) if not cap or len(cache.actions(i)) <= cap]
    if cfg.max_train_examples:
        keep = keep[: cfg.max_train_examples]
    if len(keep) < len(cache):
        cache = cache.subset(keep)
    return EpisodeStore.from_cache(cache, parser, progress=progress)


def load_dev(data: str, cfg: TrainConfig) -> list:
    """Validation episodes: a fixed, seeded subset of `max_dev_examples` (0 = all) of the
    dev split's episodes of at most `max_dev_target_length` actions. From a bag, only the
    chosen episodes' situations are parsed."""
    cache = split_cache(data, cfg.dev_split)
    source = cache if cache is not None else load_split(data, cfg.dev_split)
    cap = cfg.max_dev_target_length
    pick = [i for i in range(len(source))
            if not cap or len(cache.actions(i) if cache is not None else source[i].actions) <= cap]
    if cfg.max_dev_examples:
        pick = seeded_subset(pick, cfg.max_dev_examples, cfg.seed)
    if cache is not None:
        return cache.subset(pick).episodes
    return [source[i] for i in pick]


def train(cfg: TrainConfig, data: str, out_dir: str | Path, resume: bool = False, progress: bool = True,
          overwrite: bool = False, on_validation: Callable[[dict], None] | None = None,
          device: str | torch.device = "cpu") -> dict:
    """Train per `cfg` on dataset `data`; returns the final metrics dict.

    A new run refuses a directory that holds a run unless `overwrite` (then only the run's
    own files are replaced); nothing is written before the data has loaded.
    `on_validation` sees every validation's metrics (e.g. to print a row).
    `device`: 'cpu', 'cuda' or 'auto' (`runtime.resolve_device`).

    Started by `torchrun` with several ranks, the ranks train one model with
    DistributedDataParallel: each takes a shard of every global batch of `batch_size`
    (`distributed.shard_batch`), rank 0 validates, logs and writes the run's files, and
    every rank returns rank 0's result. The global batches do not depend on the number of
    ranks, so with dropout off neither does the result (up to float rounding). The dropout
    masks do: each rank draws those of its own shard, rank 0 from the generator a single
    process seeds, rank r > 0 from one seeded by (seed, r, update at start), so with
    dropout on N ranks train as with other masks, reproducibly for the same N. `resume`
    continues a run whatever number of ranks wrote it (batch cursor and rank 0's
    generators from last.pt); ranks r > 0 are seeded afresh from (seed, r, update), so a
    resumed multi-rank run with dropout on is not bit for bit the run left unstopped."""
    files = RunFiles(Path(out_dir))
    with distributed.joined(device) as ranks, contextlib.ExitStack() as held:
        ranks.from_main(lambda: files.claim(held, resume, overwrite))
        run = Run(cfg, data, files, ranks, progress, on_validation)
        if resume:
            run.resume()
        run.start(resumed=resume)
        run.train_loop()
        return ranks.from_main(run.finish)


class Run:
    """One training run, in the order it happens: `__init__` (seeds, data, model,
    optimizer), `resume`, `start` (run files), `train_loop` (updates with periodic
    `validate` and `checkpoint`), `finish` (model.pt and the end record)."""

    def __init__(self, cfg: TrainConfig, data: str, files: RunFiles, ranks: distributed.Ranks, progress: bool,
                 on_validation: Callable[[dict], None] | None):
        self.cfg, self.data, self.files, self.ranks, self.on_validation = cfg, data, files, ranks, on_validation
        self.progress = progress and ranks.is_main
        configure_torch(cfg.threads)
        self.seeds = seed_everything(cfg.seed)
        self.lexicon = Lexicon.named(cfg.lexicon)
        from gscan_ros.language.registry import get_parser

        parser = get_parser(cfg.parser, self.lexicon)
        self.setup_started = time.time()
        if ranks.distributed:  # a bag's decode-once cache is built by one rank, then read by all
            ranks.from_main(lambda: split_cache(data, cfg.train_split) and None)
        self.store = load_train_store(data, cfg, parser, progress=self.progress)
        if not len(self.store):
            raise DatasetFormatError(f"dataset {data!r} has no {cfg.train_split!r} episodes")
        try:
            self.repeats = word_repeats(self.store.commands, cfg.oversample_word, cfg.oversample_factor)
        except ValueError as exc:
            raise ConfigError(f"oversample_word: {exc} in {data!r}") from None
        self.dev_eps: list = []
        ranks.from_main(lambda: self.load_dev(data))  # rank 0 validates; its refusal stops every rank
        self.parser = parser
        if cfg.screen_seeds > 1 and ranks.distributed:
            raise ConfigError("screen_seeds runs on one process; screen first, then train on several ranks")
        self.best, self.elapsed_before = -1.0, 0.0
        self.best_step: int | None = None  # the update of the best validation (best.pt's)
        self.best_unsaved = False  # a validation improved on the best; `save_resume_point` writes best.pt
        self.last_metrics: dict = {}
        self.screen_resume: dict | None = None  # a screen stopped between candidates (`resume`)
        self.window = _LossWindow()  # the updates since the last `train` record (kept in last.pt)
        self.fresh_start(cfg.seed)

    def load_dev(self, data: str) -> None:
        """The validation episodes; none is an error (a best.pt picked on nothing means nothing),
        and so is one on another grid than the train split's (refused now, not at the first
        validation)."""
        self.dev_eps = load_dev(data, self.cfg)
        if not self.dev_eps:
            raise DatasetFormatError(f"dataset {data!r} has no {self.cfg.dev_split!r} episodes to validate on")
        g = self.store.grid_size
        other = next((ep for ep in self.dev_eps if g is not None and ep.situation.grid_size != g), None)
        if other is not None:
            d = other.situation.grid_size
            raise DatasetFormatError(f"dataset {data!r}: {self.cfg.dev_split} episode {other.example_id} is on a "
                                     f"{d}x{d} grid, the {self.cfg.train_split!r} split on {g}x{g}")

    def fresh_start(self, seed: int) -> None:
        """A new model, optimizer and schedule from `seed`, at update 0 (the state `seed` alone gives)."""
        cfg = self.cfg
        self.seed = seed
        self.model = new_model(cfg, self.parser, self.lexicon, self.store).to(self.ranks.device)
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=cfg.lr, betas=(0.9, 0.999))
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(self.optimizer, cfg.lr_factor)
        self.step, self.cursor = 0, EpochCursor()

    def resume(self) -> None:
        """Continue from last.pt: weights, optimizer, schedule, batch cursor, best score, RNGs.
        A best.pt older than the best last.pt records (a stop between the two writes of
        `save_resume_point`) is written again from last.pt, whose weights it was."""
        cfg = self.cfg
        ckpt = self.ranks.from_main(lambda: _read_resume_checkpoint(self.files, cfg, self.data, len(self.store)))
        restore_model(ckpt, self.model)
        self.optimizer.load_state_dict(ckpt["optimizer"])
        self.step = int(ckpt["step"])
        self.scheduler.last_epoch = self.step
        for group in self.optimizer.param_groups:
            group["lr"] = cfg.lr * cfg.lr_factor(self.step)
        self.cursor = EpochCursor(**ckpt["cursor"])
        self.seed = int(ckpt.get("train_seed", cfg.seed))
        self.best = float(ckpt["best_dev_exact_match"])
        self.best_step = ckpt.get("best_step")
        self.elapsed_before = float(ckpt.get("elapsed_s", 0.0))
        self.last_metrics = dict(ckpt.get("metrics") or {})  # a stop after the last validation: not redone
        # The updates since the last `train` record: that record logs them as the run left unstopped would.
        self.window = _LossWindow(**ckpt.get("loss_window", {}))
        _restore_rng(ckpt["rng"], self.ranks.device)
        if "screen" in ckpt:  # stopped during the seed screen: it goes on at the next candidate
            self.screen_resume = {**ckpt["screen"], "rng": ckpt["rng"]}
        if self.ranks.is_main and self.best_step == self.step and _checkpoint_step(self.files.best) != self.step:
            self.checkpoint(self.files.best, ckpt.get("metrics", {}), training_state=False)

    def start(self, resumed: bool) -> None:
        """Make the update step (DDP joins here) and, on rank 0, the run files and the start record."""
        ranks = self.ranks
        if not ranks.is_main:  # own dropout masks; the weights come from rank 0 (DDP broadcasts them)
            torch.manual_seed(int(np.random.SeedSequence([self.seed, ranks.rank, self.step]).generate_state(1)[0]))
        self.make_step()
        if ranks.is_main:
            self.files.create(resumed)
            if resumed:  # the updates after the checkpoint are trained again: log them once
                rewind(self.files.metrics, self.step)
            write_text(self.files.config, yaml.safe_dump(self.cfg.resolved(), sort_keys=False))
            append_event(self.files.metrics, {
                "event": "start", "step": self.step, "seeds": self.seeds, "train_examples": len(self.store),
                "dev_examples": len(self.dev_eps), "parameters": parameter_count(self.model), "resumed": resumed,
                "world_size": ranks.world_size, "device": str(ranks.device), "mkl_shim": mkl_shim_loaded(),
                "data_load_s": round(time.time() - self.setup_started, 2), "data": self.data,
                "config": self.cfg.resolved()})
        self.started = time.time()

    def make_step(self) -> None:
        """The update step and the closed-loop policy of the current model."""
        self.train_step = TrainStep(self.model, self.optimizer, self.store, self.scheduler, self.cfg.grad_clip,
                                    self.ranks)
        self.policy = Policy(self.model, self.cfg.parser, self.lexicon)

    def elapsed(self) -> float:
        """Training seconds, including those before a resume."""
        return self.elapsed_before + time.time() - self.started

    def train_loop(self) -> None:
        """Update until max_updates, the time budget or the target dev exact match."""
        cfg, ranks, main = self.cfg, self.ranks, self.ranks.is_main
        if cfg.screen_seeds > 1 and (self.step == 0 or self.screen_resume):
            self.screen()
            self.checkpoint(self.files.last, self.last_metrics, training_state=True)  # screening is not redone
        window = self.window
        bar = tqdm(total=cfg.max_updates, initial=self.step, desc="training", unit="upd", disable=not self.progress)
        batches = iterate_batches(self.store, cfg.batch_size_at(self.step), cfg.batching, self.seed, self.cursor,
                                  self.repeats)
        budget_s = cfg.max_minutes * 60.0
        while self.step < cfg.max_updates:
            cursor, ids = next(batches)
            try:
                loss = self.train_step(ids)
            except TrainingDiverged as exc:
                kept = f"; {self.files.last} holds the last good state" if self.files.last.is_file() else ""
                raise TrainingDiverged(f"{exc} at update {self.step + 1}{kept} (try a lower lr or grad_clip)") from None
            self.step, self.cursor = self.step + 1, cursor
            if cfg.batch_size_at(self.step) != cfg.batch_size_at(self.step - 1):
                # The new size starts a fresh epoch, so a cursor saved from here on counts its batches.
                self.cursor = EpochCursor(cursor.epoch + 1, 0)
                batches = iterate_batches(self.store, cfg.batch_size_at(self.step), cfg.batching, self.seed,
                                          self.cursor, self.repeats)
            bar.update(1)
            window.add(loss, len(ids))
            if self.step % cfg.log_every == 0:
                line = self.log_train(window)
                bar.set_postfix(loss=f"{line['loss']:.3f}", ex_s=f"{line['examples_per_s']:.0f}")
                window = self.window = _LossWindow()
            # Rank 0's clock and validations decide for every rank, so all stop at the same update.
            out_of_time = bool(budget_s) and ranks.from_main(lambda: self.elapsed() >= budget_s)
            reached = False
            paused = time.time()  # validation and checkpoints are no training: the rate leaves them out
            if self.step % cfg.validate_every == 0 or self.step == cfg.max_updates or out_of_time:
                self.last_metrics = ranks.from_main(self.validate)
                reached = self.reached_target(self.last_metrics["dev_exact_match"])
            if main and (self.step % cfg.checkpoint_every == 0 or self.step == cfg.max_updates or out_of_time
                         or reached or self.best_unsaved):
                self.save_resume_point()
            if main and cfg.snapshot_every and self.step % cfg.snapshot_every == 0:
                self.checkpoint(self.files.snapshot(self.step), self.last_metrics, training_state=False)
            window.paused += time.time() - paused
            if out_of_time or reached:
                break
        bar.close()

    def screen(self) -> None:
        """Seed screening (TrainConfig.screen_seeds): train candidates in turn for
        `screen_updates` updates each and keep the first whose step-0 noun-phrase maps
        pass `screen_passes` on the dev subset, else the best; one `screen`
        record per candidate, and the run continues from the kept candidate's state.

        After each rejected candidate, last.pt holds the best candidate so far and the
        next one's number, so a stopped screen resumes at that candidate (candidates are
        independent: each starts from its own seed) instead of from the first."""
        cfg = self.cfg
        episodes = screen_episodes(self.dev_eps, cfg.seed)
        kept: dict | None = None
        first = 0
        if self.screen_resume:  # the state resume() loaded is the best candidate so far
            first = int(self.screen_resume["next_candidate"])
            kept = {"localization": float(self.screen_resume["localization"]), "rng": self.screen_resume["rng"],
                    **{name: getattr(self, name) for name in SCREEN_STATE}}
            self.screen_resume = None
        passed = False
        for k in range(first, cfg.screen_seeds):
            seed = cfg.seed + SCREEN_SEED_STRIDE * k
            if k:  # candidate 0 is the state __init__ made from the run's own seed
                seed_everything(seed)
                self.fresh_start(seed)
                self.make_step()
            batches = iterate_batches(self.store, cfg.batch_size, cfg.batching, seed, self.cursor, self.repeats)
            for _ in tqdm(range(cfg.screen_updates), desc=f"screen {k + 1}/{cfg.screen_seeds} (seed {seed})",
                          unit="upd", disable=not self.progress):
                self.cursor, ids = next(batches)
                self.train_step(ids)
                self.step += 1
            reading = summarize(step0_readings(self.policy, episodes))["all"]
            passed = screen_passes(reading)
            if self.progress:
                tqdm.write(f"seed {seed}: the maps localize the target in {reading['localization']:.1f}% of "
                           f"{len(episodes)} dev episodes (chance {reading['localization_chance']:.1f}%): "
                           f"{'kept' if passed else 'rejected'}")
            append_event(self.files.metrics, {
                "event": "screen", "candidate": k, "seed": seed, "step": self.step,
                "localization": reading["localization"], "chance": reading["localization_chance"],
                "size_spearman": reading["size_spearman"], "passed": passed, "elapsed_s": round(self.elapsed(), 2)})
            if kept is None or reading["localization"] > kept["localization"]:
                kept = {"localization": reading["localization"], "rng": _rng_state(self.ranks.device),
                        **{name: getattr(self, name) for name in SCREEN_STATE}}
            if passed:
                break
            if k + 1 < cfg.screen_seeds:
                self.checkpoint(self.files.last, {}, training_state=True, screened=kept,
                                screen={"next_candidate": k + 1, "localization": kept["localization"]})
        for name in SCREEN_STATE:
            setattr(self, name, kept[name])
        _restore_rng(kept["rng"], self.ranks.device)
        if self.progress and not passed:
            tqdm.write(f"no candidate passed; seed {self.seed} localized the target most often and trains on")
        append_event(self.files.metrics, {"event": "screen_end", "seed": self.seed, "candidates": k + 1,
                                     "screen_updates": (k + 1) * cfg.screen_updates,
                                     "elapsed_s": round(self.elapsed(), 2)})

    def log_train(self, window: "_LossWindow") -> dict:
        """The `train` record of the updates since the last one (written by rank 0)."""
        now = time.time()
        line = {"event": "train", "step": self.step, "epoch": self.cursor.epoch, "loss": window.mean_loss(),
                "examples_per_s": window.rate(now), "mean_batch": window.examples / window.updates,
                "elapsed_s": self.elapsed_before + now - self.started, "lr": self.next_lr()}
        if self.ranks.is_main:
            append_event(self.files.metrics, line)
        return line

    def next_lr(self) -> float:
        """The learning rate of the next update, `lr * lr_factor(step)`: what a record logs
        after update `step` (as torch's `scheduler.get_last_lr()` after `scheduler.step()`)."""
        return self.optimizer.param_groups[0]["lr"]

    def reached_target(self, dev_exact_match: float) -> bool:
        return bool(self.cfg.target_dev_exact_match) and dev_exact_match >= self.cfg.target_dev_exact_match

    def validate(self) -> dict:
        """Closed-loop exact match on the dev subset (rank 0 only); a new best is noted for
        `save_resume_point`, which the caller runs next."""
        res = evaluate_episodes(self.policy, self.dev_eps, batch_size=self.cfg.eval_batch_size)
        metrics = {"step": self.step, "dev_exact_match": res.exact_match, "dev_token_accuracy": res.token_accuracy,
                   "dev_examples": len(self.dev_eps), "elapsed_s": round(self.elapsed(), 2),
                   "lr": self.next_lr(), "dev_by_group": exact_match_by_group(res.predictions)}
        if res.exact_match > self.best or not self.files.best.exists():
            # Without best.pt (lost since the resume), these weights become it, and its score with them.
            self.best, self.best_step, self.best_unsaved = res.exact_match, self.step, True
        append_event(self.files.metrics, {"event": "validation", **metrics})
        plot_learning_curve(self.files.metrics, self.files.curve)
        if self.on_validation is not None:
            self.on_validation(metrics)
        return metrics

    def save_resume_point(self) -> None:
        """last.pt, then best.pt when the last validation was a new best: the resume point is
        never older than best.pt (a stop between the two leaves a last.pt that `resume`
        writes best.pt from)."""
        self.checkpoint(self.files.last, self.last_metrics, training_state=True)
        if self.best_unsaved:
            self.checkpoint(self.files.best, self.last_metrics, training_state=False)
            self.best_unsaved = False

    def checkpoint(self, path: Path, metrics: dict, training_state: bool, screened: dict | None = None,
                   screen: dict | None = None) -> None:
        """The weights; with `training_state` (last.pt, the one before it kept), all `resume`
        needs too. `screened`: a screen candidate's kept state (`screen`) to write instead of
        the current one, with `screen` (where the screen goes on) recorded beside it."""
        run = SimpleNamespace(**screened) if screened else self
        extra = {}
        if training_state:
            extra = {"train_config": self.cfg.resolved(), "optimizer": _to_cpu(run.optimizer.state_dict()),
                     "rng": screened["rng"] if screened else _rng_state(self.ranks.device),
                     "cursor": {"epoch": run.cursor.epoch, "batch": run.cursor.batch}, "train_seed": run.seed,
                     "best_dev_exact_match": self.best, "best_step": self.best_step, "elapsed_s": self.elapsed(),
                     "loss_window": self.window.state()}
        if screen:
            extra["screen"] = screen
        save_checkpoint(path, checkpoint_dict(run.model, parser=self.cfg.parser, lexicon=self.lexicon,
                                              step=run.step, metrics=metrics, **extra), keep_previous=training_state)

    def finish(self) -> dict:
        """Validate the last update if not yet done, ship best.pt as model.pt, write the end record."""
        if not self.last_metrics or self.last_metrics.get("step") != self.step:
            self.last_metrics = self.validate()
            self.save_resume_point()
        save_checkpoint(self.files.model, dict(read_checkpoint(self.files.best)))
        reached = self.reached_target(self.best)
        append_event(self.files.metrics, {"event": "end", "step": self.step, "best_dev_exact_match": self.best,
                                     "reached_target": reached, "elapsed_s": self.elapsed()})
        return {"step": self.step, "best_dev_exact_match": self.best, "reached_target": reached,
                **self.last_metrics}


class _LossWindow:
    """Loss and examples of the updates since the last `train` record; the logged loss is
    the mean over their examples (a short batch, the last of an epoch or of one command,
    weighs what its examples weigh)."""

    def __init__(self, loss_sum: float = 0.0, examples: int = 0, updates: int = 0, loss: float | None = None):
        if loss is not None:  # a resume point written before the loss was weighed by examples: a sum of batch means
            loss_sum = loss * examples / max(updates, 1)
        self.loss_sum, self.examples, self.updates, self.since = loss_sum, examples, updates, time.time()
        self.timed = 0  # examples trained on since `since` (a resumed window's earlier ones are not)
        self.paused = 0.0  # seconds of validation and checkpoints within the window

    def state(self) -> dict:
        """What a resume needs to go on with the window (its clock starts afresh)."""
        return {"loss_sum": self.loss_sum, "examples": self.examples, "updates": self.updates}

    def add(self, loss: float, examples: int) -> None:
        """`loss`: the update's mean over its `examples`."""
        self.loss_sum += loss * examples
        self.examples += examples
        self.timed += examples
        self.updates += 1

    def mean_loss(self) -> float:
        return self.loss_sum / self.examples

    def rate(self, now: float) -> float:
        """Examples per second of training (validation and checkpoints left out)."""
        return self.timed / max(now - self.since - self.paused, 1e-9)


def _read_resume_checkpoint(files: RunFiles, cfg: TrainConfig, data: str, train_examples: int) -> dict:
    """last.pt, or with a warning the one before it when last.pt is missing (a crash between
    the two renames of its save) or unreadable; ConfigError when `cfg` changes what the run
    trained with (`config_changes`), when `data` is not the dataset it trained on (another
    name or another number of train episodes: its batch order and best dev score would mean
    nothing), or when the run has nothing left to train (`finished_end`, or past max_updates)."""
    events = read_events(files.metrics)
    end = finished_end(events, cfg)
    if end is not None:
        why = ("it reached target_dev_exact_match" if end.get("reached_target")
               else f"max_updates {cfg.max_updates}" if end["step"] >= cfg.max_updates else "max_minutes")
        raise ConfigError(f"--resume: {files.root} finished at update {end['step']} ({why}); raise it to "
                          f"train on, or start a new run")
    starts = [e for e in events if e.get("event") == "start"]
    if starts:
        was, count = starts[-1].get("data"), starts[-1].get("train_examples")
        if was and Path(was).name != Path(data).name:
            raise ConfigError(f"--resume: {files.root} trained on {was}, not {data}; resume with its own "
                              f"data or start a new run")
        if count is not None and count != train_examples:
            raise ConfigError(f"--resume: {files.root} trained on {count} train episodes, {data} gives "
                              f"{train_examples}; resume with its own data or start a new run")
    try:
        path, ckpt = files.last, read_checkpoint(files.last)
    except CheckpointError as exc:
        if not files.previous.is_file():
            raise
        log.warning("%s; resuming from %s, the checkpoint before it", exc, files.previous)
        path, ckpt = files.previous, read_checkpoint(files.previous)
    missing = [key for key in RESUME_STATE if key not in ckpt]
    if missing:
        raise CheckpointError(f"--resume: {path} holds weights only (no {', '.join(missing)}), as model.pt, "
                              f"best.pt and step_N.pt do; a run resumes from the last.pt its training wrote")
    changed = config_changes(ckpt.get("train_config", cfg.to_dict()), cfg, events)
    if changed:
        raise ConfigError(f"--resume: {path} was trained with other settings of {', '.join(changed)}; resume with "
                          f"the run's own (its config.yaml) or start a new run")
    if int(ckpt["step"]) > cfg.max_updates:
        raise ConfigError(f"--resume: {path} is at update {ckpt['step']}, past max_updates {cfg.max_updates}")
    return ckpt


def screen_episodes(dev: list, seed: int) -> list:
    """The SCREEN_EPISODES dev episodes a seed screen reads, drawn with the run's seed (every
    candidate reads the same ones). Dev is stored grouped by command, so its first
    episodes are no sample of it: they can miss a verb or an adverb altogether."""
    return seeded_subset(dev, SCREEN_EPISODES, seed)


def seeded_subset(items: list, n: int, seed: int) -> list:
    """`n` of `items` drawn with `seed`, in their order (all of them when there are no more)."""
    if len(items) <= n:
        return list(items)
    chosen = np.random.default_rng(seed).choice(len(items), n, replace=False)
    return [items[i] for i in sorted(chosen)]


def _checkpoint_step(path: Path) -> int | None:
    """The update a checkpoint holds; None when it is missing or unreadable."""
    try:
        return int(read_checkpoint(path)["step"])
    except CheckpointError:
        return None


def _to_cpu(obj):
    """A (nested) state dict with every tensor on the CPU: checkpoints load on any machine."""
    if isinstance(obj, torch.Tensor):
        return obj.cpu()
    if isinstance(obj, dict):
        return {k: _to_cpu(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(_to_cpu(v) for v in obj)
    return obj


def _rng_state(device: torch.device) -> dict:
    state = {"python": list(random.getstate()[1]), "python_version": random.getstate()[0],
             "python_gauss": random.getstate()[2], "torch": torch.get_rng_state()}
    if device.type == "cuda":  # the generator of dropout masks on that device
        state["cuda"] = torch.cuda.get_rng_state(device)
    return state


def _restore_rng(state: dict, device: torch.device) -> None:
    random.setstate((state["python_version"], tuple(state["python"]), state["python_gauss"]))
    torch.set_rng_state(state["torch"])
    if device.type == "cuda" and "cuda" in state:
        torch.cuda.set_rng_state(state["cuda"], device)


def plot_learning_curve(metrics_path: Path, png_path: Path) -> None:
    """Training loss and dev exact match against updates, from metrics.jsonl."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    train, val = [], []
    for rec in read_events(metrics_path):
        if rec.get("event") == "train":
            train.append((rec["step"], rec["loss"]))
        elif rec.get("event") == "validation":
            val.append((rec["step"], rec["dev_exact_match"]))
    fig, ax = plt.subplots(figsize=(7, 4))
    if train:
        ax.plot(*zip(*train), color="tab:blue", label="train loss")
    ax.set_xlabel("updates")
    ax.set_ylabel("loss (NLL + antonym overlap per step)")
    ax2 = ax.twinx()
    if val:
        ax2.plot(*zip(*val), "o-", color="tab:orange", label="dev exact match")
    ax2.set_ylabel("dev exact match (%)")
    ax2.set_ylim(0, 100)
    fig.legend(loc="upper right")
    fig.tight_layout()
    with replacing(png_path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)
