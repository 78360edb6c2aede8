"""Training throughput: examples/s and peak RSS, mixed batches vs the original one-command batches.

    .venv/bin/python bench/train.py [--data DIR] [--config FILE] [--set KEY=VALUE ...] [--updates 10]
                                    [--warmup 2] [--threads 2] [--device cpu|cuda|auto]
    .venv/bin/python bench/train.py --data data_gen/len --config configs/length.yaml   # split I, 12x12
    .venv/bin/python bench/train.py --checkpoint results/paper/constituency_s0/last.pt  # a trained model

Without --data, a dataset of 6000 candidate examples is generated into a temp dir
(seed 0; gSCAN-length episodes, ~14 actions on average). Each mode runs in its own
child process, so each peak RSS is that mode's alone (states cache included). The
first `--warmup` updates (allocator and cache warm-up) are not timed; a timed update
includes building the batch, forward, backward and the Adam step. The children start
as the experiment runner's trainings do: on AMD CPUs with the MKL vendor shim preloaded
where `make setup` built it (`GSCAN_MKL_SHIM=0` measures without it).
"""
from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time

from gscan_ros.runtime import DEVICES, mkl_shim_env
from gscan_ros.training.batches import BATCHING

from _data import dataset_or_generated


def measure(data: str, mode: str, updates: int, warmup: int, threads: int, batch_size: int,
            config: str | None = None, device: str = "cpu", overrides: list[str] = (),
            checkpoint: str | None = None) -> dict:
    import numpy as np
    import torch

    from gscan_ros.language.lexicon import Lexicon
    from gscan_ros.language.registry import get_parser
    from gscan_ros.model.checkpoint import checkpoint_lexicon, read_checkpoint, restore_model
    from gscan_ros.runtime import configure_torch, mkl_shim_loaded, resolve_device
    from gscan_ros.training.batches import EpisodeStore, batch_order
    from gscan_ros.training.config import TrainConfig
    from gscan_ros.training.step import TrainStep
    from gscan_ros.training.trainer import iter_split, new_model

    configure_torch(threads)
    dev = resolve_device(device)
    torch.manual_seed(0)
    cfg = TrainConfig.load(config, overrides)
    ckpt = read_checkpoint(checkpoint) if checkpoint else None
    lexicon = checkpoint_lexicon(ckpt) if ckpt else Lexicon.named(cfg.lexicon)
    # the config's (or checkpoint's) parse: constituency graphs have more, wider modules
    parser = get_parser(ckpt["parser"] if ckpt else cfg.parser, lexicon)
    t0 = time.time()
    store = EpisodeStore(iter_split(data, "train"), parser)
    cache_s = time.time() - t0
    model = (restore_model(ckpt) if ckpt else new_model(cfg, parser, lexicon, store)).to(dev)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    if ckpt and "optimizer" in ckpt:  # a training checkpoint: Adam's moments as the run left them
        optimizer.load_state_dict(ckpt["optimizer"])
        for group in optimizer.param_groups:
            group["lr"] = 1e-3
    update = TrainStep(model, optimizer, store)
    order = batch_order(store, batch_size, mode, np.random.default_rng(0))
    order = sorted(order, key=len, reverse=True)  # full batches first (per_command: the original's 200-episode chunks)
    if len(order) < warmup + updates:
        raise SystemExit(f"{len(order)} batches in the data; --warmup + --updates needs {warmup + updates}")
    examples, steps, elapsed = 0, 0, 0.0
    for i, ids in enumerate(order[: warmup + updates]):
        start = time.time()
        update(ids)
        if dev.type == "cuda":  # the time of the work, not of queueing it
            torch.cuda.synchronize(dev)
        if i >= warmup:
            elapsed += time.time() - start
            examples += len(ids)
            steps += int(store.lengths[ids].sum())
    return {"mode": mode, "device": str(dev), "threads": threads, "updates": updates, "examples": examples,
            "examples_per_s": examples / elapsed, "steps_per_s": steps / elapsed,
            "mean_batch": examples / updates, "mean_episode_steps": steps / examples,
            "train_episodes": len(store), "state_cache_s": round(cache_s, 2), "mkl_shim": mkl_shim_loaded(),
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", help="dataset (default: generate 6000 candidates into a temp dir)")
    ap.add_argument("--updates", type=int, default=10, help="timed updates per mode")
    ap.add_argument("--warmup", type=int, default=2, help="untimed updates first")
    ap.add_argument("--threads", type=int, default=2, help="torch intra-op threads")
    ap.add_argument("--batch-size", type=int, default=200)
    ap.add_argument("--config", help="training config whose model is measured (default: the built-in defaults; "
                                     "configs/length.yaml for split I data)")
    ap.add_argument("--device", default="cpu", choices=DEVICES, help="where the network runs")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="config override, as `gscan-ros train --set` "
                         "(e.g. parser=dependency, model.message=attention+state)")
    ap.add_argument("--checkpoint", help="time updates of this trained model (a run's last.pt also restores "
                                         "Adam's moments) instead of a fresh one; its model and parse win over "
                                         "--config's")
    ap.add_argument("--mode", choices=BATCHING, help="(internal) measure one mode in this process")
    args = ap.parse_args()
    if args.mode:
        print(json.dumps(measure(args.data, args.mode, args.updates, args.warmup, args.threads, args.batch_size,
                                 args.config, args.device, args.set, args.checkpoint)))
        return
    from gscan_ros.errors import CheckpointError
    from gscan_ros.model.checkpoint import read_checkpoint
    from gscan_ros.training.config import ConfigError, TrainConfig

    try:  # a bad config, override or checkpoint is one line here, not a traceback from each child
        TrainConfig.load(args.config, args.set)
        if args.checkpoint:
            read_checkpoint(args.checkpoint)
    except (ConfigError, CheckpointError) as err:
        raise SystemExit(f"bench/train.py: {err}") from None
    with dataset_or_generated(args.data, examples=6000) as data:
        results = {}
        for mode in BATCHING:
            cmd = [sys.executable, __file__, "--data", data, "--mode", mode, "--updates", str(args.updates),
                   "--warmup", str(args.warmup), "--threads", str(args.threads), "--batch-size", str(args.batch_size),
                   "--device", args.device, *(["--config", args.config] if args.config else []),
                   *(["--checkpoint", args.checkpoint] if args.checkpoint else []),
                   *(arg for item in args.set for arg in ("--set", item))]
            results[mode] = json.loads(subprocess.run(cmd, check=True, capture_output=True, text=True,
                                                      env=mkl_shim_env()).stdout)
    for mode, r in results.items():
        print(f"{mode:12s} {r['examples_per_s']:7.1f} examples/s  ({r['steps_per_s']:.0f} steps/s, mean batch "
              f"{r['mean_batch']:.0f}, {r['mean_episode_steps']:.1f} steps/episode)  peak RSS {r['peak_rss_mb']:.0f} MB"
              f"  [{r['device']}, threads {r['threads']}, MKL shim {'on' if r['mkl_shim'] else 'off'}, "
              f"state cache {r['state_cache_s']} s for "
              f"{r['train_episodes']} episodes]")
    ratio = results["mixed"]["examples_per_s"] / results["per_command"]["examples_per_s"]
    print(f"mixed / per_command throughput ratio: {ratio:.2f}")


if __name__ == "__main__":
    main()
