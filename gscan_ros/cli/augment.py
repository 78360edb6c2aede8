"""`gscan-ros augment`: a dataset with its train split augmented (GECA, as Ruis et al. 2020 did for gSCAN)."""
from __future__ import annotations

import argparse

from gscan_ros.cli.args import dataset_path, nonnegative_int, output_dir, positive_int


def register(subparsers) -> None:
    from gscan_ros.data.geca import AUGMENT_METHODS, RELEASED_ADDED_EXAMPLES

    p = subparsers.add_parser(
        "augment",
        help="add data-augmentation examples to a dataset's train split (GECA)",
        description="Read a dataset (dataset.txt or bags), add examples to its train split and write "
                    "DIR/dataset.txt; every other split is copied as it is. Each added example is one its "
                    "situation and the planner agree on, so `gscan-ros verify` accepts the output. "
                    "The seed and the input alone fix the output.",
    )
    p.add_argument("--data", required=True, type=dataset_path, metavar="DATASET",
                   help="dataset.txt, a directory holding it, or bag data")
    p.add_argument("--out", required=True, type=output_dir, metavar="DIR",
                   help="output directory (DIR/dataset.txt); not the input's")
    p.add_argument("--method", required=True, choices=AUGMENT_METHODS,
                   help="geca: good-enough compositional data augmentation (Andreas 2020)")
    p.add_argument("--seed", type=nonnegative_int, default=0, help="random seed (default: 0)")
    p.add_argument("--examples", type=positive_int, default=RELEASED_ADDED_EXAMPLES, metavar="N",
                   help=f"examples to add (default: {RELEASED_ADDED_EXAMPLES:,}, as Ruis et al.)")
    p.add_argument("--keep-held-out", nargs="*", metavar="SPLIT",
                   help="also add examples of a kind a hold-out split of the dataset claims (e.g. a red "
                        "square target: visual), of every such split, or only of the SPLITs named (an "
                        "example two splits claim needs both); dropped by default")
    p.add_argument("--overwrite", action="store_true", help="replace DIR/dataset.txt if it exists")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import sys

    from gscan_ros.data.geca import augment_dataset

    report = augment_dataset(args.data, args.out, examples=args.examples, seed=args.seed,
                             keep_held_out=_keep(args.keep_held_out), overwrite=args.overwrite,
                             progress=not args.quiet)
    added = len(report.added)
    print(f"wrote {args.out}/dataset.txt: train {report.train_examples} + {added} GECA examples "
          f"(seed {report.seed}) in {report.seconds:.1f} s")
    print(f"  {report.train_pairs} distinct train (command, actions) pairs, {report.templates} templates, "
          f"{report.templates_tried} tried")
    for reason, n in sorted(report.dropped.items()):
        print(f"  dropped: {reason}: {n}")
    for split, n in sorted(report.held_out_kinds.items()):
        print(f"  proposals of the kind of {split}: {n} ({'kept' if split in report.keep_held_out else 'dropped'})")
    if added < report.requested:
        print(f"gscan-ros augment: warning: the templates ran out after {added} of {report.requested} examples",
              file=sys.stderr)
    return 0


def _keep(names: list[str] | None) -> bool | list[str]:
    """--keep-held-out: absent, bare (every hold-out split), or the splits named."""
    if names is None:
        return False
    return names or True
