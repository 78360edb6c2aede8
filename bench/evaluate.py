"""Closed-loop evaluation throughput: batched (many live episodes per forward) vs batch 1.

    .venv/bin/python bench/evaluate.py [--checkpoint CKPT] [--data DIR] [--episodes 512] [--threads 2]
                                       [--max-steps N] [--device cpu|cuda|auto]

Defaults: the shipped model and 3000 freshly generated candidate examples (seed 0);
episodes from the `test` split. The model decides when episodes stop, so a trained
checkpoint gives realistic episode lengths; an untrained one runs to the cap. To time
gSCAN-length episodes with any model, cap them: `--max-steps 14` decodes exactly 15
steps per episode (unless the model stops earlier), like a ~14-action gSCAN episode.
"""
from __future__ import annotations

import argparse
import resource
import time

from gscan_ros.model.policy import MAX_STEPS
from gscan_ros.model.runtime import DEVICES

from _data import dataset_or_generated


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", help="checkpoint (default: the shipped model)")
    ap.add_argument("--data", help="dataset (default: generate 3000 candidates into a temp dir)")
    ap.add_argument("--split", default="test")
    ap.add_argument("--episodes", type=int, default=512)
    ap.add_argument("--single-episodes", type=int, default=64, help="episodes for the batch-1 measurement")
    ap.add_argument("--batch-size", type=int, default=1024)
    ap.add_argument("--threads", type=int, default=2, help="torch intra-op threads")
    ap.add_argument("--max-steps", type=int, default=MAX_STEPS, help="decoding cap per episode (+1 for EOS)")
    ap.add_argument("--device", default="cpu", choices=DEVICES, help="where the network runs")
    args = ap.parse_args()

    from gscan_ros.data.io import iter_episodes
    from gscan_ros.model.policy import Policy
    from gscan_ros.model.runtime import configure_torch
    from gscan_ros.training.evaluate import evaluate_episodes

    configure_torch(args.threads)
    policy = Policy.from_checkpoint(args.checkpoint, device=args.device)
    with dataset_or_generated(args.data, examples=3000) as data:
        episodes = []
        for ep in iter_episodes(data, [args.split]):
            episodes.append(ep)
            if len(episodes) >= args.episodes:
                break
    rates = {}
    for label, eps, batch in (("batched", episodes, args.batch_size),
                              ("batch 1", episodes[: args.single_episodes], 1)):
        evaluate_episodes(policy, eps[: min(8, len(eps))], batch_size=batch, max_steps=args.max_steps)  # warm-up
        start = time.time()
        res = evaluate_episodes(policy, eps, batch_size=batch, max_steps=args.max_steps)
        seconds = time.time() - start
        steps = sum(min(len(p.actions) + 1, args.max_steps + 1) for p in res.predictions)  # + EOS unless capped
        rates[label] = len(eps) / seconds
        print(f"{label:8s} {rates[label]:8.1f} episodes/s  ({steps / seconds:.0f} decoding steps/s, "
              f"{steps / len(eps):.1f} steps/episode, {len(eps)} episodes, "
              f"batch {batch}, exact match {res.exact_match:.1f} %, threads {args.threads}, {policy.device})")
    print(f"batched / batch-1 ratio: {rates['batched'] / rates['batch 1']:.1f}")
    print(f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")


if __name__ == "__main__":
    main()
