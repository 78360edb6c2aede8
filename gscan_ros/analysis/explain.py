"""What the network thinks (paper § "Interpretability and acquisition"), and numbers for it.

- `trace`: one episode step by step through `Policy` (the ROS node's API), keeping every
  step's world state, action and per-word maps (the data of the paper's Fig. 3).
- `size_ordering`: (-att_small + att_big) / 2 from one step's maps, where the word's
  antonym head ran on the same inputs (big|small share one module). policy_node
  publishes it live with this same function.
- `referent_word`: the node whose map the noun phrase passes up to the verb.
- `step0_readings` + `summarize`: per split, how often that map's argmax is the target's
  cell (localization) or 1-2 cells from it (beside), how often the noun's own map peaks
  on an object of the noun's shape (where a failed localization goes wrong: the noun, or
  the words composed on top of it), the Spearman correlation between the
  size-ordering value at each object of the referred shape and its true size, and how
  often the size word's own map ranks the target first among the objects the command
  names (the Spearman averages over every pair and hides a confused top two).
- `noun_colours`: how the noun's map ranks the colours of its shape (split C's red square,
  never a training target, is the combination it learns to rank low).
- `snapshots`: a run's `step_*.pt` files in update order (Fig. 4, metrics along training).
"""
from __future__ import annotations

import re
from collections import defaultdict
from dataclasses import dataclass, replace
from functools import cached_property
from pathlib import Path
from typing import Iterable, Mapping, Sequence

import numpy as np
import torch

from gscan_ros.data.episode import Episode
from gscan_ros.data.splits import SPLIT_LETTERS
from gscan_ros.errors import GscanError, InvalidActionError
from gscan_ros.language.graph import CommandGraph
from gscan_ros.model.policy import MAX_STEPS, Policy
from gscan_ros.world import CommandFrame, World, resolve_target
from gscan_ros.world.types import NOUNS, SIZE_ADJECTIVES, VERBS, Action, Situation, WorldObject

SNAPSHOT_PATTERN = re.compile(r"step_(\d+)\.pt")


# ------------------------------------------------------------------------ one episode
def size_heads_of(attention: Mapping[str, np.ndarray],
                  antonyms: Mapping[str, np.ndarray]) -> dict[str, np.ndarray] | None:
    """{"small": map, "big": map}: both heads of the command's size word, run on the same
    inputs (`attention` maps words to their maps, `antonyms` a word to its antonym head's
    map, `StepOutput.antonyms`). None when the command has no size word or the model has
    no antonym head for it (big and small in separate modules)."""
    for word in SIZE_ADJECTIVES:
        if word in attention and word in antonyms:
            other = "big" if word == "small" else "small"
            return {word: np.asarray(attention[word]), other: np.asarray(antonyms[word])}
    return None


def size_ordering(attention: Mapping[str, np.ndarray], antonyms: Mapping[str, np.ndarray]) -> np.ndarray | None:
    """(-att_small + att_big) / 2 (paper): high where big objects are, low at small ones;
    None without both heads (`size_heads_of`)."""
    return ordering_of(size_heads_of(attention, antonyms))


def ordering_of(heads: Mapping[str, np.ndarray] | None) -> np.ndarray | None:
    return None if heads is None else ((heads["big"] - heads["small"]) / 2).astype(np.float32)


def referent_word(graph: CommandGraph) -> str | None:
    """The word of the highest node above the noun whose subtree has no verb: the map the
    noun phrase passes up ("yellow" in the semantic parse of "walk to a yellow small
    circle", "NP" in the constituency parse). None without exactly one noun and one verb."""
    nouns = [n.id for n in graph.nodes if n.word in NOUNS]
    verbs = [n.id for n in graph.nodes if n.word in VERBS]
    if len(nouns) != 1 or len(verbs) != 1:
        return None
    parent = {e.child: e.parent for e in graph.edges}

    def has_verb(node: int) -> bool:
        return node == verbs[0] or any(has_verb(c) for c in graph.children(node))

    node = nouns[0]
    while node in parent and not has_verb(parent[node]):
        node = parent[node]
    return graph.node(node).word


