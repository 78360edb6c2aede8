"""Checkpoints side by side on every test split: closed-loop exact match on the same seeded episodes.

    .venv/bin/python bench/research/compare_checkpoints.py --data DIR --checkpoint LABEL=CKPT [LABEL=CKPT ...]
                                                  [--max-examples 1000] [--threads 1] [--splits ...]

The fast recipe must be at least as good as the faithful one on every
split at the same number of updates: give the faithful run's snapshot first and the
fast runs' checkpoints at the same update after it. The episodes are read once and every
checkpoint decodes the same seeded subset of each split (`evaluate --max-examples`). The
table has one row per split and one column per checkpoint (with its update count); the
last lines say, for every checkpoint after the first, on how many splits it is at least
as good as the first.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/, for the benches' _data
from _data import labelled  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="dataset with the test splits (bags or dataset.txt)")
    ap.add_argument("--checkpoint", type=labelled("CHECKPOINT"), nargs="+", required=True, metavar="LABEL=CKPT",
                    help="checkpoints to compare; the first is the reference")
    ap.add_argument("--splits", nargs="+", help="test splits (default: every one the data has)")
    ap.add_argument("--max-examples", type=int, default=1000, help="seeded subset per split (0 = all)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the subset")
    ap.add_argument("--threads", type=int, default=1, help="torch threads")
    ap.add_argument("--batch-size", type=int, default=1024)
    args = ap.parse_args()

    from gscan_ros.data.io import select_test_episodes
    from gscan_ros.data.splits import SPLIT_LETTERS
    from gscan_ros.errors import GscanError
    from gscan_ros.model.policy import Policy
    from gscan_ros.runtime import configure_torch
    from gscan_ros.training.evaluate import evaluate_episodes

    configure_torch(args.threads)
    try:
        policies = [(label, Policy.from_checkpoint(path)) for label, path in args.checkpoint]
        episodes = select_test_episodes(args.data, args.splits, args.max_examples, args.seed)
    except (GscanError, OSError) as err:
        sys.exit(f"bench/research/compare_checkpoints.py: {err}")
    columns = []
    for label, policy in policies:
        start = time.time()
        summary = evaluate_episodes(policy, episodes, batch_size=args.batch_size).summary()
        print(f"{label}: {len(episodes)} episodes in {time.time() - start:.0f} s", file=sys.stderr)
        columns.append((label, policy.metadata["step"], summary))

    splits = list(columns[0][2])
    print("| split | examples | " + " | ".join(f"{label} ({step} updates)" for label, step, _ in columns) + " |")
    print("|---|---:|" + "---:|" * len(columns))
    for split in splits:
        cells = " | ".join(f"{summary[split]['exact_match']:.2f}" for _, _, summary in columns)
        print(f"| {SPLIT_LETTERS.get(split, '')} {split} | {columns[0][2][split]['examples']} | {cells} |")
    ref_label, _, ref = columns[0]
    for label, _, summary in columns[1:]:
        ahead = [s for s in splits if summary[s]["exact_match"] >= ref[s]["exact_match"]]
        behind = ", ".join(f"{SPLIT_LETTERS.get(s, s)} {summary[s]['exact_match'] - ref[s]['exact_match']:+.2f}"
                           for s in splits if s not in ahead)
        print(f"{label} >= {ref_label} on {len(ahead)} of {len(splits)} splits" + (f" (behind: {behind})" if behind
                                                                                      else ""))


if __name__ == "__main__":
    main()
