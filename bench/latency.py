"""Latency of the ROS stack across processes: command -> first action, and per lock-step step.

Starts world_simulator_node, parser_node and policy_node as separate processes (Fast DDS
on loopback, the fast-discovery profile), runs sampled gSCAN commands one episode at a
time with a GscanCommander (reset_world between them), and times on DDS timestamps:

- first action: command published -> first action received (parse + graph + reset + step);
- step: action t received -> action t+1 received (world step and publish, one model step);
- model step: `Policy.step` alone, in this process (the CPU cost inside the policy node).

    .venv/bin/python bench/latency.py [--checkpoint PATH] [--episodes 30] [--no-images]

Without --checkpoint the shipped model (gscan_ros/assets/default_model.pt) is used.
"""
from __future__ import annotations

import argparse
import signal
import tempfile
import time
from pathlib import Path

import numpy as np

from gscan_ros.nodes.processes import NodeProcess, fresh_domain_id, join_local_graph, ros_env


def percentiles(ms: list[float]) -> str:
    a = np.asarray(ms)
    return f"p50 {np.percentile(a, 50):6.2f} ms  p99 {np.percentile(a, 99):6.2f} ms  (n={a.size})"


def resolve_checkpoint(path: Path | None) -> tuple[Path, str]:
    """The checkpoint to benchmark and how to name it in the report."""
    from gscan_ros.errors import CheckpointError
    from gscan_ros.model.policy import default_checkpoint_path

    path = path or default_checkpoint_path()
    if not path.is_file():
        raise CheckpointError(f"checkpoint {str(path)!r} does not exist; pass --checkpoint")
    return path, "shipped default model" if path == default_checkpoint_path() else str(path)


def model_step_ms(checkpoint: Path, commands: list, situations: list, steps: int = 30) -> list[float]:
    """Policy.step wall time on CPU, one thread (as the node runs it)."""
    import torch

    from gscan_ros.model.policy import Policy
    from gscan_ros.world import World

    torch.set_num_threads(1)
    policy = Policy.from_checkpoint(checkpoint)
    out = []
    for command, situation in zip(commands, situations):
        policy.reset(policy.parse(command))
        world = World(situation)
        for _ in range(steps):
            t0 = time.perf_counter()
            result = policy.step(world.encode())
            out.append((time.perf_counter() - t0) * 1e3)
            if result.action.token == "<eos>":
                break
            world.step(result.action)
    return out[5:]  # drop warm-up


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", type=Path, default=None)
    ap.add_argument("--episodes", type=int, default=30)
    ap.add_argument("--max-steps", type=int, default=60)
    ap.add_argument("--no-images", action="store_true", help="world node does not render world_image")
    args = ap.parse_args()

    from gscan_ros.data.sources import sample_episode
    from gscan_ros.nodes.commander import GscanCommander

    tmp = Path(tempfile.mkdtemp(prefix="gscan_latency_"))
    checkpoint, label = resolve_checkpoint(args.checkpoint)
    join_local_graph()  # before the commander's rclpy.init
    env = ros_env(fresh_domain_id(), tmp)
    nodes = [
        NodeProcess("world_simulator_node", env, tmp, {"seed": 0, "publish_images": not args.no_images}),
        NodeProcess("parser_node", env, tmp, {"checkpoint": checkpoint}),
        NodeProcess("policy_node", env, tmp, {"checkpoint": checkpoint, "max_steps": args.max_steps}),
    ]
    commander = GscanCommander.connect(int(env["ROS_DOMAIN_ID"]))
    first_ms, step_ms, commands, situations = [], [], [], []
    try:
        commander.wait_until_ready(timeout=90)
        for episode_index in range(args.episodes):
            episode = sample_episode(episode_index)  # the world serves seed i after i resets
            commands.append(episode.command)
            situations.append(episode.situation)
            result = commander.run_episode(episode.command, timeout=60)
            if not result.finished:
                raise SystemExit(f"episode {episode_index}: {result.outcome} ({result.reason or 'no <eos>'})")
            times = result.action_times_ns
            first_ms.append((times[0] - result.sent_ns) / 1e6)
            step_ms += [(b - a) / 1e6 for a, b in zip(times, times[1:])]
            commander.reset_world()
    finally:
        commander.shutdown()
        for node in nodes:
            node.stop(signal.SIGINT)

    print(f"model: {label}; world images {'off' if args.no_images else 'on'}; {args.episodes} episodes")
    print(f"command -> first action:  {percentiles(first_ms[1:])}")  # the first one includes warm-up
    print(f"per lock-step step:       {percentiles(step_ms)}")
    print(f"Policy.step (in-process): {percentiles(model_step_ms(checkpoint, commands, situations))}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
