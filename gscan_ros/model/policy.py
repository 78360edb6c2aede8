"""Policy: a trained model plus the parser it was trained with, acting one step at a time.

The ROS policy node uses exactly `from_checkpoint`, `parser_name`, `reset(graph)` and
`step(observation)`; batched closed-loop evaluation uses `rollout(graphs)`.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np
import torch
from torch import nn

from gscan_ros.errors import CheckpointError, GraphError, GscanError
from gscan_ros.language.graph import CommandGraph
from gscan_ros.language.lexicon import Lexicon
from gscan_ros.model.checkpoint import checkpoint_lexicon, read_checkpoint, restore_model
from gscan_ros.world.types import NUM_CHANNELS, Action

DEFAULT_CHECKPOINT = "default_model.pt"
# Actions per episode before <eos> is forced: decoding runs at most MAX_STEPS + 1 steps (121,
# the original's `max_decoding_steps`). The one definition: evaluation, explain, policy_node
# (and so bringup/demo) take it from here; config/params.yaml repeats it under test.
MAX_STEPS = 120


def default_checkpoint_path() -> Path:
    """The model shipped inside the package (`gscan_ros/assets/default_model.pt`)."""
    return Path(str(resources.files("gscan_ros") / "assets" / DEFAULT_CHECKPOINT))


@dataclass
class StepOutput:
    action: Action
    attention: dict[str, np.ndarray] = field(default_factory=dict)  # node word -> float32[6, 6]
    # node word -> the map of its antonym head on the same inputs (words of antonym pairs only)
    antonyms: dict[str, np.ndarray] = field(default_factory=dict)


def require_grid(grid_size: int, model_grid: int, what: str) -> None:
    """Refuse `what` (an episode, a situation, an observation) on a grid other than the
    model's: a model reads one grid size."""
    if grid_size != model_grid:
        raise GscanError(f"{what} is on a {grid_size}x{grid_size} grid; the model was trained on "
                         f"{model_grid}x{model_grid}")


class Policy:
    """Model + parser name + lexicon; stateful single-episode stepping for the ROS node."""

    def __init__(self, model: nn.Module, parser_name: str = "semantic", lexicon: Lexicon | None = None,
                 metadata: dict | None = None):
        self.model = model.eval()
        self._parser_name = parser_name
        self.lexicon = lexicon if lexicon is not None else Lexicon.none()
        self.metadata = metadata or {}
        self._parser = None
        self._rollout = None

    @classmethod
    def from_checkpoint(cls, path: str | os.PathLike | None = None, device: str | torch.device = "cpu") -> "Policy":
        """Load a checkpoint (None: the shipped default model) onto `device`, as torch names it
        (the launcher picks it: `gscan_ros.runtime.resolve_device`); CheckpointError if unusable."""
        ckpt = read_checkpoint(default_checkpoint_path() if path is None else path)
        model = restore_model(ckpt).to(device)
        meta = {"step": ckpt.get("step", 0), "metrics": ckpt.get("metrics", {}), "kind": ckpt["kind"]}
        return cls(model, str(ckpt["parser"]), checkpoint_lexicon(ckpt), meta)

    @property
    def device(self) -> torch.device:
        return self.model.device

    @property
    def parser_name(self) -> str:
        return self._parser_name

    @property
    def parser(self):
        """The parser the model was trained with (built lazily; uses the checkpoint's lexicon)."""
        if self._parser is None:
            from gscan_ros.language.registry import get_parser

            self._parser = get_parser(self._parser_name, self.lexicon)
        return self._parser

    def parse(self, command: str) -> CommandGraph:
        return self.parser.parse(command)

    @torch.no_grad()
    def rollout(self, graphs: list[CommandGraph]):
        """A batched closed-loop decoder for `graphs` (`compositional.Rollout`, `decoder.Seq2SeqRollout`)."""
        return self.model.rollout(graphs)

    # ---- single-episode API (ROS policy node)
    def reset(self, graph: CommandGraph) -> None:
        """Start an episode; GraphError if the graph needs modules the model does not have."""
        if graph.parser != self._parser_name:
            raise GraphError(f"graph comes from the {graph.parser!r} parser; this model expects {self._parser_name!r}")
        self._rollout = self.rollout([graph])

    @property
    def grid_size(self) -> int:
        return self.model.cfg.grid_size

    def require_grid(self, grid_size: int, what: str) -> None:
        require_grid(grid_size, self.grid_size, what)

    def require_observation(self, shape: tuple[int, ...], what: str) -> None:
        """Refuse an observation array the model cannot read, naming its grid size first."""
        self.require_grid(shape[0], what)
        if tuple(shape) != self.observation_shape:
            raise GscanError(f"{what} has shape {tuple(shape)}; the model reads {self.observation_shape}")

    def require_episodes_grid(self, episodes) -> None:
        """`require_grid` for every episode, named by example and split."""
        for ep in episodes:
            self.require_grid(ep.situation.grid_size, f"episode {ep.example_id} of split {ep.split!r}")

    @property
    def observation_shape(self) -> tuple[int, int, int]:
        """(G, G, 16): the observations the model was trained on."""
        return (self.grid_size, self.grid_size, getattr(self.model.cfg, "in_channels", NUM_CHANNELS))

    @torch.no_grad()
    def step(self, observation: np.ndarray) -> StepOutput:
        """One decoding step on uint8[G, G, 16] (G: the model's grid): the argmax action (or EOS),
        each word's map and, for a word of an antonym pair, its antonym head's map."""
        if self._rollout is None:
            raise GraphError("Policy.step called before reset(graph)")
        obs = np.asarray(observation)
        expected = self.observation_shape
        if obs.shape != expected:
            raise CheckpointError(f"observation has shape {obs.shape}; the model expects {expected}")
        logits, maps = self._rollout.step(obs[None].astype(np.uint8, copy=False))
        action = Action(int(logits[0].argmax()))
        attention, antonyms = self._rollout.word_maps(maps, 0) if maps is not None else ({}, {})
        return StepOutput(action, attention, antonyms)
