"""Benchmark dataset generation and demonstration throughput (prints figures).

1. end to end: `generate_dataset` (layouts -> situations -> planner -> splits ->
   dataset.txt written) in examples generated per second, per worker count;
2. demonstrate + per-step encoding: re-plan each example and build its T+1
   observation tensors (`Episode.states()`), as training data loading does.

Usage: .venv/bin/python bench/generate.py [--examples N] [--workers 2] [--replay N]
(default: the full compositional dataset, ~1.4 GB in a temporary directory).
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--examples", type=int,
                        help="generate a subset of N examples (default: full dataset; a subset still draws "
                             "every layout block and pays pool start-up, so its ex/s is lower)")
    parser.add_argument("--workers", default="2", help="comma-separated worker counts (default 2)")
    parser.add_argument("--replay", type=int, default=5_000, help="examples for the demonstrate bench (default 5000)")
    args = parser.parse_args()

    from gscan_ros.data.dataset import iter_examples
    from gscan_ros.data.generate import GenerationConfig, generate_dataset
    from gscan_ros.world import demonstrate

    config = GenerationConfig(seed=0, max_examples=args.examples)
    with tempfile.TemporaryDirectory() as tmp:
        for workers in [int(w) for w in args.workers.split(",")]:
            report = generate_dataset(os.path.join(tmp, f"w{workers}"), config, workers=workers)
            kept = sum(report.split_sizes.values())
            size_mb = report.path.stat().st_size / 1e6
            print(f"generate  workers={workers}: {report.generated} generated, {kept} kept in "
                  f"{report.seconds:.1f} s = {report.generated / report.seconds:,.0f} generated ex/s, "
                  f"{kept / report.seconds:,.0f} kept ex/s; dataset.txt {size_mb:.0f} MB")

        # A seeded subset spreads over all 675 commands (the full file starts with the
        # shortest ones, "walk to a circle", which would flatter the figure).
        sample = generate_dataset(os.path.join(tmp, "replay"), GenerationConfig(seed=1, max_examples=args.replay))
        episodes = [example.to_episode(split, index) for split, index, example in iter_examples(sample.path)]
        start = time.perf_counter()
        for episode in episodes:
            demonstrate(episode.situation, episode.command)
        plan_s = time.perf_counter() - start
        start = time.perf_counter()
        steps = sum(len(episode.states()) for episode in episodes)
        encode_s = time.perf_counter() - start
        n = len(episodes)
        print(f"demonstrate: {n / plan_s:,.0f} ex/s; per-step encoding (states()): {n / encode_s:,.0f} ex/s "
              f"({steps / encode_s:,.0f} states/s); both: {n / (plan_s + encode_s):,.0f} ex/s "
              f"({n} examples, 1 process)")


if __name__ == "__main__":
    main()
