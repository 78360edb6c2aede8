"""Latency of the ROS stack across processes: command -> first action, and per lock-step step.

Starts world_simulator_node, parser_node and policy_node as separate processes (Fast DDS
on loopback, the fast-discovery profile), sends sampled gSCAN commands one episode at a
time, and times on DDS timestamps:

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

from gscan_ros.nodes.harness import NodeProcess, Probe, fresh_domain_id, ros_env


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

    from std_msgs.msg import String
    from std_srvs.srv import Trigger

    from gscan_ros.nodes.common import EVENT_QOS
    from gscan_ros.data.sources import sample_episode

    tmp = Path(tempfile.mkdtemp(prefix="gscan_latency_"))
    checkpoint, label = resolve_checkpoint(args.checkpoint)
    env = ros_env(fresh_domain_id(), tmp)
    nodes = [
        NodeProcess("world_simulator_node", env, tmp, {"seed": 0, "publish_images": not args.no_images}),
        NodeProcess("parser_node", env, tmp, {"checkpoint": checkpoint}),
        NodeProcess("policy_node", env, tmp, {"checkpoint": checkpoint, "max_steps": args.max_steps}),
    ]
    probe = Probe(int(env["ROS_DOMAIN_ID"]))
    received: list[tuple[int, str]] = []  # (DDS receive time, token)
    probe.node.create_subscription(
        String, "action", lambda msg, info: received.append((info["received_timestamp"], msg.data)), EVENT_QOS
    )
    commands_pub = probe.node.create_publisher(String, "command", EVENT_QOS)
    reset = probe.node.create_client(Trigger, "reset_world")
    first_ms, step_ms, commands, situations = [], [], [], []
    try:
        probe.wait_for_endpoints({"/command": {"parser_node"}, "/observation": {"policy_node"},
                                  "/action": {"world_simulator_node"}})
        probe.spin_until(reset.service_is_ready, what="reset_world")
        probe.spin_until(lambda: commands_pub.get_subscription_count() > 0, what="the parser")
        for episode_index in range(args.episodes):
            episode = sample_episode(episode_index)  # the world serves seed i after i resets
            commands.append(episode.command)
            situations.append(episode.situation)
            start = len(received)
            t0 = time.time_ns()
            commands_pub.publish(String(data=episode.command))
            probe.spin_until(lambda: any(tok == "<eos>" for _, tok in received[start:]), what="<eos>")
            times = [t for t, _ in received[start:]]
            first_ms.append((times[0] - t0) / 1e6)
            step_ms += [(b - a) / 1e6 for a, b in zip(times, times[1:])]
            future = reset.call_async(Trigger.Request())
            probe.spin_until(future.done, what="reset")
    finally:
        probe.close()
        for node in nodes:
            node.stop(signal.SIGINT)

    print(f"model: {label}; world images {'off' if args.no_images else 'on'}; {args.episodes} episodes")
    print(f"command -> first action:  {percentiles(first_ms[1:])}")  # the first one includes warm-up
    print(f"per lock-step step:       {percentiles(step_ms)}")
    print(f"Policy.step (in-process): {percentiles(model_step_ms(checkpoint, commands, situations))}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
