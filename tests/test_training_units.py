"""Small rules of the trainer and the evaluator: what the logged loss averages, which dev
episodes a seed screen reads, and that evaluating leaves a model's mode as it was."""
import pytest
import torch

from gscan_ros.language import all_commands, get_parser
from gscan_ros.model.compositional import CompositionalNetwork
from gscan_ros.model.config import ModelConfig
from gscan_ros.model.modules import ModuleTable
from gscan_ros.training.evaluate import evaluate_episodes
from gscan_ros.training.trainer import SCREEN_EPISODES, _LossWindow, screen_episodes

from model_support import walk_episodes

torch.set_num_threads(1)


def test_the_logged_loss_is_the_mean_over_examples():
    """A short batch (an epoch's last, or one command's) weighs what its examples weigh."""
    window = _LossWindow()
    window.add(1.0, 10)
    window.add(4.0, 2)
    assert window.mean_loss() == pytest.approx((1.0 * 10 + 4.0 * 2) / 12)
    resumed = _LossWindow(**window.state())
    resumed.add(0.5, 4)
    assert resumed.mean_loss() == pytest.approx((10 + 8 + 2) / 16)
    older = _LossWindow(loss=3.0, examples=100, updates=2)  # a resume point that kept the batch means' sum
    assert older.mean_loss() == pytest.approx(1.5)


def test_a_seed_screen_reads_a_seeded_sample_of_dev_not_its_head():
    """Dev is stored grouped by command, so its first episodes can miss a verb or an adverb."""
    dev = list(range(1000))
    picked = screen_episodes(dev, seed=3)
    assert len(picked) == SCREEN_EPISODES == len(set(picked)) and picked == sorted(picked)
    assert picked != dev[:SCREEN_EPISODES] and max(picked) > 900
    assert picked == screen_episodes(dev, seed=3) != screen_episodes(dev, seed=4)
    assert screen_episodes(dev[:100], seed=3) == dev[:100]


@pytest.mark.parametrize("training", [True, False])
def test_evaluating_a_bare_model_leaves_its_mode_as_it_was(training):
    parse = get_parser("semantic").parse
    model = CompositionalNetwork(ModelConfig(cnn_channels=4, att_dim=4, rnn_layers=1, rnn_dim=8),
                                 ModuleTable.from_graphs(parse(c) for c in all_commands()))
    model.train(training)
    evaluate_episodes(model, walk_episodes(2), max_steps=3)
    assert model.training is training
