"""`gscan-ros replay`: reads the bag, evaluates closed loop, prints exact match overall and per split."""
import pytest

from gscan_ros.cli import main
from gscan_ros.data.bag import write_bag
from gscan_ros.model import policy as policy_module
from gscan_ros.training import evaluate as evaluate_module
from gscan_ros.training.evaluate import EvalResult, Prediction
from gscan_ros.world.types import Action

from bag_support import make_episodes


class FakePolicy:
    parser_name = "semantic"


@pytest.fixture
def replay_env(tmp_path, monkeypatch):
    """A bag plus an 'evaluator' that reproduces the recording for train episodes only."""
    episodes = make_episodes(9, seed=2)
    write_bag(tmp_path / "bag", episodes)
    calls = {}

    def fake_evaluate(policy, chosen, batch_size):
        calls.update(policy=policy, episodes=list(chosen), batch_size=batch_size)
        return EvalResult(
            [Prediction(e, list(e.actions) if e.split == "train" else [Action.STAY] * 99) for e in chosen]
        )

    monkeypatch.setattr(policy_module.Policy, "from_checkpoint", classmethod(lambda cls, path=None: FakePolicy()))
    monkeypatch.setattr(evaluate_module, "evaluate_episodes", fake_evaluate)
    return tmp_path / "bag", episodes, calls


def test_replay_reports_overall_and_per_split(replay_env, capsys):
    bag, episodes, calls = replay_env
    assert main(["replay", str(bag), "--batch-size", "4"]) == 0
    out = capsys.readouterr().out
    assert calls["episodes"] == episodes and calls["batch_size"] == 4
    assert "exact match: 33.33% (3/9)" in out
    assert "train" in out and "100.00%" in out
    assert "visual" in out and "0.00%" in out
    visual = next(line for line in out.splitlines() if line.strip().startswith("visual"))
    assert "(failed: " in visual  # each failed episode's kind, counted
    train = next(line for line in out.splitlines() if line.strip().startswith("train"))
    assert "failed" not in train


def test_replay_limits_and_filters_episodes(replay_env, capsys):
    bag, episodes, calls = replay_env
    assert main(["replay", str(bag), "--splits", "train", "--max-episodes", "2"]) == 0
    assert calls["episodes"] == [e for e in episodes if e.split == "train"][:2]
    assert "exact match: 100.00% (2/2)" in capsys.readouterr().out


def test_replay_errors_are_one_line(replay_env, tmp_path, capsys):
    bag, _, _ = replay_env
    assert main(["replay", str(bag), "--splits", "dev"]) == 1  # a split the bag has none of (or a typo) is named
    assert "no examples in split(s) dev of" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:
        main(["replay", str(tmp_path / "missing")])
    err = capsys.readouterr().err
    assert exit_info.value.code == 1 and err.count("\n") == 1 and "missing' does not exist" in err
    (tmp_path / "empty").mkdir()
    assert main(["replay", str(tmp_path / "empty")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not a rosbag2 bag" in err and "per-split bags" in err
    with pytest.raises(SystemExit):
        main(["replay", str(bag), "--max-episodes", "0"])


def test_replay_reads_a_folder_of_per_split_bags(replay_env, tmp_path, capsys):
    """As `generate --format mcap` writes them: the bags of --splits, or all of them."""
    _, episodes, calls = replay_env
    for split in ("train", "visual"):
        write_bag(tmp_path / "splits" / split, [e for e in episodes if e.split == split])
    assert main(["replay", str(tmp_path / "splits")]) == 0
    assert sorted(e.example_id for e in calls["episodes"]) == [e.example_id for e in episodes
                                                                if e.split in ("train", "visual")]
    assert main(["replay", str(tmp_path / "splits"), "--splits", "visual"]) == 0
    assert calls["episodes"] == [e for e in episodes if e.split == "visual"]
    assert "exact match: 0.00%" in capsys.readouterr().out


def test_replay_end_to_end_with_a_real_checkpoint(tmp_path, capsys):
    """An untrained tiny model: checks the real Policy / evaluate wiring, not the model's quality."""
    import torch

    from gscan_ros.language import all_commands, get_parser
    from gscan_ros.language.lexicon import Lexicon
    from gscan_ros.model.checkpoint import checkpoint_dict, save_checkpoint
    from gscan_ros.model.compositional import CompositionalNetwork
    from gscan_ros.model.config import ModelConfig
    from gscan_ros.model.modules import ModuleTable

    torch.manual_seed(0)
    parser = get_parser("semantic", Lexicon.none())
    table = ModuleTable.from_graphs(parser.parse(c) for c in all_commands())
    model = CompositionalNetwork(ModelConfig(cnn_channels=4, att_dim=4, rnn_layers=1, rnn_dim=8), table)
    checkpoint = tmp_path / "tiny.pt"
    save_checkpoint(checkpoint, checkpoint_dict(model, parser="semantic", lexicon=Lexicon.none(), step=0, metrics={}))
    write_bag(tmp_path / "bag", make_episodes(6, seed=8))

    assert main(["replay", str(tmp_path / "bag"), "--checkpoint", str(checkpoint), "--max-episodes", "4"]) == 0
    out = capsys.readouterr().out
    assert "replayed 4 episodes" in out and "(parser semantic)" in out
    assert "exact match:" in out and "/4)" in out

