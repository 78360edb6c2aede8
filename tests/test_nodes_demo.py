"""`gscan-ros demo`: one episode through the in-process stack, printed, recorded and animated."""
import os

from PIL import Image

from gscan_ros.cli import main
from gscan_ros.data.bag import iter_bag_episodes
from gscan_ros.data.sources import sample_episode
from gscan_ros.nodes.harness import fresh_domain_id

from ros_helpers import tiny_checkpoint


def test_demo_prints_the_episode_and_writes_bag_and_gif(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("ROS_DOMAIN_ID", str(fresh_domain_id()))
    monkeypatch.delenv("ROS_AUTOMATIC_DISCOVERY_RANGE", raising=False)
    checkpoint = tiny_checkpoint(tmp_path / "tiny.pt")
    out = tmp_path / "demo"
    code = main(["demo", "--checkpoint", str(checkpoint), "--seed", "1", "--max-steps", "4", "--out", str(out)])
    printed = capsys.readouterr().out
    assert code == 0
    command = sample_episode(1).command
    assert f"command:  {command}" in printed
    assert "parse (semantic):" in printed and "match:    " in printed
    gold = ", ".join(a.token for a in sample_episode(1).actions)
    assert f"planner:  {gold}" in printed
    episodes = list(iter_bag_episodes(out / "bag"))
    assert [e.command for e in episodes] == [command]
    with Image.open(out / "episode.gif") as gif:
        assert gif.n_frames == len(episodes[0].actions) + 1
    assert os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"  # set by the demo when unset


def test_demo_with_an_unparsable_command_fails_with_one_line(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("ROS_DOMAIN_ID", str(fresh_domain_id()))
    checkpoint = tiny_checkpoint(tmp_path / "tiny.pt")
    code = main(["demo", "--checkpoint", str(checkpoint), "--command", "fly to the moon", "--out", str(tmp_path)])
    assert code == 1
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith("gscan-ros demo: error: unknown word 'fly'")
