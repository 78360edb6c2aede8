"""Bags recorded the ROS way: an all-topics recording of the live stack (written by the
third-party `rosbags` library, as `ros2 bag record -a` writes one) trains, replays and
verifies, and its `/command` messages played into a fresh stack give the same episodes."""
import json

import pytest
import torch

from gscan_ros import episode_status as es
from gscan_ros.cli import main
from gscan_ros.data.bag import BagEpisodeReader
from gscan_ros.data.bag_cache import load_episode_cache
from gscan_ros.model.checkpoint import read_checkpoint
from gscan_ros.nodes.commander import GscanCommander, Outcome
from gscan_ros.world.types import Action

from ros_helpers import AllTopicsRecorder, Probe, fresh_domain_id, in_process_stack, parameters

pytestmark = pytest.mark.e2e

WALK, TURN, EOS = Action.WALK, Action.TURN_LEFT, Action.EOS
TIMEOUT = 30.0
COMMANDS = ["walk to a red circle", "walk to a small circle", "walk to a big square", "walk to a circle"]


def record(checkpoint, bag, commands, cut_last=False):
    """Run `commands` in a fresh in-process stack (world seed 3) while an all-topics
    recorder writes `bag`; with `cut_last`, the last one is cut by max_steps=1."""
    probe = Probe(fresh_domain_id())
    try:
        stack = in_process_stack(probe, checkpoint, [WALK, TURN, EOS])
        commander = GscanCommander(context=probe.context)
        commander.wait_until_ready(TIMEOUT)
        recorder = AllTopicsRecorder(commander, bag)
        recorder.discover()
        commander.spin_for(1.0)  # the latched world state arrives
        results = []
        for i, command in enumerate(commands):
            if cut_last and i == len(commands) - 1:
                stack.policy_node.set_parameters(parameters(max_steps=1))
            results.append(commander.run_episode(command, timeout=TIMEOUT))
            recorder.discover()  # topics that appeared meanwhile (attention maps)
        commander.spin_for(0.5)  # the last messages arrive
        recorder.close()
        commander.shutdown()
        return results
    finally:
        probe.close()


def plain_commands(bag):
    """The `/command` messages of a bag, in order (what `ros2 bag play` would publish)."""
    from rosbags.highlevel import AnyReader

    with AnyReader([bag]) as reader:
        connections = [c for c in reader.connections if c.topic == "/command"]
        return [reader.deserialize(raw, c.msgtype).data for c, _, raw in reader.messages(connections=connections)]


def test_an_all_topics_recording_trains_replays_and_plays_back(checkpoint, tmp_path, capsys):
    torch.set_num_threads(1)
    bag = tmp_path / "recorded"
    results = record(checkpoint, bag, COMMANDS, cut_last=True)
    assert [r.outcome for r in results] == [Outcome.SUCCEEDED] * 3 + [Outcome.MAX_STEPS]

    # The bag is the live topics: plain commands, the policy's reports, no gscan_ros metadata.
    assert plain_commands(bag) == COMMANDS
    assert "gscan_ros" not in (bag / "metadata.yaml").read_text()
    reader = BagEpisodeReader(bag)
    episodes = list(reader)
    assert [e.command for e in episodes] == COMMANDS[:3] and all(e.actions == (WALK, TURN) for e in episodes)
    assert reader.report.outcomes == {es.CUT: 1} and reader.report.complete, reader.report.summary()
    cut = [r for r in BagEpisodeReader(bag, include_incomplete=True).records() if r.outcome == es.CUT]
    assert [r.episode.actions for r in cut] == [(WALK,)]

    # Train on it (the cut episode is no demonstration), replay it, verify it.
    run = tmp_path / "run"
    assert main(["train", "--data", str(bag), "--out", str(run), "--quiet", "--set", "batch_size=2",
                 "--set", "max_updates=2", "--set", "validate_every=2", "--set", "threads=1",
                 "--set", "train_split=live", "--set", "dev_split=live", "--set", "lexicon=none",
                 "--set", "screen_seeds=0"]) == 0
    start = next(json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()
                 if json.loads(line)["event"] == "start")
    assert start["train_examples"] == 3
    assert len(load_episode_cache(bag, ["live"], include_incomplete=True)) == 4  # asked for: the cut one too
    assert read_checkpoint(run / "last.pt")["step"] == 2
    capsys.readouterr()
    assert main(["replay", str(bag), "--checkpoint", str(checkpoint)]) == 0
    out = capsys.readouterr().out
    assert "replayed 3 episodes" in out and "episodes that did not end complete: 1 cut (not replayed)" in out
    assert main(["verify", str(bag), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "verified 3 examples: 0 mismatch(es) (3 recorded episodes replayed, not re-planned)" in out
    assert "episodes that did not end complete: 1 cut (not checked)" in out
    assert main(["verify", str(bag), "--quiet", "--include-incomplete"]) == 0
    out = capsys.readouterr().out
    assert "verified 4 examples" in out and "episodes that did not end complete: 1 cut (checked: 1 cut)" in out
    assert main(["evaluate", "--checkpoint", str(checkpoint), "--data", str(bag), "--out", str(tmp_path / "ev"),
                 "--quiet"]) == 1  # the test splits by default: a recording says where its episodes are
    assert "a recording's episodes are in split live (--splits live)" in capsys.readouterr().err

    # `/command` played back into a fresh stack, in order, gives the same episodes.
    again = tmp_path / "again"
    played = record(checkpoint, again, plain_commands(bag)[:3])
    assert [r.outcome for r in played] == [Outcome.SUCCEEDED] * 3
    replayed = list(BagEpisodeReader(again))
    assert [(e.command, e.situation, e.actions) for e in replayed] == [
        (e.command, e.situation, e.actions) for e in episodes]
