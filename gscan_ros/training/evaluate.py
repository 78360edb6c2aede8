"""Batched closed-loop evaluation and the gSCAN metrics (ylkuo/compositional-gscan `predict.py`).

The model acts, the one `World` executes, the new state is encoded and fed back — for
many episodes at once: one batched forward over every live episode per decoding step,
finished episodes dropped from the batch. An episode stops at EOS or after
`max_steps + 1` decoding iterations (121, like the original's `max_decoding_steps`).
An action the world rejects (`InvalidActionError`) stays in the prediction and leaves
the world unchanged.
"""
from __future__ import annotations

import dataclasses
from collections import defaultdict
from dataclasses import dataclass, field
from functools import cached_property
from typing import Sequence

import numpy as np
import torch
from tqdm import tqdm

from gscan_ros.data.episode import Episode
from gscan_ros.data.splits import SPLIT_LETTERS
from gscan_ros.errors import InvalidActionError
from gscan_ros.model.policy import MAX_STEPS, Policy
from gscan_ros.training.distributed import Ranks, shard_of
from gscan_ros.training.failures import FAILURE_KINDS, classify_failure
from gscan_ros.world.types import ADVERBS, COLORS, SIZE_ADJECTIVES, TRANSITIVE_VERBS, Action
from gscan_ros.world.world import World


def token_accuracy(predicted: Sequence, gold: Sequence) -> float:
    """% of aligned positions that agree; the shorter sequence never matches past its end.

    As `sequence_accuracy` of ylkuo/compositional-gscan `predict.py` (and MM's `seq2seq/helpers.py`).
    """
    longest = max(len(predicted), len(gold))
    if longest == 0:
        return 100.0
    same = sum(1 for p, g in zip(predicted, gold) if p == g)
    return 100.0 * same / longest


@dataclass
class Prediction:
    episode: Episode
    actions: list[Action]
    attention: dict[str, list[np.ndarray]] | None = None  # word -> one float32[36] map per step
    max_steps: int = MAX_STEPS  # the decoding cap it ran under: more actions than this never stopped

    @property
    def token_accuracy(self) -> float:
        return token_accuracy(self.actions, self.episode.actions)

    @property
    def exact_match(self) -> bool:
        return list(self.actions) == list(self.episode.actions)

    @cached_property
    def failure(self) -> str | None:
        """`failure_kind` at the cap it was decoded with, replayed once (summary and predictions file both read it)."""
        return failure_kind(self)


def failure_kind(prediction: Prediction, max_steps: int | None = None) -> str | None:
    """The `FAILURE_KINDS` entry of a failed prediction (None for an exact match); more
    than `max_steps` actions (default: the prediction's own cap) means the decoding cap,
    not an EOS, ended it."""
    cap = prediction.max_steps if max_steps is None else max_steps
    return classify_failure(prediction.episode, prediction.actions, stopped=len(prediction.actions) <= cap)


@dataclass
class EvalResult:
    predictions: list[Prediction] = field(default_factory=list)

    def summary(self) -> dict:
        """Per split: examples, exact match %, token accuracy %, exact match per target
        length, failures of each kind and exact match per `command_groups` axis."""
        by_split: dict[str, list[Prediction]] = defaultdict(list)
        for p in self.predictions:
            by_split[p.episode.split].append(p)
        out = {}
        for split in sorted(by_split, key=lambda s: (SPLIT_LETTERS.get(s, "~"), s)):
            preds = by_split[split]
            by_len: dict[int, list[Prediction]] = defaultdict(list)
            for p in preds:
                by_len[len(p.episode.actions)].append(p)  # each failure at its own length (quirk Q8)
            out[split] = {
                "letter": SPLIT_LETTERS.get(split, ""),
                "examples": len(preds),
                "exact_match": _pct(p.exact_match for p in preds),
                "token_accuracy": float(np.mean([p.token_accuracy for p in preds])),
                "by_target_length": {
                    str(n): {"examples": len(ps), "exact_match": _pct(p.exact_match for p in ps)}
                    for n, ps in sorted(by_len.items())
                },
                "failures": failure_counts(preds),
                "by_group": episodes_by_group(preds),
            }
        return out

    @property
    def exact_match(self) -> float:
        return _pct(p.exact_match for p in self.predictions)

    @property
    def token_accuracy(self) -> float:
        return float(np.mean([p.token_accuracy for p in self.predictions])) if self.predictions else 0.0


