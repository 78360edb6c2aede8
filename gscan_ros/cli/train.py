"""`gscan-ros train`: train a compositional network (or a baseline: seq2seq, AuxLoss, LCGN) on a dataset."""
from __future__ import annotations

import argparse
import json

from gscan_ros.cli.args import add_device_argument, dataset_path, existing_file, output_dir


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "train",
        help="train a model on a generated dataset",
        description="Teacher-forced training with periodic closed-loop validation. Settings come from "
        "a YAML config (fields of TrainConfig, model settings under 'model:') and --set overrides. "
        "Under `torchrun --nproc_per_node N -m gscan_ros.cli train ...` the N processes train one model "
        "(DistributedDataParallel, each a shard of every batch; docs/scaling.md).",
    )
    p.add_argument("--config", type=existing_file, metavar="FILE",
                   help="YAML training config (default: built-in defaults; with --resume, RUN_DIR/config.yaml)")
    p.add_argument("--data", required=True, type=dataset_path, metavar="DIR",
                   help="dataset directory/file (dataset.txt or bags)")
    p.add_argument("--out", type=output_dir, default="runs/train", metavar="RUN_DIR",
                   help="run directory (default: runs/train)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config key, e.g. --set batch_size=100 --set model.rnn_dim=40")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--resume", action="store_true",
                      help="continue from RUN_DIR/last.pt with the run's own settings (only the budget and threads "
                           "may change; docs/experiments.md)")
    mode.add_argument("--overwrite", action="store_true",
                      help="replace the run files already in RUN_DIR (refused without this flag)")
    p.add_argument("--include-incomplete", action="store_true",
                   help="also train on recorded episodes that did not end complete (cut at max_steps, "
                        "preempted, rejected): no demonstrations, left out by default")
    add_device_argument(p)
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from gscan_ros.runtime import check_cpu_count
    from gscan_ros.training.config import ConfigError, TrainConfig
    from gscan_ros.training.distributed import joined
    from gscan_ros.training.trainer import train

    overrides = [*args.overrides, *(["include_incomplete=true"] if args.include_incomplete else [])]
    config = args.config
    if config is None and args.resume and (args.out / "config.yaml").is_file():
        config = args.out / "config.yaml"  # the run's own settings; --set changes its budget or threads
    cfg = TrainConfig.load(config, overrides)
    # This machine's limit, not the config's: a run resumed elsewhere takes `--set threads=N`.
    check_cpu_count(cfg.threads, "threads", ConfigError)
    with joined(args.device) as ranks:
        result = train(cfg, str(args.data), args.out, resume=args.resume, overwrite=args.overwrite,
                       progress=not args.quiet, device=ranks.device)
        if ranks.is_main:
            print(json.dumps(result, indent=2))
    return 0