def with_referent(situation: Situation, command: str) -> Situation:
    """The situation with the command's referent as its target (the figures mark it);
    unchanged when the command has no unique referent there."""
    try:
        target = resolve_target(situation, command)
    except GscanError:
        return situation
    if target == situation.target_object:
        return situation
    return replace(situation, target_object=target, direction_to_target=None, distance_to_target=None)


@dataclass
class TraceStep:
    situation: Situation  # the world state the model saw at this step
    action: Action  # what the model chose (EOS included)
    attention: dict[str, np.ndarray]  # word -> float32[g, g]
    antonyms: dict[str, np.ndarray]  # word -> its antonym head's map on the same inputs

    @property
    def size_ordering(self) -> np.ndarray | None:
        return size_ordering(self.attention, self.antonyms)


@dataclass
class Trace:
    graph: CommandGraph
    steps: list[TraceStep]


def require_attention(policy: Policy) -> None:
    """GscanError unless the policy's model passes attention maps (compositional, message
    'attention' or 'attention+state')."""
    if not getattr(getattr(policy.model, "cfg", None), "uses_attention", False):
        raise GscanError(f"this checkpoint ({policy.metadata.get('kind', 'unknown')} model) draws no attention "
                         "maps to show")


@torch.no_grad()
def trace(policy: Policy, situation: Situation, command: str, actions: Sequence[Action] | None = None,
          until: int | None = None, max_steps: int = MAX_STEPS) -> Trace:
    """Run one episode and keep every step's maps.

    Closed loop (the model's own actions, as policy_node runs it) unless `actions` is
    given: then the states are those after each of `actions` (a demonstration), so that
    several checkpoints are shown the same states. Stops at EOS, after `until` steps
    (step `until` included), or after `max_steps + 1` decoding steps.
    """
    require_attention(policy)
    graph = policy.parse(command)
    policy.reset(graph)
    world = World(situation)
    steps: list[TraceStep] = []
    last = max_steps if actions is None else len(actions)
    for t in range(last + 1):
        out = policy.step(world.encode())
        steps.append(TraceStep(world.snapshot(), out.action, out.attention, out.antonyms))
        move = out.action if actions is None else (actions[t] if t < len(actions) else Action.EOS)
        if move is Action.EOS or (until is not None and t >= until):
            break
        try:
            world.step(move)
        except InvalidActionError:
            pass  # as in closed-loop evaluation: the world stays as it was
    return Trace(graph, steps)


# ------------------------------------------------------------------------ the numbers
def spearman(x: Sequence[float], y: Sequence[float]) -> float:
    """Spearman's rank correlation (ties get their mean rank); nan when either side is constant
    or there are fewer than two pairs."""
    if len(x) != len(y):
        raise ValueError(f"spearman needs paired values, got {len(x)} and {len(y)}")
    if len(x) < 2:
        return float("nan")
    rx, ry = _ranks(np.asarray(x, dtype=np.float64)), _ranks(np.asarray(y, dtype=np.float64))
    rx, ry = rx - rx.mean(), ry - ry.mean()
    denom = np.sqrt((rx ** 2).sum() * (ry ** 2).sum())
    return float((rx * ry).sum() / denom) if denom > 0 else float("nan")


def _ranks(a: np.ndarray) -> np.ndarray:
    order = np.argsort(a, kind="stable")
    ranks = np.empty(len(a))
    ranks[order] = np.arange(1, len(a) + 1)
    for value in np.unique(a):  # ties share their mean rank
        tied = a == value
        ranks[tied] = ranks[tied].mean()
    return ranks


def peak_cell(referent_map: np.ndarray) -> tuple[int, int]:
    """(row, column) of the map's highest cell."""
    m = np.asarray(referent_map)
    row, col = np.unravel_index(int(np.argmax(m)), m.shape)
    return int(row), int(col)


def peak_distance(referent_map: np.ndarray, target: WorldObject) -> int:
    """Grid (Manhattan) distance from the map's highest cell to the target's cell (0: the
    map localizes the target)."""
    return _grid_distance(peak_cell(referent_map), target.position)


