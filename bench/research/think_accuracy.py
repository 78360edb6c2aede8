"""Does AuxLoss fail to find the target (think) or to get there (act)? Split by split.

    .venv/bin/python bench/research/think_accuracy.py --checkpoint results/paper/auxloss_s0/model.pt \
        --data DIR [--splits test visual_easier ...] [--max-examples 2000] [--seed 0] [--threads 1]

AuxLoss's target-location classifier names a cell before any action is decoded. On each
split (a seeded subset, the episodes `evaluate --max-examples` decodes) this prints the
share of episodes whose most likely cell is the target's ("think"), and closed-loop exact
match among the episodes thought right and those thought wrong ("act"). A split where
think fails and exact match follows it is a failure to identify the target; one where
think succeeds and exact match stays low is a failure to act on it. A wrong guess is
named by what sits in its cell, against the target: an object of the same shape, of the
same colour, another object (other shape and colour), or an empty cell (the agent's own
included). The classifier reads only the initial state, like the decoder's start.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

WRONG_KINDS = ("same shape", "same colour", "other object", "empty")


def wrong_guess(situation, cell: int) -> str:
    """What sits in the guessed `cell` (row * G + column), against the target."""
    target = situation.target_object
    here = next((o for o in situation.placed_objects
                 if o.position.row * situation.grid_size + o.position.col == cell), None)
    if here is None:
        return "empty"
    if here.shape == target.shape:
        return "same shape"
    return "same colour" if here.color == target.color else "other object"


def pct(flags: np.ndarray) -> float | None:
    """Percent of True in `flags`, None for none."""
    return round(100.0 * float(flags.mean()), 2) if len(flags) else None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", required=True, help="an AuxLoss checkpoint (model.pt of a finished run)")
    ap.add_argument("--data", required=True, help="a dataset with the test splits")
    ap.add_argument("--splits", nargs="+", default=None, help="test splits (default: every one in --data)")
    ap.add_argument("--max-examples", type=int, default=2000, help="seeded subset per split (0: all)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here (refuses an existing file)")
    args = ap.parse_args()
    if args.json is not None and args.json.exists():
        sys.exit(f"bench/research/think_accuracy.py: {args.json} exists; choose another --json path")

    import torch

    from gscan_ros.data.io import select_test_episodes
    from gscan_ros.errors import GscanError
    from gscan_ros.model.policy import Policy
    from gscan_ros.runtime import configure_torch
    from gscan_ros.training.batches import EpisodeStore
    from gscan_ros.training.evaluate import evaluate_episodes

    configure_torch(args.threads)
    try:
        policy = Policy.from_checkpoint(args.checkpoint)
        if getattr(policy.model, "kind", None) != "auxloss":
            raise GscanError(f"{args.checkpoint} is a {getattr(policy.model, 'kind', '?')} model, not auxloss")
        by_split: dict[str, list] = {}
        for ep in select_test_episodes(args.data, args.splits, args.max_examples, args.seed):
            by_split.setdefault(ep.split, []).append(ep)
    except (GscanError, OSError) as err:
        sys.exit(f"bench/research/think_accuracy.py: {err}")

    model = policy.model.eval()
    rows = []
    print("| split | episodes | think: target cell first % | exact % | exact % when thought right "
          "| exact % when thought wrong | wrong guesses: same shape / same colour / other object / empty, % |")
    print("|---|---:|---:|---:|---:|---:|---|")
    for split, episodes in by_split.items():
        store = EpisodeStore(episodes, policy.parser)
        ids = np.arange(len(episodes))
        guesses = np.empty(len(episodes), dtype=np.int64)
        with torch.no_grad():
            for start in range(0, len(ids), 1024):
                batch = model.make_batch(store, ids[start : start + 1024])
                text, final, mask, world = model.encode(batch.commands, batch.first_states)
                guesses[start : start + 1024] = model.think(text, final, mask, world).target_logits.argmax(-1).cpu()
        targets = store.target_cells(ids)
        right = guesses == targets
        kinds = [wrong_guess(ep.situation, int(g)) for ep, g, ok in zip(episodes, guesses, right) if not ok]
        exact = np.array([p.exact_match for p in evaluate_episodes(policy, episodes).predictions])

        row = {"split": split, "episodes": len(episodes), "think": pct(right), "exact_match": pct(exact),
               "exact_when_right": pct(exact[right]), "exact_when_wrong": pct(exact[~right]),
               "wrong_guesses": {k: kinds.count(k) for k in WRONG_KINDS}}
        rows.append(row)
        cells = ["–" if row[k] is None else f"{row[k]:.1f}"
                 for k in ("think", "exact_match", "exact_when_right", "exact_when_wrong")]
        shares = " / ".join(f"{100.0 * kinds.count(k) / len(kinds):.0f}" for k in WRONG_KINDS) if kinds else "–"
        print(f"| {split} | {len(episodes)} | " + " | ".join(cells) + f" | {shares} |", flush=True)
    if args.json is not None:
        args.json.write_text(json.dumps({"checkpoint": args.checkpoint, "data": args.data,
                                         "max_examples": args.max_examples, "seed": args.seed, "rows": rows},
                                        indent=1) + "\n")


if __name__ == "__main__":
    main()
