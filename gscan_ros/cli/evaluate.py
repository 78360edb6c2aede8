"""`gscan-ros evaluate`: batched closed-loop evaluation of a checkpoint on dataset splits."""
from __future__ import annotations

import argparse

from gscan_ros.cli.args import (
    add_device_argument,
    dataset_path,
    existing_file,
    nonnegative_int,
    output_dir,
    positive_int,
    thread_count,
)
from gscan_ros.data.splits import SPLIT_LETTERS
from gscan_ros.errors import GscanError


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "evaluate",
        help="closed-loop exact match / token accuracy per split",
        description="The model acts, the World executes, the new state is fed back (batched over many "
        "episodes). Writes results.json, results.md and predictions.json (gSCAN prediction format; "
        "per-word attention maps with --attention). --splits takes split names; the paper's letters stand for "
        + ", ".join(f"{letter} = {split}" for split, letter in SPLIT_LETTERS.items()) + ". For G at k = 5/10/50, "
        "train models on data made with `gscan-ros generate --k-shot K` and evaluate each. Under "
        "`torchrun --nproc_per_node N -m gscan_ros.cli evaluate ...` the N processes share the batches and "
        "rank 0 writes the same files one process would (docs/scaling.md).",
    )
    p.add_argument("--checkpoint", type=existing_file, metavar="CKPT",
                   help="checkpoint file (default: the shipped model)")
    p.add_argument("--data", required=True, type=dataset_path, metavar="DIR",
                   help="dataset directory/file (dataset.txt or bags)")
    p.add_argument("--splits", nargs="+", metavar="SPLIT",
                   help="splits to evaluate (default: every test split present)")
    p.add_argument("--max-examples", type=nonnegative_int, default=0, metavar="N",
                   help="seeded subset of N episodes per split (0 = all)")
    p.add_argument("--out", type=output_dir, default="runs/eval", metavar="DIR",
                   help="output directory (default: runs/eval)")
    p.add_argument("--overwrite", action="store_true", help="replace the results of an earlier evaluation in DIR")
    p.add_argument("--batch-size", type=positive_int, default=1024, help="episodes decoded together (default: 1024)")
    kept = p.add_mutually_exclusive_group()  # the maps are kept only in predictions.json
    kept.add_argument("--no-predictions", action="store_true", help="skip predictions.json")
    kept.add_argument("--attention", action="store_true",
                      help="store every word's attention map per step in predictions.json (large: ~85 kB per episode)")
    p.add_argument("--threads", type=thread_count, default=0,
                   help="torch threads (0 = torch default; at most the CPUs available)")
    p.add_argument("--seed", type=nonnegative_int, default=None,
                   help="seed of the --max-examples subset (default: 0)")
    add_device_argument(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import contextlib
    import time

    from gscan_ros.data.io import select_test_episodes
    from gscan_ros.model.policy import Policy, default_checkpoint_path
    from gscan_ros.runtime import configure_torch
    from gscan_ros.training.distributed import joined
    from gscan_ros.training.evaluate import evaluate_episodes
    from gscan_ros.training.evaluation_files import claim_report_dir, markdown_table, write_reports
    from gscan_ros.user_files import file_sha256

    if args.seed is not None and not args.max_examples:
        raise GscanError("--seed picks the --max-examples subset; without --max-examples every episode is decoded")
    seed = args.seed or 0
    configure_torch(args.threads)
    with contextlib.ExitStack() as held:
        # The ranks only exchange predictions (Python objects): gloo, whatever the device.
        ranks = held.enter_context(joined(args.device, backend="gloo"))
        ranks.from_main(lambda: claim_report_dir(held, args.out, args.overwrite))  # rank 0 writes the reports
        policy = Policy.from_checkpoint(args.checkpoint, device=ranks.device)  # a clear error if unreadable
        checkpoint = args.checkpoint or default_checkpoint_path()
        digest = file_sha256(checkpoint)  # which weights these results score, whatever the path holds later
        episodes = select_test_episodes(args.data, args.splits, args.max_examples, seed)
        start = time.time()
        result = evaluate_episodes(policy, episodes, batch_size=args.batch_size, ranks=ranks,
                                   record_attention=args.attention,
                                   progress=not args.quiet and ranks.is_main)
        if result is None:  # not rank 0: rank 0 has every prediction and writes the reports
            return 0
        seconds = time.time() - start
        meta = {"checkpoint": str(checkpoint), "checkpoint_sha256": digest, "parser": policy.parser_name,
                "data": str(args.data), "max_examples": args.max_examples, "episodes": len(episodes),
                "seconds": round(seconds, 2), "episodes_per_s": round(len(episodes) / max(seconds, 1e-9), 1),
                "title": f"closed-loop evaluation of {args.checkpoint or 'the shipped model'}"}
        write_reports(args.out, result, meta, predictions=not args.no_predictions)
    print(markdown_table(result.summary()), end="")
    print(f"{len(episodes)} episodes in {seconds:.1f} s; results in {args.out}/")
    return 0
