"""Synthetic parse graphs and one-hot states for model tests (no parser or world needed), and a
tiny checkpoint file for the CLI and node tests. No ROS here: non-ROS tests import this."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from gscan_ros.language import all_commands, get_parser
from gscan_ros.language.graph import CommandGraph, GraphEdge, GraphNode
from gscan_ros.language.lexicon import Lexicon
from gscan_ros.model.checkpoint import checkpoint_dict, save_checkpoint
from gscan_ros.model.compositional import CompositionalNetwork
from gscan_ros.model.config import ModelConfig
from gscan_ros.model.modules import ModuleSpec, ModuleTable

SIZE_KEY = "big|small"


def chain(words: list[str], command: str | None = None) -> CommandGraph:
    """A semantic-style chain: words[0](words[1](...)); 'big'/'small' share SIZE_KEY."""
    nodes = []
    for i, w in enumerate(words):
        module, head = (SIZE_KEY, ("big", "small").index(w)) if w in ("big", "small") else (w, 0)
        nodes.append(GraphNode(i, w, module, 1 if i + 1 < len(words) else 0, head))
    edges = [GraphEdge(i, i + 1, "arg", 0) for i in range(len(words) - 1)]
    return CommandGraph.build(command or " ".join(words), "semantic", nodes, edges, 0)


def binary() -> CommandGraph:
    """A constituency-style graph with a two-slot module: VP_2(push, NP_2(red, circle))."""
    nodes = [GraphNode(0, "VP", "VP_2", 2), GraphNode(1, "push", "push_leaf", 0),
             GraphNode(2, "NP", "NP_2", 2), GraphNode(3, "red", "red_leaf", 0), GraphNode(4, "circle", "circle", 0)]
    edges = [GraphEdge(0, 1, "verb", 0), GraphEdge(0, 2, "obj", 1), GraphEdge(2, 3, "amod", 0),
             GraphEdge(2, 4, "head", 1)]
    return CommandGraph.build("push a red circle", "constituency", nodes, edges, 0)


GRAPHS = [
    chain(["walk", "circle"]),
    chain(["while spinning", "walk", "red", "small", "circle"]),
    chain(["push", "big", "square"]),
    chain(["pull", "green", "cylinder"]),
    chain(["cautiously", "walk", "small", "square"]),
]


def table(graphs=GRAPHS) -> ModuleTable:
    base = ModuleTable.from_graphs(graphs)
    return ModuleTable(
        ModuleSpec(s.key, s.arity, 2, ((0, 1),)) if s.key == SIZE_KEY else s for s in base.specs
    )


def make_net(cfg=None, graphs=GRAPHS, seed=0):
    """A seeded network (eval mode) with the modules of `graphs`, size words sharing SIZE_KEY."""
    torch.manual_seed(seed)
    return CompositionalNetwork(cfg or ModelConfig(), table(graphs)).eval()


def random_states(rng: np.random.Generator, n: int) -> np.ndarray:
    """n one-hot gSCAN-like encodings: a few objects (size, shape, color bits) + agent + heading."""
    out = np.zeros((n, 6, 6, 16), dtype=np.uint8)
    for i in range(n):
        cells = rng.choice(36, size=rng.integers(2, 8), replace=False)
        for c in cells[1:]:
            r, col = divmod(int(c), 6)
            out[i, r, col, rng.integers(0, 4)] = 1
            out[i, r, col, 4 + rng.integers(0, 3)] = 1
            out[i, r, col, 7 + rng.integers(0, 4)] = 1
        r, col = divmod(int(cells[0]), 6)
        out[i, r, col, 11] = 1
        out[i, r, col, 12 + rng.integers(0, 4)] = 1
    return out


def episode_states(rng: np.random.Generator, length: int) -> np.ndarray:
    """`length` states of one episode: the objects stay put, the agent (and its heading)
    moves, as teacher forcing sees them (most set bits shared by every state)."""
    objects = random_states(rng, 1)[0]
    objects[..., 11:] = 0
    out = np.repeat(objects[None], length, 0)
    for t in range(length):
        r, col = divmod(int(rng.integers(36)), 6)
        out[t, r, col, 11] = 1
        out[t, r, col, 12 + rng.integers(0, 4)] = 1
    return out


def teacher_batch(table: ModuleTable, graphs: list[CommandGraph], states: list[np.ndarray],
                  targets: list[np.ndarray], quantum: int = 1):
    """The TeacherBatch of episodes (graph, states [T+1, 6, 6, 16], targets [T+1]) as
    `EpisodeStore.batch` builds it, and `order`: batch row r holds episode order[r]."""
    from gscan_ros.model.layout import Layout
    from gscan_ros.model.sparse_encoder import sparse_states
    from gscan_ros.model.teacher_forcing import TeacherBatch

    lengths = np.array([len(t) for t in targets])
    order = np.argsort(-lengths, kind="stable")
    lengths = lengths[order]
    alive = np.array([(lengths > t).sum() for t in range(int(lengths[0]))])
    active = np.minimum(-(-alive // quantum) * quantum, len(graphs))
    rows = np.concatenate([np.arange(n) for n in active])
    steps = np.repeat(np.arange(int(lengths[0])), active)
    valid = steps < lengths[rows]
    empty = np.zeros_like(states[0][0])
    packed = np.stack([states[order[r]][s] if v else empty for r, s, v in zip(rows, steps, valid)])
    packed_targets = np.array([targets[order[r]][s] if v else -1 for r, s, v in zip(rows, steps, valid)])
    idx, off = sparse_states(packed)
    batch = TeacherBatch(Layout([graphs[i] for i in order], table), idx, off, torch.from_numpy(packed_targets),
                         torch.from_numpy(rows), torch.from_numpy(valid), torch.from_numpy(lengths.astype(np.float32)),
                         [int(n) for n in active])
    return batch, order


def walk_episodes(n: int, seed: int = 0, max_distance: int = 3):
    """n real walk episodes ("walk to a <color> <shape>", 2 objects, short routes), planned
    by the world's own planner."""
    from gscan_ros.data.episode import Episode
    from gscan_ros.world.planner import demonstrate
    from gscan_ros.world.types import COLORS, SHAPES, Heading, Position, Situation, WorldObject

    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n:
        cells = rng.choice(36, size=3, replace=False)
        agent, target_cell, other_cell = (Position(*divmod(int(c), 6)) for c in cells)
        if abs(agent.row - target_cell.row) + abs(agent.col - target_cell.col) > max_distance:
            continue
        shape, other_shape = rng.choice(SHAPES, 2, replace=False)
        color = str(rng.choice(COLORS))
        target = WorldObject(str(shape), color, int(rng.integers(1, 5)), target_cell)
        other = WorldObject(str(other_shape), str(rng.choice(COLORS)), int(rng.integers(1, 5)), other_cell)
        situation = Situation(agent, Heading.EAST, (target, other), target)
        command = f"walk to a {color} {shape}"
        out.append(Episode(command, situation, tuple(demonstrate(situation, command)), "train", len(out)))
    return out


