"""Flood the stack with bad commands: every one must be answered on `status`, memory must stay flat.

Starts world_simulator_node, parser_node and policy_node as separate processes and
sends (GscanCommander.send_command) `--rate` commands per second for `--seconds`: unknown words,
empty strings, 10 kB strings and ungrammatical ones, plus one valid command in 100
(each preempts the policy's running episode). Prints how many rejections came back on
`status`, whether every node survived, and each node's resident memory after the first
second (warm-up) and at the end.

    .venv/bin/python bench/flood.py [--rate 1000] [--seconds 10] [--checkpoint PATH]
"""
from __future__ import annotations

import argparse
import itertools
import signal
import tempfile
import time
from pathlib import Path

from latency import resolve_checkpoint

from gscan_ros.errors import GscanError
from gscan_ros.nodes.processes import NodeProcess, fresh_domain_id, join_local_graph, ros_env

BAD_COMMANDS = (
    "walk to a purple circle",
    "",
    "x" * 10_000,
    "circle a to walk",
    "push push push",
    "идти к красному кругу",
)
VALID_EVERY = 100
VALID_COMMANDS = ("walk to a red circle", "push a big square cautiously", "pull a small cylinder")


def rss_mib(pid: int) -> float:
    """Resident set size of a process (and its threads) from /proc."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rate", type=int, default=1000, help="commands per second")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--checkpoint", type=Path, default=None)
    args = ap.parse_args()

    from gscan_ros.nodes.commander import GscanCommander

    tmp = Path(tempfile.mkdtemp(prefix="gscan_flood_"))
    checkpoint, label = resolve_checkpoint(args.checkpoint)
    join_local_graph()  # before the commander's rclpy.init
    env = ros_env(fresh_domain_id(), tmp)
    nodes = {
        "world_simulator_node": NodeProcess("world_simulator_node", env, tmp, {"seed": 0}),
        "parser_node": NodeProcess("parser_node", env, tmp, {"checkpoint": checkpoint}),
        "policy_node": NodeProcess("policy_node", env, tmp, {"checkpoint": checkpoint, "max_steps": 30}),
    }
    commander = GscanCommander.connect(int(env["ROS_DOMAIN_ID"]))

    def rejected() -> int:
        return sum(line.startswith("parser_node: rejected") for line in commander.status_log)

    try:
        commander.wait_until_ready(timeout=90)
        before = {}
        total = int(args.rate * args.seconds)
        bad_sent = 0
        bad = itertools.cycle(BAD_COMMANDS)
        valid = itertools.cycle(VALID_COMMANDS)
        start = time.monotonic()
        for i in range(total):
            if i == args.rate:  # after one second of warm-up (first graphs, allocator pools)
                before = {name: rss_mib(p.process.pid) for name, p in nodes.items()}
            if i % VALID_EVERY == VALID_EVERY - 1:
                commander.send_command(next(valid))
            else:
                commander.send_command(next(bad))
                bad_sent += 1
            # Pace to the rate, serving the commander's subscriptions while ahead of schedule.
            commander.spin_for(start + (i + 1) / args.rate - time.monotonic())
        sent_s = time.monotonic() - start
        try:
            commander.spin_until(lambda: rejected() >= bad_sent, timeout=30, what=f"{bad_sent} rejections")
        except GscanError as exc:
            print(f"incomplete: {exc}")
        drained_s = time.monotonic() - start
        after = {name: rss_mib(p.process.pid) for name, p in nodes.items()}
        alive = {name: p.alive() for name, p in nodes.items()}
        rejections = rejected()
    finally:
        commander.shutdown()
        for node in nodes.values():
            node.stop(signal.SIGINT)

    print(f"model: {label}")
    print(f"sent {total} commands ({bad_sent} bad) in {sent_s:.1f} s = {total / sent_s:.0f}/s; "
          f"{rejections} rejections on status after {drained_s:.1f} s")
    for name in nodes:
        print(f"{name:22s} alive={alive[name]}  RSS {before[name]:7.1f} MiB -> {after[name]:7.1f} MiB "
              f"({after[name] - before[name]:+.1f})")
    return 0 if rejections == bad_sent and all(alive.values()) else 1


if __name__ == "__main__":
    raise SystemExit(main())
