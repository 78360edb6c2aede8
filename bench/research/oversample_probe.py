"""Does fitting the few examples of a rare word transfer to its held-out split? A probe.

    .venv/bin/python bench/research/oversample_probe.py --checkpoint RUN/model.pt --data DIR
        [--word cautiously] [--per-batch 2] [--updates 2000] [--eval-every 500] [--lr 3e-4]
        [--subset 50000] [--split adverb_1] [--max-examples 300] [--seed 0] [--threads 1]
        [--alone EVERY]

Split G's k-shot runs of the paper plan end at 0 % with their own k "cautiously" training
examples unfitted (`bench/research/snapshot_curve.py --train-containing cautiously`). This
continues such a checkpoint (its Adam state, at `--lr`) on batches of `batch_size` that
always hold `--per-batch` of the train episodes whose command has `--word`, the rest drawn
from a seeded `--subset` of the other train episodes, so each rare example is seen
hundreds of times in a few thousand updates. Every `--eval-every` updates it prints, on
the rare train examples, on a seeded subset of `--split` and of `test`: closed-loop exact
match and teacher-forced token accuracy / gold NLL. If the held-out split rises once the
examples are fitted, the run's 0 % was the budget (too few exposures); if the examples
are fitted and the split stays at 0, it is not. A probe for reading the tables, not a
training recipe: the mixture is not the gSCAN training distribution.
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", required=True, help="a trained run's checkpoint (last.pt keeps Adam's state)")
    ap.add_argument("--data", required=True, help="the run's dataset (train and the held-out split)")
    ap.add_argument("--word", default="cautiously", help="the rare word whose train examples are oversampled")
    ap.add_argument("--per-batch", type=int, default=2, help="rare examples in every batch")
    ap.add_argument("--batch-size", type=int, default=50)
    ap.add_argument("--updates", type=int, default=2000)
    ap.add_argument("--eval-every", type=int, default=500)
    ap.add_argument("--lr", type=float, default=3e-4)
    ap.add_argument("--subset", type=int, default=50000, help="other train episodes (seeded sample) to fill batches")
    ap.add_argument("--split", default="adverb_1", help="the held-out split to watch")
    ap.add_argument("--max-examples", type=int, default=300, help="seeded subset of --split and of test")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--alone", type=int, default=0, metavar="EVERY",
                    help="instead of --per-batch: every EVERY-th update is one rare example alone")
    args = ap.parse_args()
    if args.alone < 0 or not 0 < args.per_batch < args.batch_size:
        sys.exit(f"bench/research/oversample_probe.py: --per-batch must be in 1..{args.batch_size - 1}")

    import torch

    from gscan_ros.data.io import select_test_episodes
    from gscan_ros.errors import GscanError
    from gscan_ros.model.checkpoint import read_checkpoint
    from gscan_ros.model.policy import Policy
    from gscan_ros.runtime import configure_torch
    from gscan_ros.training.batches import EpisodeStore, has_word
    from gscan_ros.training.evaluate import evaluate_episodes, teacher_forced
    from gscan_ros.training.step import TrainStep
    from gscan_ros.training.trainer import iter_split

    configure_torch(args.threads)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    try:
        ckpt = read_checkpoint(args.checkpoint)
        policy = Policy.from_checkpoint(args.checkpoint)
        rare, others, seen = [], [], 0
        for ep in iter_split(args.data, "train"):  # the others: a seeded reservoir sample, one pass
            if has_word(ep.command, args.word):
                rare.append(ep)
                continue
            if seen < args.subset:
                others.append(ep)
            elif (slot := int(rng.integers(0, seen + 1))) < args.subset:
                others[slot] = ep
            seen += 1
        held_out = select_test_episodes(args.data, [args.split, "test"], args.max_examples, args.seed)
    except (GscanError, OSError) as err:
        sys.exit(f"bench/research/oversample_probe.py: {err}")
    if not rare:
        sys.exit(f"bench/research/oversample_probe.py: no train command of {args.data} has {args.word!r}")
    store = EpisodeStore(rare + others, policy.parser)
    rare_ids = np.arange(len(rare))
    model = policy.model
    optimizer = torch.optim.Adam(model.parameters(), lr=args.lr)
    if "optimizer" in ckpt:
        optimizer.load_state_dict(ckpt["optimizer"])
        for group in optimizer.param_groups:
            group["lr"] = args.lr
    update = TrainStep(model, optimizer, store)
    watch = {f"train:{args.word}": rare}
    for ep in held_out:
        watch.setdefault(ep.split, []).append(ep)
    watch_stores = {name: EpisodeStore(eps, policy.parser) for name, eps in watch.items()}
    mixing = (f"one alone every {args.alone} updates" if args.alone
              else f"{args.per_batch} of {args.batch_size} per batch")
    print(f"{len(rare)} train episodes with {args.word!r}, {len(others)} others; {mixing}; "
          f"checkpoint at {ckpt.get('step', 0)} updates, lr {args.lr}")
    print("| probe updates | episodes | exact % | teacher-forced token acc. % | gold NLL / step |")
    print("|---:|---|---:|---:|---:|")

    def report(done: int) -> None:
        for name, eps in watch.items():
            forced = teacher_forced(model, watch_stores[name])
            exact = evaluate_episodes(policy, eps).exact_match
            print(f"| {done} | {name} ({len(eps)}) | {exact:.2f} | {forced.token_accuracy:.2f} | {forced.nll:.3f} |",
                  flush=True)

    report(0)
    start = time.time()
    for done in range(1, args.updates + 1):
        if args.alone and done % args.alone == 0:
            ids = rare_ids[[(done // args.alone - 1) % len(rare)]]
        elif args.alone:
            ids = len(rare) + rng.choice(len(others), args.batch_size, replace=False)
        else:
            ids = np.concatenate([rng.choice(rare_ids, args.per_batch),
                                  len(rare) + rng.choice(len(others), args.batch_size - args.per_batch, replace=False)])
        update(ids)
        if done % args.eval_every == 0 or done == args.updates:
            print(f"({done} updates, {time.time() - start:.0f} s)", file=sys.stderr)
            report(done)


if __name__ == "__main__":
    main()