def _grid_distance(a: Sequence[int], b: Sequence[int]) -> int:
    return abs(a[0] - b[0]) + abs(a[1] - b[1])


BESIDE = (1, 2)
"""Peak distances counted as 'beside' the target: the slow runs' maps mark a cell one or two
rows from it, which the 5- and 7-wide convolutions still see (docs/model.md, "The plateau")."""


def size_correlation(ordering: np.ndarray, situation: Situation, shape: str) -> float:
    """Spearman between the size-ordering value at each `shape` object's cell and its size."""
    objects = [o for o in situation.placed_objects if o.shape == shape]
    values = [float(ordering[o.position.row, o.position.col]) for o in objects]
    return spearman(values, [o.size for o in objects])


@dataclass
class Reading:
    """The step-0 maps of one episode that the numbers need."""

    split: str
    command: str
    situation: Situation
    referent: np.ndarray | None  # the map the noun phrase passes up
    ordering: np.ndarray | None  # the size-ordering map (commands with a size word)
    noun: np.ndarray | None = None  # the noun's own map
    size_heads: dict[str, np.ndarray] | None = None  # "small" and "big": both heads' maps (a size word)

    @cached_property
    def frame(self) -> CommandFrame:
        return CommandFrame.parse(self.command)

    @property
    def shape(self) -> str:
        """The shape the command's noun names."""
        return self.frame.shape

    @property
    def size_word(self) -> np.ndarray | None:
        """The map of the command's size word (None without one)."""
        return self.size_heads.get(self.frame.size) if self.size_heads and self.frame.size else None


@torch.no_grad()
def step0_readings(policy: Policy, episodes: Sequence[Episode], batch_size: int = 512) -> list[Reading]:
    """Every episode's initial state through the model, `batch_size` at a time."""
    require_attention(policy)
    policy.require_episodes_grid(episodes)
    policy.model.eval()
    readings = []
    for start in range(0, len(episodes), batch_size):
        chunk = episodes[start : start + batch_size]
        graphs = [policy.parse(ep.command) for ep in chunk]
        rollout = policy.rollout(graphs)
        _, maps = rollout.step(np.stack([World(ep.situation).encode() for ep in chunk]))
        for row, (ep, graph) in enumerate(zip(chunk, graphs)):
            attention, antonyms = rollout.word_maps(maps, row)
            heads = size_heads_of(attention, antonyms)
            reading = Reading(ep.split, ep.command, ep.situation, attention.get(referent_word(graph)),
                              ordering_of(heads), size_heads=heads)
            reading.noun = attention.get(reading.shape)  # the frame parsed once, cached on the reading
            readings.append(reading)
    return readings


def summarize(readings: Iterable[Reading]) -> dict[str, dict]:
    """Per split, then "all": episodes; localization % (of episodes with a target and a
    referent map); the same by chance for a uniform pick among the objects; beside % and
    on-agent % (the map peaks 1-2 cells from the target, or on the agent's cell); noun on
    shape % (of episodes with a noun map: it peaks on an object of the noun's shape);
    episodes with a defined size correlation and their mean Spearman (nan if none); size
    word first % (`size_word_first`) of the episodes with a size word whose command names
    two or more objects."""
    groups: dict[str, list[Reading]] = defaultdict(list)
    for r in readings:
        groups[r.split].append(r)
        groups["all"].append(r)
    out = {}
    for split in sorted(groups, key=lambda s: (s == "all", SPLIT_LETTERS.get(s, "~"), s)):
        hits, beside, on_agent, chance, rhos, noun_hits, size_first = [], [], [], [], [], [], []
        for r in groups[split]:
            if r.noun is not None:
                peak = peak_cell(r.noun)
                noun_hits.append(any(o.shape == r.shape and tuple(o.position) == peak
                                     for o in r.situation.placed_objects))
            target = r.situation.target_object
            if target is not None and r.referent is not None:
                peak = peak_cell(r.referent)
                distance = _grid_distance(peak, target.position)
                hits.append(distance == 0)
                beside.append(distance in BESIDE)
                on_agent.append(peak == tuple(r.situation.agent_position))
                chance.append(1.0 / len(r.situation.placed_objects))
            if r.ordering is not None:
                rho = size_correlation(r.ordering, r.situation, r.shape)
                if not np.isnan(rho):
                    rhos.append(rho)
            first = size_word_first(r)
            if first is not None:
                size_first.append(first)
        out[split] = {
            "episodes": len(groups[split]),
            "localization": 100.0 * float(np.mean(hits)) if hits else float("nan"),
            "localization_chance": 100.0 * float(np.mean(chance)) if chance else float("nan"),
            "beside": 100.0 * float(np.mean(beside)) if beside else float("nan"),
            "on_agent": 100.0 * float(np.mean(on_agent)) if on_agent else float("nan"),
            "noun_on_shape": 100.0 * float(np.mean(noun_hits)) if noun_hits else float("nan"),
            "size_episodes": len(rhos),
            "size_spearman": float(np.mean(rhos)) if rhos else float("nan"),
            "size_word_first": 100.0 * float(np.mean(size_first)) if size_first else float("nan"),
        }
    return out


