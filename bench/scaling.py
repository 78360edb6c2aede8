"""Data-parallel scaling on one machine: `gscan-ros train` as 1 process x T threads vs
N `torchrun` processes x T/N threads (gloo, 127.0.0.1), in training examples/s.

    .venv/bin/python bench/scaling.py [--data DIR] [--config FILE] [--processes 2] [--threads 2]
                                      [--updates 60] [--batch-size 200] [--set KEY=VALUE ...]

Without --data, 6000 candidate examples are generated into a temp dir (seed 0), as for
bench/train.py. Both runs train the same batches (the global batch is --batch-size either
way); the rate is the mean `examples_per_s` of the runs' metrics lines after the first
(warm-up), so data loading and the final validation are not counted. Seed screening is
off (`screen_seeds=0`): its candidates' updates would count as the run's.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

from _data import dataset_or_generated, loopback_torchrun

LOG_EVERY = 10


def train_command(data: str, out: Path, threads: int, args: argparse.Namespace) -> list[str]:
    return ["-m", "gscan_ros.cli", "train", "--data", data, "--out", str(out), "--quiet",
            *(["--config", args.config] if args.config else []),
            "--set", f"threads={threads}", "--set", f"max_updates={args.updates}",
            "--set", f"batch_size={args.batch_size}", "--set", f"log_every={LOG_EVERY}",
            "--set", "validate_every=1000000", "--set", "checkpoint_every=1000000", "--set", "max_dev_examples=8",
            "--set", "screen_seeds=0",
            *(arg for item in args.set for arg in ("--set", item))]


def rate(run: Path) -> float:
    lines = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    rates = [r["examples_per_s"] for r in lines if r["event"] == "train"][1:]
    if not rates:
        raise SystemExit(f"{run}: too few updates for a rate; raise --updates above {2 * LOG_EVERY}")
    return sum(rates) / len(rates)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", help="dataset (default: generate 6000 candidates into a temp dir)")
    ap.add_argument("--config", help="training config (default: the built-in defaults)")
    ap.add_argument("--processes", type=int, default=2, help="torchrun processes")
    ap.add_argument("--threads", type=int, default=2, help="threads in all (the processes share them)")
    ap.add_argument("--updates", type=int, default=60)
    ap.add_argument("--batch-size", type=int, default=200)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="config override for both runs, as `gscan-ros train --set`")
    args = ap.parse_args()
    if args.threads % args.processes:
        raise SystemExit("--threads must be a multiple of --processes")
    with dataset_or_generated(args.data, examples=6000) as data, tempfile.TemporaryDirectory() as tmp:
        one, many = Path(tmp) / "one", Path(tmp) / "many"
        subprocess.run([sys.executable, *train_command(data, one, args.threads, args)], check=True,
                       stdout=subprocess.DEVNULL)
        torchrun, env = loopback_torchrun(args.processes, args.threads // args.processes)
        subprocess.run([*torchrun, *train_command(data, many, args.threads // args.processes, args)],
                       check=True, env=env, stdout=subprocess.DEVNULL)
        single, parallel = rate(one), rate(many)
    print(f"1 process x {args.threads} threads:  {single:7.1f} examples/s")
    print(f"{args.processes} processes x {args.threads // args.processes} threads: {parallel:7.1f} examples/s"
          f"  ({parallel / single:.2f}x; batch {args.batch_size}, {args.updates} updates)")


if __name__ == "__main__":
    main()
