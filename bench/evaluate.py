"""Closed-loop evaluation throughput: batched (many live episodes per forward) vs batch 1.

    .venv/bin/python bench/evaluate.py [--checkpoint CKPT] [--data DIR] [--episodes 512] [--threads 2]
                                       [--processes 1] [--repeats 3] [--max-steps N] [--device cpu|cuda|auto]

Defaults: the shipped model and 3000 freshly generated candidate examples (seed 0);
episodes from the `test` split. After one untimed batch (the allocator's warm-up), the
episodes are decoded `--repeats` times and the median rate is reported. The model
decides when episodes stop, so a trained checkpoint gives realistic episode lengths; an
untrained one runs to the cap. To time gSCAN-length episodes with any model, cap them:
`--max-steps 14` decodes exactly 15 steps per episode (unless the model stops earlier),
like a ~14-action gSCAN episode.

`--processes N` times the sharded evaluation of `torchrun --nproc_per_node N -m
gscan_ros.cli evaluate` (docs/scaling.md): the bench starts itself as N torchrun ranks of
`--threads` threads each (gloo on 127.0.0.1), every rank decodes its share of the
batches, and the time runs from a barrier to rank 0 holding all predictions.
"""
from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import time

from gscan_ros.model.policy import MAX_STEPS
from gscan_ros.runtime import DEVICES

from _data import dataset_or_generated, loopback_torchrun


def measure(args: argparse.Namespace, data: str) -> None:
    """Time the batched and the batch-1 decoding, one process or as one rank of many."""
    import torch.distributed as dist

    from gscan_ros.data.io import iter_episodes
    from gscan_ros.model.policy import Policy
    from gscan_ros.runtime import configure_torch
    from gscan_ros.training.distributed import joined
    from gscan_ros.training.evaluate import evaluate_episodes

    configure_torch(args.threads)
    with joined(args.device) as ranks:
        policy = Policy.from_checkpoint(args.checkpoint, device=ranks.device)
        episodes = []
        for ep in iter_episodes(data, [args.split]):
            episodes.append(ep)
            if len(episodes) >= args.episodes:
                break
        rates = {}
        for label, eps, batch in (("batched", episodes, args.batch_size),
                                  ("batch 1", episodes[: args.single_episodes], 1)):
            # Warm-up: one whole batch, so that the allocator holds a batch's tensors and
            # the timed passes see what the hundreds of batches of a real evaluation see.
            evaluate_episodes(policy, eps[: min(batch if batch > 1 else 8, len(eps))], batch_size=batch,
                              max_steps=args.max_steps)
            passes = []
            for _ in range(args.repeats):
                if ranks.distributed:
                    dist.barrier()
                start = time.time()
                res = evaluate_episodes(policy, eps, batch_size=batch, max_steps=args.max_steps, ranks=ranks)
                passes.append(len(eps) / (time.time() - start))
            if res is None:  # not rank 0: the predictions went to rank 0
                continue
            rates[label] = statistics.median(passes)
            steps = sum(min(len(p.actions) + 1, args.max_steps + 1) for p in res.predictions)  # + EOS unless capped
            print(f"{label:8s} {rates[label]:8.1f} episodes/s  ({steps / len(eps) * rates[label]:.0f} decoding "
                  f"steps/s, {steps / len(eps):.1f} steps/episode, {len(eps)} episodes, batch {batch}, "
                  f"exact match {res.exact_match:.1f} %, {ranks.world_size} process(es) x {args.threads} "
                  f"thread(s), {policy.device}; median of {' '.join(f'{r:.1f}' for r in passes)})", flush=True)
        if ranks.is_main:
            print(f"batched / batch-1 ratio: {rates['batched'] / rates['batch 1']:.1f}")
            print(f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB (rank 0)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", help="checkpoint (default: the shipped model)")
    ap.add_argument("--data", help="dataset (default: generate 3000 candidates into a temp dir)")
    ap.add_argument("--split", default="test")
    ap.add_argument("--episodes", type=int, default=512)
    ap.add_argument("--single-episodes", type=int, default=64, help="episodes for the batch-1 measurement")
    ap.add_argument("--batch-size", type=int, default=1024)
    ap.add_argument("--threads", type=int, default=2, help="torch intra-op threads (per process)")
    ap.add_argument("--processes", type=int, default=1,
                    help="torchrun ranks on this machine sharing the batches (docs/scaling.md)")
    ap.add_argument("--repeats", type=int, default=3, help="timed passes over the episodes (median reported)")
    ap.add_argument("--max-steps", type=int, default=MAX_STEPS, help="decoding cap per episode (+1 for EOS)")
    ap.add_argument("--device", default="cpu", choices=DEVICES, help="where the network runs")
    args = ap.parse_args()
    if min(args.processes, args.threads, args.repeats) < 1:
        raise SystemExit("--processes, --threads and --repeats must be at least 1")
    if args.processes > 1 and "WORLD_SIZE" not in os.environ:
        # Launch the ranks on one dataset (generated once, here) and wait for them.
        with dataset_or_generated(args.data, examples=3000) as data:
            torchrun, env = loopback_torchrun(args.processes, args.threads)
            argv = [f"--{key.replace('_', '-')}={value}" for key, value in vars(args).items()
                    if value is not None and key != "data"]
            raise SystemExit(subprocess.run([*torchrun, __file__, *argv, f"--data={data}"], env=env).returncode)
    with dataset_or_generated(args.data, examples=3000) as data:
        measure(args, data)


if __name__ == "__main__":
    main()
