"""A run's learning curve on any test split, read from its snapshots (`step_<N>.pt`).

    .venv/bin/python bench/research/snapshot_curve.py RUN_DIR --data DIR [--splits adverb_1 test]
        [--max-examples 500] [--seed 0] [--threads 1] [--no-closed-loop] [--json FILE]
        [--train-containing cautiously]

Per snapshot and split: closed-loop exact match and token accuracy (as `gscan-ros
evaluate`), and teacher forced (`training.evaluate.teacher_forced`): the % of gold actions
that are the model's argmax given the gold prefix, their mean NLL, and the % of episodes
with every step right (= closed-loop exact match). Where exact match stays 0 the whole
run (split G at small k), the teacher-forced columns say whether the split is being
learned slowly or not at all, and `--train-containing WORD` adds the train episodes whose
command has WORD (the k "cautiously" examples) as a row "train:WORD": whether the run
has fitted even those. Every snapshot reads the same seeded episodes.
"""
from __future__ import annotations

import argparse
import json
import re
import sys
import time
from pathlib import Path


def snapshots(run: Path) -> list[Path]:
    """step_<N>.pt by N, then last.pt when it is past the last snapshot."""
    steps = sorted(run.glob("step_*.pt"), key=lambda p: int(re.sub(r"\D", "", p.stem)))
    return steps or sorted(run.glob("last.pt"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="run directory with step_<N>.pt snapshots")
    ap.add_argument("--data", required=True, help="dataset with the test splits")
    ap.add_argument("--splits", nargs="+", default=["adverb_1", "test"])
    ap.add_argument("--max-examples", type=int, default=500, help="seeded subset per split (0 = all)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the subset")
    ap.add_argument("--threads", type=int, default=1, help="torch threads")
    ap.add_argument("--no-closed-loop", action="store_true", help="teacher-forced columns only")
    ap.add_argument("--train-containing", metavar="WORD", nargs="+", default=[],
                    help="also the train episodes whose command has WORD (every one, not a subset)")
    ap.add_argument("--json", type=Path, help="also write the rows here (refuses an existing file)")
    args = ap.parse_args()
    if args.json is not None and args.json.exists():
        sys.exit(f"bench/research/snapshot_curve.py: {args.json} exists; give another path")

    from gscan_ros.data.io import select_test_episodes
    from gscan_ros.errors import GscanError
    from gscan_ros.model.policy import Policy
    from gscan_ros.runtime import configure_torch
    from gscan_ros.training.batches import EpisodeStore, has_word
    from gscan_ros.training.evaluate import evaluate_episodes, teacher_forced
    from gscan_ros.training.trainer import iter_split

    configure_torch(args.threads)
    paths = snapshots(args.run)
    if not paths:
        sys.exit(f"bench/research/snapshot_curve.py: no step_<N>.pt or last.pt in {args.run}")
    by_split: dict[str, list] = {}
    try:
        policies = [Policy.from_checkpoint(p) for p in paths]
        for ep in select_test_episodes(args.data, args.splits, args.max_examples, args.seed):
            by_split.setdefault(ep.split, []).append(ep)
        for word in args.train_containing:
            by_split[f"train:{word}"] = [ep for ep in iter_split(args.data, "train") if has_word(ep.command, word)]
            if not by_split[f"train:{word}"]:
                raise GscanError(f"no train command of {args.data} has {word!r}")
    except (GscanError, OSError) as err:
        sys.exit(f"bench/research/snapshot_curve.py: {err}")
    stores = {split: EpisodeStore(eps, policies[0].parser) for split, eps in by_split.items()}

    rows = []
    print("| updates | split | episodes | closed-loop exact % | token acc. % | teacher-forced token acc. % "
          "| gold NLL / step | teacher-forced sequences % |")
    print("|---:|---|---:|---:|---:|---:|---:|---:|")
    for path, policy in zip(paths, policies):
        start = time.time()
        for split, eps in by_split.items():
            forced = teacher_forced(policy.model, stores[split])
            row = {"checkpoint": str(path), "updates": policy.metadata["step"], "split": split, **forced.summary()}
            if not args.no_closed_loop:
                closed = evaluate_episodes(policy, eps)
                row.update(exact_match=closed.exact_match, closed_token_accuracy=closed.token_accuracy)
            rows.append(row)
            closed_cells = ("–", "–") if args.no_closed_loop else (f"{row['exact_match']:.2f}",
                                                                   f"{row['closed_token_accuracy']:.2f}")
            print(f"| {row['updates']} | {split} | {forced.episodes} | {closed_cells[0]} | {closed_cells[1]} | "
                  f"{forced.token_accuracy:.2f} | {forced.nll:.3f} | {forced.sequence_accuracy:.2f} |", flush=True)
        print(f"{path.name}: {time.time() - start:.0f} s", file=sys.stderr)
    if args.json is not None:
        args.json.write_text(json.dumps({"run": str(args.run), "data": args.data, "max_examples": args.max_examples,
                                         "seed": args.seed, "rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
