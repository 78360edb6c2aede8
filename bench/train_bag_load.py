"""Train-split load time from bags: first run (decode bag, write cache) vs. later runs (cache).

    .venv/bin/python bench/train_bag_load.py [--data BAGS --drop-cache] [--split train] [--old]

--data is a bag or a directory of per-split bags (`gscan-ros generate --format mcap`);
without it, a bag directory of at most 10,000 examples is generated into a temporary
directory. The first load decodes the bag only where no cache file exists yet: a cache of
your own data is deleted first only with --drop-cache. --old also times the previous path
(stream Episodes from the bag, replay every one through World).
"""
from __future__ import annotations

import argparse
import time

from _data import dataset_or_generated


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None, help="bag or bag directory (default: generate one)")
    ap.add_argument("--split", default="train")
    ap.add_argument("--old", action="store_true", help="also time Episodes + World replay (the old path)")
    ap.add_argument("--drop-cache", action="store_true", help="delete the cache file of --data's split first")
    args = ap.parse_args()

    import torch

    from gscan_ros.data.bag_cache import cache_path
    from gscan_ros.data.io import is_bag, split_bags
    from gscan_ros.language.lexicon import Lexicon
    from gscan_ros.language.registry import get_parser
    from gscan_ros.training.batches import EpisodeStore
    from gscan_ros.training.config import TrainConfig
    from gscan_ros.training.trainer import load_split, load_train_store

    torch.set_num_threads(1)
    parser = get_parser("semantic", Lexicon.named("wordnet"))
    cfg = TrainConfig(train_split=args.split)
    with dataset_or_generated(args.data, examples=10_000, seed=1, fmt="mcap") as data:
        bag = data if is_bag(data) else split_bags(data)[args.split]
        if args.data is None or args.drop_cache:
            cache_path(bag).unlink(missing_ok=True)
        first = "first load (cache)" if cache_path(bag).exists() else "first load (decode + write cache)"
        for label in (first, "second load (cache)", "third load (cache)"):
            t0 = time.perf_counter()
            store = load_train_store(data, cfg, parser)
            print(f"{label:36s} {time.perf_counter() - t0:7.2f} s  {len(store)} episodes, "
                  f"{store.ep_ptr[-1]} states")
        print(f"cache file: {cache_path(bag)} ({cache_path(bag).stat().st_size / 2**20:.1f} MiB)")
        if args.old:
            t0 = time.perf_counter()
            store = EpisodeStore(load_split(data, args.split), parser)
            elapsed = time.perf_counter() - t0
            print(f"{'old path (Episodes + World replay)':36s} {elapsed:7.2f} s  {len(store)} episodes")


if __name__ == "__main__":
    main()
