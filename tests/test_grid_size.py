"""Grid size as a parameter through every layer: the released 12x12 length split end to end."""
import json

import numpy as np
import pytest
import yaml

from gscan_ros.cli import main
from gscan_ros.data.dataset import read_header
from gscan_ros.data.io import iter_episodes
from gscan_ros.data.sources import sample_episode
from gscan_ros.errors import DatasetFormatError
from gscan_ros.world import demonstrate
from gscan_ros.world.world import World
from msg_adapters import MessageFormatError, cdr_to_observation, observation_to_cdr


@pytest.fixture(scope="module")
def length_data(tmp_path_factory):
    out = tmp_path_factory.mktemp("len")
    assert main(["generate", "--out", str(out), "--split-kind", "length", "--examples", "400", "--workers", "1",
                 "--quiet"]) == 0
    return out


@pytest.mark.slow
def test_length_split_defaults_to_the_released_12x12_world(length_data):
    header = read_header(length_data / "dataset.txt")
    assert header.grid_size == 12
    lengths = {}
    for ep in iter_episodes(length_data):
        assert ep.situation.grid_size == 12
        lengths.setdefault(ep.split, []).append(len(ep.actions))
    assert min(lengths["target_lengths"]) > 15 and max(lengths["target_lengths"]) > 23  # beyond 6x6's reach
    assert max(max(lengths[s]) for s in ("train", "dev", "test")) <= 15


@pytest.mark.slow
def test_a_12x12_model_trains_evaluates_per_length_and_refuses_6x6_data(length_data, tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["train", "--config", "configs/length.yaml", "--data", str(length_data), "--out", str(run),
                 "--quiet", "--set", "max_updates=2", "--set", "batch_size=16", "--set", "validate_every=2",
                 "--set", "threads=1", "--set", "max_dev_examples=4"]) == 0
    config = yaml.safe_load((run / "config.yaml").read_text())
    assert config["max_train_target_length"] == 15
    out = tmp_path / "eval"
    assert main(["evaluate", "--checkpoint", str(run / "model.pt"), "--data", str(length_data), "--splits",
                 "target_lengths", "--max-examples", "6", "--out", str(out), "--quiet",
                 "--threads", "1"]) == 0
    by_length = json.loads((out / "results.json").read_text())["splits"]["target_lengths"]["by_target_length"]
    assert by_length and all(int(n) > 15 for n in by_length)
    small = tmp_path / "small"
    assert main(["generate", "--out", str(small), "--examples", "200", "--workers", "1", "--quiet"]) == 0
    capsys.readouterr()
    assert main(["evaluate", "--checkpoint", str(run / "model.pt"), "--data", str(small), "--splits", "test",
                 "--max-examples", "2", "--out", str(tmp_path / "e2"), "--quiet", "--threads", "1"]) == 1
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert "12x12" in line and "6x6" in line


@pytest.mark.slow
def test_training_refuses_a_config_that_names_another_grid(length_data, tmp_path, capsys):
    assert main(["train", "--config", "configs/length.yaml", "--data", str(length_data), "--out",
                 str(tmp_path / "r"), "--quiet", "--set", "max_updates=1", "--set", "model.grid_size=6"]) == 1
    assert "model.grid_size is 6" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("grid", [4, 12, 16])
def test_sampled_worlds_of_any_supported_size(grid):
    episode = sample_episode(3, grid)
    assert episode.situation.grid_size == grid
    assert tuple(demonstrate(episode.situation, episode.command)) == episode.actions
    obs = World(episode.situation).encode()
    assert obs.shape == (grid, grid, 16)
    np.testing.assert_array_equal(cdr_to_observation(observation_to_cdr(obs)), obs)


@pytest.mark.parametrize("grid", [3, 17])
def test_unsupported_sizes_are_one_error(grid):
    with pytest.raises(DatasetFormatError, match="not supported"):
        sample_episode(0, grid)
    with pytest.raises(MessageFormatError, match="square grid of 4 to 16"):
        cdr_to_observation(observation_to_cdr(np.zeros((grid, grid, 16), np.uint8)))


def test_generate_rejects_an_unsupported_grid_size(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["generate", "--out", str(tmp_path / "g"), "--examples", "5", "--grid-size", "40"])
    assert exit_.value.code == 1
    assert "--grid-size" in capsys.readouterr().err and not (tmp_path / "g").exists()