def tiny_checkpoint(path: Path, seed: int = 0, weight_scale: float = 1.0) -> Path:
    """A randomly initialised, very small compositional policy for the semantic parser.

    The node and e2e tests check the protocol (actions until `<eos>` or max_steps), never the
    policy's quality, so an untrained model is enough and takes a second to build.
    Scaling the initial weights up makes its (random) actions depend more on the
    observation, so episodes move the agent instead of repeating one action.
    """
    torch.manual_seed(seed)
    parser = get_parser("semantic", Lexicon.none())
    table = ModuleTable.from_graphs(parser.parse(c) for c in all_commands())
    model = CompositionalNetwork(ModelConfig(cnn_channels=4, att_dim=4, rnn_layers=1, rnn_dim=8), table)
    with torch.no_grad():
        for weights in model.parameters():
            weights.mul_(weight_scale)
    save_checkpoint(path, checkpoint_dict(model, parser="semantic", lexicon=Lexicon.none(), step=0, metrics={}))
    return path


def train_to_exact_match(update, batches, model, episodes, *, batch_size: int, max_updates: int,
                         every: int = 50) -> tuple[float, int, float]:
    """Overfit: `update` on `batches` until closed-loop exact match on `episodes` is 100 %
    (checked every `every` updates) or `max_updates`; (exact match, updates, last loss)."""
    from gscan_ros.training.evaluate import evaluate_episodes

    exact = 0.0
    for step in range(1, max_updates + 1):
        loss = update(next(batches)[1])
        if step % every == 0:
            exact = evaluate_episodes(model, episodes, batch_size=batch_size).exact_match
            if exact == 100.0:
                break
    return exact, step, loss