def size_word_first(r: Reading) -> bool | None:
    """Is the size word's own map higher at the target than at every other object the
    command names (its shape, and its colour when it has one: what "small" and "big" are
    relative to: docs/world.md, "Planner")? None without a size word, a target or a second such
    object. A map ordered by size passes whatever the parse feeds it."""
    target = r.situation.target_object
    if r.size_word is None or target is None:
        return None
    colour = r.frame.color
    named = [o for o in r.situation.placed_objects
             if o.shape == r.shape and (colour is None or o.color == colour) and o.position != target.position]
    if not named:
        return None
    at_target = r.size_word[target.position.row, target.position.col]
    return bool(at_target > max(r.size_word[o.position.row, o.position.col] for o in named))


def size_heads(readings: Iterable[Reading]) -> dict[str, tuple[int, float]]:
    """Per head ("small", "big"): (maps, median of max − min over the grid), over the
    episodes with a size word. The antonym overlap loss min–max normalises each map, so a
    head whose map is flat scores no overlap at all: a range of ~0 is a head that took
    that way out and passes no size information up."""
    ranges: dict[str, list[float]] = defaultdict(list)
    for r in readings:
        for head, grid in (r.size_heads or {}).items():
            ranges[head].append(float(grid.max() - grid.min()))
    return {head: (len(v), float(np.median(v))) for head, v in sorted(ranges.items(), reverse=True)}


def size_heads_table(found: Mapping[str, tuple[int, float]]) -> str:
    lines = ["| head | maps | median range (max − min) |", "|---|---:|---:|"]
    lines += [f"| {head} | {n} | {value:.3g} |" for head, (n, value) in found.items()]
    return "\n".join(lines) + "\n"