def failure_counts(predictions: Sequence[Prediction]) -> dict[str, int]:
    """How many of `predictions` failed in each of the `FAILURE_KINDS`."""
    kinds = [p.failure for p in predictions]
    return {kind: kinds.count(kind) for kind in FAILURE_KINDS}


def command_groups(episode: Episode) -> dict[str, str]:
    """The command type of an episode along the axes its concepts vary on: verb, adverb,
    size word, colour word, a heavy target (push/pull twice per cell), whether the gold
    moves the target at all (a push or pull against a wall or object does not) and target
    length. Used to see which concept a model learns late (docs/model.md)."""
    words = episode.command.split()
    adverb = next((a for a in ADVERBS if episode.command.endswith(" " + a)), "none")
    target = episode.situation.target_object
    heavy = target is not None and target.heavy and words[0] in TRANSITIVE_VERBS
    n = len(episode.actions)
    return {
        "verb": words[0],
        "adverb": adverb.replace(" ", "_"),
        "size_word": next((w for w in words if w in SIZE_ADJECTIVES), "none"),
        "color_word": "yes" if any(w in COLORS for w in words) else "no",
        "heavy_target": "yes" if heavy else "no",
        "moves_target": "yes" if any(a in (Action.PUSH, Action.PULL) for a in episode.actions) else "no",
        "target_length": "<=8" if n <= 8 else "9-16" if n <= 16 else ">=17",
    }


def _hits_by_group(predictions: Sequence[Prediction]) -> dict[str, dict[str, list[bool]]]:
    """Each `command_groups` axis -> value -> the exact-match flags of its predictions."""
    hits: dict[str, dict[str, list[bool]]] = defaultdict(lambda: defaultdict(list))
    for p in predictions:
        for axis, value in command_groups(p.episode).items():
            hits[axis][value].append(p.exact_match)
    return {axis: dict(sorted(values.items())) for axis, values in hits.items()}


def exact_match_by_group(predictions: Sequence[Prediction]) -> dict[str, dict[str, float]]:
    """Exact match % per value of each `command_groups` axis, e.g. {"adverb": {"none": 97.1, ...}}."""
    return {axis: {value: round(_pct(flags), 2) for value, flags in values.items()}
            for axis, values in _hits_by_group(predictions).items()}


def episodes_by_group(predictions: Sequence[Prediction]) -> dict[str, dict[str, dict]]:
    """Episodes and exact match % per value of each `command_groups` axis, e.g.
    {"moves_target": {"no": {"examples": 8604, "exact_match": 50.5}, ...}}."""
    return {axis: {value: {"examples": len(flags), "exact_match": round(_pct(flags), 2)}
                   for value, flags in values.items()}
            for axis, values in _hits_by_group(predictions).items()}


def _pct(flags) -> float:
    flags = list(flags)
    return 100.0 * sum(flags) / len(flags) if flags else 0.0


@torch.no_grad()
def evaluate_episodes(model_or_policy, episodes: Sequence[Episode], batch_size: int = 1024,
                      max_steps: int = MAX_STEPS, record_attention: bool = False, parser: str = "semantic",
                      progress: bool = False, ranks: Ranks = Ranks()) -> EvalResult | None:
    """Closed-loop decode `episodes`, `batch_size` at a time. A bare model is wrapped in a
    Policy with `parser` (and no lexicon).

    Sharded over `ranks` (every rank calls it with the same episodes): each rank decodes
    every world_size-th batch, exactly the batches one process would decode, and rank 0
    gets all predictions back in order, bit for bit the single-process result; the other
    ranks get None."""
    was_training = (model_or_policy.model if isinstance(model_or_policy, Policy) else model_or_policy).training
    policy = model_or_policy if isinstance(model_or_policy, Policy) else Policy(model_or_policy, parser)  # eval()s it
    policy.require_episodes_grid(episodes)
    policy.model.eval()
    mine = shard_of(range(0, len(episodes), batch_size), ranks)
    decoded: dict[int, list[Prediction]] = {}
    try:
        for start in tqdm(mine, desc="evaluating", unit="batch", disable=not progress):
            decoded[start] = _decode_batch(policy, episodes[start : start + batch_size], max_steps, record_attention)
    finally:
        policy.model.train(was_training)
    if not ranks.distributed:
        return EvalResult([p for start in sorted(decoded) for p in decoded[start]])
    # Only what was decoded travels; rank 0 pairs it with its own copy of the episodes.
    parts = ranks.gather_to_main({start: [(p.actions, p.attention) for p in preds] for start, preds in decoded.items()})
    if parts is None:
        return None
    merged = {start: preds for part in parts for start, preds in part.items()}
    return EvalResult([Prediction(ep, actions, attention, max_steps)
                       for start in sorted(merged)
                       for ep, (actions, attention) in zip(episodes[start : start + batch_size], merged[start])])


