"""`gscan-ros report`: the paper's tables from run results, ours beside the paper's.

Reads every run's results.json and metrics.jsonl under the given folders (any mix of run
directories and folders of them, e.g. several workers' result folders) and writes a
markdown file: Table 1 (splits A-H, G per k), Table 2 (split I per target length), the
runs and updates behind each column, a learning-curve figure, and notes on where ours
and the paper's differ. Same inputs, byte-identical markdown. Details: docs/experiments.md.
"""
from __future__ import annotations

import argparse

from gscan_ros.cli.args import existing_dir, existing_file, output_file


def register(subparsers) -> None:
    p = subparsers.add_parser("report", help="the paper's tables (mean ± std over seeds) from experiment runs",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dirs", nargs="+", type=existing_dir, metavar="RUN_DIR",
                   help="run directories or folders holding them")
    p.add_argument("--out", required=True, type=output_file(".md"), metavar="FILE.md", help="the markdown report")
    curves = p.add_mutually_exclusive_group()
    curves.add_argument("--curves", type=output_file(".png"), metavar="FILE.png",
                        help="learning-curve figure (default: FILE_curves.png next to --out)")
    curves.add_argument("--no-curves", action="store_true", help="no figure")
    p.add_argument("--plan", type=existing_file, metavar="PLAN.yaml",
                   help="the experiment plan the runs come from: the runs it retrains (another config or "
                        "dataset, no weights) are listed and their cells marked")
    p.add_argument("--overwrite", action="store_true", help="replace --out / --curves if they exist")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import contextlib

    from gscan_ros.experiments.tables import write_report
    from gscan_ros.outputs import check_targets, claimed

    curves = None if args.no_curves else args.curves or args.out.with_name(f"{args.out.stem}_curves.png")
    with contextlib.ExitStack() as held:
        for path, flag in ((args.out, "--out"), (curves, "--curves")):
            if path is not None:
                held.enter_context(claimed(path))
                check_targets([path], overwrite=args.overwrite, flag=flag)
        runs = write_report(args.dirs, args.out, curves, args.plan)
    print(f"wrote {args.out} from {len(runs)} run(s)" + (f" and {curves}" if curves else ""))
    return 0
