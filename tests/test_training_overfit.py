"""A tiny run overfits 50 real walk episodes to 100% closed-loop exact match (real World)."""
import pytest
import torch

from gscan_ros.language.lexicon import Lexicon
from gscan_ros.language.registry import get_parser
from gscan_ros.model.compositional import CompositionalNetwork
from gscan_ros.model.config import ModelConfig
from gscan_ros.model.policy import Policy
from gscan_ros.training.batches import EpisodeStore, EpochCursor, iterate_batches
from gscan_ros.training.step import TrainStep

from model_support import train_to_exact_match, walk_episodes


@pytest.mark.slow
def test_overfits_50_walk_episodes():
    torch.set_num_threads(1)
    torch.manual_seed(0)
    parser = get_parser("semantic", Lexicon.none())
    episodes = walk_episodes(50, seed=1)
    store = EpisodeStore(episodes, parser)
    net = CompositionalNetwork(ModelConfig(cnn_dropout=0.0), store.graph_table())
    update = TrainStep(net, torch.optim.Adam(net.parameters(), lr=3e-3), store)
    policy = Policy(net, "semantic")
    batches = iterate_batches(store, 50, "mixed", seed=0, cursor=EpochCursor())
    exact, step, loss = train_to_exact_match(update, batches, policy, episodes, batch_size=50, max_updates=600)
    assert exact == 100.0, f"closed-loop exact match {exact} after {step} updates (loss {loss:.4f})"