def _decode_batch(policy: Policy, episodes: Sequence[Episode], max_steps: int, record: bool) -> list[Prediction]:
    graphs = [policy.parse(ep.command) for ep in episodes]
    rollout = policy.rollout(graphs)
    worlds = [World(ep.situation) for ep in episodes]
    preds = [Prediction(ep, [], {} if record else None, max_steps) for ep in episodes]
    live = list(range(len(episodes)))
    eos = int(Action.EOS)
    for _ in range(max_steps + 1):
        logits, maps = rollout.step(np.stack([worlds[i].encode() for i in live]))
        chosen = logits.argmax(-1)
        if record and maps is not None:
            maps = maps.cpu()
            for row, i in enumerate(live):
                for slot, word in rollout.words[row]:
                    preds[i].attention.setdefault(word, []).append(maps[row, slot].numpy())
        keep = []
        for row, (i, action) in enumerate(zip(live, chosen.tolist())):
            if action == eos:
                continue
            preds[i].actions.append(Action(action))
            try:
                worlds[i].step(Action(action))
            except InvalidActionError:
                pass  # kept in the prediction; the world stays as it was
            keep.append(row)
        if not keep:
            break
        if len(keep) < len(live):
            rollout.keep(torch.tensor(keep))
            live = [live[r] for r in keep]
    return preds


@dataclass
class TeacherForced:
    """How well a model predicts the gold actions when fed the gold prefix.

    An episode is `all_right` when every step's argmax (EOS included) is the gold action:
    exactly the episodes a greedy closed loop reproduces, so `sequence_accuracy` equals
    closed-loop exact match (within the step cap). Token accuracy and the gold actions'
    NLL move before either does, which makes them the learning curve of a split whose
    exact match is still 0 (split G at small k)."""

    episodes: int
    steps: int
    token_accuracy: float  # % of gold steps (EOS included) predicted
    nll: float  # mean -log p(gold action) per step
    sequence_accuracy: float  # % of episodes with every step right

    def summary(self) -> dict:
        return dataclasses.asdict(self)


@torch.no_grad()
def teacher_forced(model: torch.nn.Module, store, ids: Sequence[int] | None = None,
                   batch_size: int = 256) -> TeacherForced:
    """`TeacherForced` of `model` (any model kind, in eval mode) on episodes
    `ids` of an `EpisodeStore` (default: all of them)."""
    from gscan_ros.training.step import teacher_batch

    ids = np.arange(len(store)) if ids is None else np.asarray(ids)
    was_training = model.training
    model.eval()
    right = steps = all_right = 0
    nll = 0.0
    try:
        for start in range(0, len(ids), batch_size):
            chunk = ids[start : start + batch_size]
            batch = teacher_batch(model, store, chunk)
            out = model(batch)
            gold, row, logits, step_nll = _gold_steps(batch, out)
            hit = logits.argmax(-1) == gold
            right += int(hit.sum())
            steps += int(gold.numel())
            nll += float(step_nll.sum())
            misses = torch.zeros(len(chunk), dtype=torch.long).index_add_(0, row.cpu(), (~hit).long().cpu())
            all_right += int((misses == 0).sum())
    finally:
        model.train(was_training)
    n = len(ids)
    return TeacherForced(n, steps, 100.0 * right / max(steps, 1), nll / max(steps, 1), 100.0 * all_right / max(n, 1))


def _gold_steps(batch, out) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(gold action, batch row, logits, NLL) of every real step of a teacher-forcing batch:
    the compositional batch packs steps time-major with padding (`valid`); the output of
    the models with the seq2seq decoder (seq2seq, AuxLoss, LCGN) holds the valid steps of
    its [rows, T] targets in row-major order."""
    if hasattr(batch, "valid"):
        valid = batch.valid.to(out.logits.device)
        return (batch.targets.to(valid.device)[valid], batch.rows.to(valid.device)[valid], out.logits[valid],
                out.nll[valid])
    targets = batch.targets.to(out.logits.device)
    valid = targets >= 0
    return targets[valid], valid.nonzero()[:, 0], out.logits, out.nll
