"""Test-only ROS helpers; the process harness itself is `gscan_ros.nodes.harness`."""
from __future__ import annotations

import time
from pathlib import Path

def tiny_checkpoint(path: Path, seed: int = 0, weight_scale: float = 1.0) -> Path:
    """A randomly initialised, very small compositional policy for the semantic parser.

    The e2e tests check the protocol (actions until `<eos>` or max_steps), never the
    policy's quality, so an untrained model is enough and takes a second to build.
    Scaling the initial weights up makes its (random) actions depend more on the
    observation, so episodes move the agent instead of repeating one action.
    """
    import torch

    from gscan_ros.language import all_commands, get_parser
    from gscan_ros.language.lexicon import Lexicon
    from gscan_ros.model.checkpoint import checkpoint_dict, save_checkpoint
    from gscan_ros.model.compositional import CompositionalNetwork, ModelConfig, ModuleTable

    torch.manual_seed(seed)
    parser = get_parser("semantic", Lexicon.none())
    table = ModuleTable.from_graphs(parser.parse(c) for c in all_commands())
    model = CompositionalNetwork(ModelConfig(cnn_channels=4, att_dim=4, rnn_layers=1, rnn_dim=8), table)
    with torch.no_grad():
        for weights in model.parameters():
            weights.mul_(weight_scale)
    save_checkpoint(path, checkpoint_dict(model, parser="semantic", lexicon=Lexicon.none(), step=0, metrics={}))
    return path


def parameters(**values) -> list:
    """rclpy parameter overrides for constructing a node in-process."""
    from rclpy.parameter import Parameter

    return [Parameter(name, value=value) for name, value in values.items()]


def source_info(t_ns: int | None = None) -> dict:
    """The MessageInfo a subscription callback gets, for calling node callbacks directly."""
    return {"source_timestamp": time.time_ns() if t_ns is None else t_ns}
