"""dataset.txt -> bag -> Episodes is the identity on a small generated gSCAN dataset."""
import json

import pytest

from gscan_ros.data.bag import iter_bag_episodes, read_bag_info, write_bag
from gscan_ros.data.bag_cache import load_episode_cache
from gscan_ros.data.dataset import iter_raw_examples
from gscan_ros.data.generate import GenerationConfig, generate_dataset
from gscan_ros.data.io import iter_episodes


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("gscan")
    report = generate_dataset(out, GenerationConfig(seed=3, max_examples=60))
    return report.path


def test_generated_splits_round_trip_through_bags(dataset, tmp_path):
    splits = sorted({split for split, _, _ in iter_raw_examples(dataset)})
    assert len(splits) > 3
    for split in splits:
        episodes = list(iter_episodes(dataset, [split]))
        info = write_bag(tmp_path / split, episodes)
        assert info.splits == {split: len(episodes)}
        back = list(iter_episodes(tmp_path / split))  # io dispatches to the bag reader
        assert back == episodes
        for original, restored in zip(episodes, back):
            # The gSCAN situation JSON and the example's metadata survive exactly.
            assert restored.situation.to_json() == original.situation.to_json()
            assert {k: v for k, v in restored.meta.items() if k != "episode_id"} == original.meta


def test_bag_situations_equal_the_dataset_json(dataset, tmp_path):
    raw = [(split, ex) for split, _, ex in iter_raw_examples(dataset, ["train"])]
    write_bag(tmp_path / "train", iter_episodes(dataset, ["train"]))
    back = list(iter_bag_episodes(tmp_path / "train"))
    assert [json.loads(json.dumps(e.situation.to_json())) for e in back] == [ex["situation"] for _, ex in raw]
    cache = load_episode_cache(tmp_path / "train")
    assert cache.episodes == back
    assert read_bag_info(tmp_path / "train").episodes == len(raw)


def test_directory_of_split_bags_reads_like_the_dataset(dataset, tmp_path):
    """`generate --format mcap` writes DIR/<split>/ bags; DIR then works wherever dataset.txt does."""
    splits = ["train", "test"]
    for split in splits:
        write_bag(tmp_path / split, iter_episodes(dataset, [split]))
    for split in splits:
        assert list(iter_episodes(tmp_path, [split])) == list(iter_episodes(dataset, [split]))
    everything = list(iter_episodes(tmp_path))
    assert sorted({e.split for e in everything}) == sorted(splits)
    assert len(everything) == sum(len(list(iter_episodes(dataset, [s]))) for s in splits)
