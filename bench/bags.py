"""Bag throughput: episodes/s written, messages/s read (streaming, with states, cached).

Uses real gSCAN episodes from a small generated dataset, so episode lengths and
situations are realistic. Run: `.venv/bin/python bench/bags.py [--episodes N] [--images]`.
"""
from __future__ import annotations

import argparse
import gc
import itertools
import tempfile
import time
from pathlib import Path

from gscan_ros.data.bag import BagEpisodeReader, iter_bag_episodes, write_bag
from gscan_ros.data.bag_cache import load_episode_cache
from gscan_ros.data.generate import GenerationConfig, generate_dataset
from gscan_ros.data.io import iter_episodes


def timed(fn):
    """(fn(), seconds), from a collected heap: a full garbage collection that the step
    before provoked would otherwise land in this step's time."""
    gc.collect()
    start = time.perf_counter()
    result = fn()
    return result, time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=5000)
    parser.add_argument("--images", action="store_true", help="also write /world_image (rgb8) per step")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    with tempfile.TemporaryDirectory(prefix="bench_bags_") as tmp:
        tmp = Path(tmp)
        report = generate_dataset(tmp / "data", GenerationConfig(seed=args.seed, max_examples=args.episodes))
        episodes = list(itertools.islice(iter_episodes(report.path), args.episodes))
        bag = tmp / "bag"

        info, seconds = timed(lambda: write_bag(bag, episodes, include_images=args.images))
        size_mb = sum(p.stat().st_size for p in info.mcap_paths) / 1e6
        print(f"episodes: {len(episodes)}, messages: {info.message_count}, mcap: {size_mb:.1f} MB"
              f" ({size_mb * 1e6 / len(episodes):.0f} B/episode)")
        print(f"write:              {len(episodes) / seconds:10.0f} episodes/s"
              f"  {info.message_count / seconds:10.0f} messages/s")

        _, seconds = timed(lambda: list(iter_bag_episodes(bag)))
        print(f"read episodes:      {info.message_count / seconds:10.0f} messages/s"
              f"  {len(episodes) / seconds:10.0f} episodes/s")

        reader = BagEpisodeReader(bag, decode_states=True)
        _, seconds = timed(lambda: list(reader.records()))
        print(f"read with states:   {info.message_count / seconds:10.0f} messages/s"
              f"  {len(episodes) / seconds:10.0f} episodes/s")

        _, seconds = timed(lambda: load_episode_cache(bag))
        print(f"cache build:        {seconds:10.2f} s")
        cache, seconds = timed(lambda: load_episode_cache(bag))
        print(f"cache load:         {seconds:10.2f} s  = {info.message_count / seconds:10.0f} messages/s"
              f"  {len(episodes) / seconds:10.0f} episodes/s (commands, actions, states)")
        _, seconds = timed(lambda: [cache.states(i) for i in range(len(cache))])
        print(f"cache states:       {len(episodes) / seconds:10.0f} episodes/s unpacked")
        restored, seconds = timed(lambda: cache.episodes)
        assert restored == episodes
        print(f"cache -> Episodes:  {len(episodes) / seconds:10.0f} episodes/s (parses each Situation)")


if __name__ == "__main__":
    main()