def noun_colours(readings: Iterable[Reading]) -> dict[str, dict[str, tuple[int, float]]]:
    """Does the noun's map favour some colours of its shape? Per noun (shape) and colour:
    (objects, mean of the map's value at such an object divided by the highest value at
    any object of the shape in the same scene). Only scenes with two or more objects of the
    noun's shape count; 1.0 means the colour is never ranked below another of its shape.
    A combination that is never a training target (split C's red square) is the one to
    watch: fitting train only ever rewards a map that ranks it low."""
    values: dict[str, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    for r in readings:
        if r.noun is None:
            continue
        shape = r.shape
        same = [o for o in r.situation.placed_objects if o.shape == shape]
        if len(same) < 2:
            continue
        at = [float(r.noun[o.position.row, o.position.col]) for o in same]
        top = max(at)
        if top <= 0:
            continue
        for o, v in zip(same, at):
            values[shape][o.color].append(v / top)
    return {shape: {c: (len(v), float(np.mean(v))) for c, v in sorted(by_colour.items())}
            for shape, by_colour in sorted(values.items())}


def weakest_colour(found: Mapping[str, Mapping[str, tuple[int, float]]]) -> tuple[str, str, float] | None:
    """(noun, colour, mean relative value) of the colour a noun's map ranks lowest, or None."""
    entries = [(shape, colour, value) for shape, by_colour in found.items() for colour, (_, value) in by_colour.items()]
    return min(entries, key=lambda e: e[2]) if entries else None


def noun_colours_table(found: Mapping[str, Mapping[str, tuple[int, float]]]) -> str:
    """`noun_colours` as a markdown table: a row per noun, a column per colour."""
    colours = sorted({c for by_colour in found.values() for c in by_colour})
    lines = ["| noun | " + " | ".join(colours) + " |", "|---|" + "---:|" * len(colours)]
    for shape, by_colour in found.items():
        cells = [f"{by_colour[c][1]:.2f} ({by_colour[c][0]})" if c in by_colour else "–" for c in colours]
        lines.append(f"| {shape} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def metrics_table(summary: Mapping[str, Mapping]) -> str:
    """`summarize`'s result as a markdown table."""
    lines = ["| split | episodes | localization % | chance % | beside % | on agent % | noun on its shape % "
             "| size episodes | size Spearman | size word first % |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for split, m in summary.items():
        name = f"{SPLIT_LETTERS[split]} {split}" if split in SPLIT_LETTERS else split
        lines.append(f"| {name} | {m['episodes']} | {m['localization']:.1f} | {m['localization_chance']:.1f} "
                     f"| {m['beside']:.1f} | {m['on_agent']:.1f} | {m['noun_on_shape']:.1f} | {m['size_episodes']} "
                     f"| {m['size_spearman']:.3f} | {m['size_word_first']:.1f} |")
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- snapshots
def snapshots(run_dir: str | Path) -> list[tuple[int, Path]]:
    """(update, path) of the run's `step_<N>.pt` snapshots, in update order; GscanError if none."""
    found = sorted((int(m.group(1)), p) for p in Path(run_dir).iterdir()
                   if p.is_file() and (m := SNAPSHOT_PATTERN.fullmatch(p.name)))
    if not found:
        raise GscanError(f"{run_dir} has no step_<N>.pt snapshots; train with --set snapshot_every=N")
    return found


def evenly(items: Sequence, most: int) -> list:
    """At most `most` of `items`, evenly spaced, first and last included."""
    if len(items) <= most:
        return list(items)
    if most == 1:
        return [items[-1]]
    picks = np.linspace(0, len(items) - 1, most).round().astype(int)
    return [items[i] for i in dict.fromkeys(picks.tolist())]


def progression_metrics(paths: Sequence[tuple[int, Path]], episodes: Sequence[Episode],
                        batch_size: int = 512, device: str | torch.device = "cpu") -> list[dict]:
    """For each snapshot: its update, the dev exact match of its last validation (and that
    validation's update), and `summarize`'s "all" row over `episodes` (decoded on `device`)."""
    rows = []
    for step, path in paths:
        policy = Policy.from_checkpoint(path, device=device)
        metrics = policy.metadata.get("metrics") or {}
        readings = step0_readings(policy, episodes, batch_size)
        rows.append({"update": step, "dev_exact_match": metrics.get("dev_exact_match"),
                     "validated_at": metrics.get("step"), **summarize(readings)["all"],
                     "weakest_colour": weakest_colour(noun_colours(readings))})
    return rows


def _weakest_text(weakest: tuple[str, str, float] | None) -> str:
    return "-" if weakest is None else f"{weakest[1]} {weakest[0]} {weakest[2]:.2f}"


def progression_table(rows: Sequence[Mapping]) -> str:
    lines = ["| update | dev exact match % | localization % | beside % | on agent % | noun on its shape % "
             "| size Spearman | size word first % | noun's weakest colour |",
             "|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        em = r["dev_exact_match"]
        em_text = "-" if em is None else f"{em:.1f}"
        if em is not None and r["validated_at"] not in (None, r["update"]):
            em_text += f" (at {r['validated_at']})"
        lines.append(f"| {r['update']} | {em_text} | {r['localization']:.1f} | {r['beside']:.1f} "
                     f"| {r['on_agent']:.1f} | {r['noun_on_shape']:.1f} | {r['size_spearman']:.3f} "
                     f"| {r['size_word_first']:.1f} | {_weakest_text(r.get('weakest_colour'))} |")
    return "\n".join(lines) + "\n"
