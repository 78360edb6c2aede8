"""`gscan-ros demo`: one episode through the in-process stack, printed, recorded and animated."""
import os
import re

import pytest
from PIL import Image

from gscan_ros.cli import main
from gscan_ros.data.bag import iter_bag_episodes
from gscan_ros.data.sources import sample_episode
from gscan_ros.training.failures import FAILURE_KINDS, failure_label

from model_support import tiny_checkpoint
from ros_helpers import fresh_domain_id

pytestmark = pytest.mark.e2e  # a whole stack, driven by the demo


def test_demo_prints_the_episodes_and_writes_bag_and_gifs(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("ROS_DOMAIN_ID", str(fresh_domain_id()))
    monkeypatch.delenv("ROS_AUTOMATIC_DISCOVERY_RANGE", raising=False)
    checkpoint = tiny_checkpoint(tmp_path / "tiny.pt")
    out = tmp_path / "demo"
    code = main(["demo", "--checkpoint", str(checkpoint), "--seed", "1", "--episodes", "2", "--max-steps", "4",
                  "--out", str(out)])
    printed = capsys.readouterr().out
    assert code == 0
    commands = [sample_episode(seed).command for seed in (1, 2)]  # seed, then the seed after reset_world
    for seed, command in zip((1, 2), commands):
        assert f"command:  {command}" in printed
        gold = ", ".join(a.token for a in sample_episode(seed).actions)
        assert f"planner:  {gold}" in printed
    assert "parse (semantic):" in printed
    verdicts = [line for line in printed.splitlines() if line.startswith("match:    ")]
    kinds = "|".join(map(failure_label, FAILURE_KINDS))
    assert len(verdicts) == 2 and all(re.fullmatch(rf"match:    (yes, exact match|no, ({kinds}) \(.+\))", v)
                                      for v in verdicts), verdicts
    assert "of 2 episodes" in printed
    # An untrained model: its episodes may end cut at --max-steps, recorded with that outcome.
    episodes = list(iter_bag_episodes(out / "bag", include_incomplete=True))
    assert [e.command for e in episodes] == commands
    for i, episode in enumerate(episodes, start=1):
        with Image.open(out / f"episode_{i}.gif") as gif:
            assert gif.n_frames == len(episode.actions) + 1
    assert os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"  # set by the demo when unset


def test_demo_with_an_unparsable_command_fails_with_one_line(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("ROS_DOMAIN_ID", str(fresh_domain_id()))
    checkpoint = tiny_checkpoint(tmp_path / "tiny.pt")
    code = main(["demo", "--checkpoint", str(checkpoint), "--command", "fly to the moon",
                 "--out", str(tmp_path / "demo")])
    assert code == 1
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith("gscan-ros demo: error: unknown word 'fly'")
    assert not (tmp_path / "demo").exists()  # refused before any output: --out stays free for the next try


def test_demo_of_a_dataset_on_another_grid_fails_before_any_output(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("ROS_DOMAIN_ID", str(fresh_domain_id()))
    data = tmp_path / "grid8"
    assert main(["generate", "--out", str(data), "--examples", "30", "--grid-size", "8", "--seed", "0",
                 "--workers", "1", "--quiet"]) == 0
    capsys.readouterr()
    code = main(["demo", "--checkpoint", str(tiny_checkpoint(tmp_path / "tiny.pt")), "--dataset", str(data),
                 "--out", str(tmp_path / "demo")])
    assert code == 1
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert re.search(r"example \S+ of split 'test' is on a 8x8 grid; the model was trained on 6x6$", line), line
    assert not (tmp_path / "demo").exists()
