"""`gscan-ros generate`: write a gSCAN dataset (compositional splits A-H or length split I)."""
from __future__ import annotations

import argparse

from gscan_ros.cli.args import float_in, int_in, nonnegative_int, output_dir, positive_int, worker_count
from gscan_ros.data.splits import SPLIT_KINDS
from gscan_ros.runtime import available_cpus
from gscan_ros.world.types import SUPPORTED_GRID_SIZES


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "generate",
        help="generate a gSCAN dataset (dataset.txt or MCAP bags)",
        description="Generate gSCAN examples with the original generator's sampling and split rules. "
                    "The seed alone fixes the output (any --workers gives the same bytes).",
    )
    p.add_argument("--out", required=True, type=output_dir, metavar="DIR",
                   help="output directory (DIR/dataset.txt or DIR/<split>/)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the dataset already in DIR (its dataset.txt and split bags; refused without this)")
    p.add_argument("--seed", type=nonnegative_int, default=0, help="random seed (default: 0)")
    size = p.add_mutually_exclusive_group(required=True)
    size.add_argument("--examples", type=positive_int, metavar="N",
                      help="a seeded sample of the same-seed full set, a subset of each split: N shared out "
                           "over its splits in proportion, each example in its full-set split (the k-shot "
                           "examples always in train; sampled test examples the full set discards as "
                           "duplicates of train are left out, so a few fewer than N may remain)")
    size.add_argument("--full", action="store_true", help="generate every candidate (the full dataset)")
    p.add_argument("--split-kind", choices=SPLIT_KINDS, default="compositional",
                   help="compositional splits A-H (default) or the target-length split I")
    p.add_argument("--workers", type=worker_count, default=available_cpus(), metavar="N",
                   help="worker processes, at most the available CPUs (default: all of them)")
    p.add_argument("--format", choices=("txt", "mcap"), default="txt", dest="fmt",
                   help="dataset.txt (default) or one rosbag2/MCAP bag per split")
    p.add_argument("--grid-size", type=int_in(SUPPORTED_GRID_SIZES[0], SUPPORTED_GRID_SIZES[-1]), metavar="N",
                   help="side of the square grid (default: 6 compositional, 12 length, as released)")
    p.add_argument("--num-resampling", type=positive_int, metavar="R",
                   help="layouts per inner direction/distance (default: 5)")
    p.add_argument("--percentage-train", type=float_in(0, 1, low_open=True), metavar="P",
                   help="1 - random test fraction (default: 0.9 compositional, 0.8 length)")
    p.add_argument("--percentage-dev", type=float_in(0, 1, high_open=True), default=0.01, metavar="P",
                   help="dev fraction of train (default: 0.01)")
    p.add_argument("--k-shot", type=nonnegative_int, metavar="K",
                   help="compositional split: 'cautiously' examples moved into train, at most the adverb_1 "
                        "examples (default: 1, as released)")
    p.add_argument("--cut-off-target-length", type=positive_int, metavar="L",
                   help="length split: targets longer than L are held out (default: 15)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from gscan_ros.data.generate import GenerationConfig, generate_dataset

    config = GenerationConfig(
        seed=args.seed,
        split_kind=args.split_kind,
        max_examples=None if args.full else args.examples,
        num_resampling=args.num_resampling,
        percentage_train=args.percentage_train,
        percentage_dev=args.percentage_dev,
        k_shot=args.k_shot,
        cut_off_target_length=args.cut_off_target_length,
        grid_size=args.grid_size,
    )
    report = generate_dataset(args.out, config, workers=args.workers, fmt=args.fmt, progress=not args.quiet,
                              overwrite=args.overwrite)
    kept = sum(report.split_sizes.values())
    print(f"wrote {report.path}: {kept} examples in {report.seconds:.1f} s "
          f"({report.generated / max(report.seconds, 1e-9):.0f} generated examples/s, {args.workers} worker(s))")
    print(f"  candidates {report.candidates}, dropped (several rules) {report.dropped_multiple_rules}, "
          f"test duplicates of train discarded {report.discarded_equivalent}")
    for split, n in report.split_sizes.items():
        print(f"  {split:15s} {n}")
    return 0
