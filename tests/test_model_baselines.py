"""AuxLoss and LCGN: the batched models against the plain reference (teacher forcing and closed
loop), the target-location label, overfitting, checkpoints and `gscan-ros train` on their configs."""
from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from gscan_ros.cli import main
from gscan_ros.errors import CheckpointError
from gscan_ros.language.lexicon import Lexicon
from gscan_ros.language.registry import get_parser
from gscan_ros.model.auxloss import AuxLossBatch
from gscan_ros.model.checkpoint import build_model, checkpoint_dict, read_checkpoint, restore_model, save_checkpoint
from gscan_ros.model.decoder import Seq2SeqBatch, command_vocabulary
from gscan_ros.model.policy import Policy
from gscan_ros.training.batches import EpisodeStore, EpochCursor, iterate_batches
from gscan_ros.training.config import ConfigError, TrainConfig
from gscan_ros.training.step import TrainStep
from gscan_ros.training.trainer import iter_split
from gscan_ros.world.types import AGENT_CHANNEL, HEADING_CHANNEL0, Action

import baseline_reference as reference
from model_support import random_states, train_to_exact_match, walk_episodes

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
EPISODES = {"auxloss": reference.auxloss_episode, "lcgn": reference.lcgn_episode}
# The models checked against the reference: each kind, and AuxLoss with its other classifier.
VARIANTS = [pytest.param("auxloss", {}, id="auxloss"),
            pytest.param("auxloss", {"think_scorer": "dot"}, id="auxloss-dot"),
            pytest.param("lcgn", {}, id="lcgn")]
COMMANDS = ["walk to a circle", "push a big red square while spinning", "pull a small cylinder cautiously"]
TIGHT = {"atol": 1e-10, "rtol": 1e-8}


def build(kind: str, seed: int = 0, **settings):
    torch.manual_seed(seed)
    return build_model(kind, settings, {"tokens": command_vocabulary()})


def episodes():
    """Three initial states and gold actions (EOS last) of lengths 4, 6 and 2. Row 1's agent
    stands on an object (one node of both); row 2's agent is alone on the grid (a node
    without senders)."""
    rng = np.random.default_rng(0)
    states = random_states(rng, 3)
    agent = np.argwhere(states[1, ..., AGENT_CHANNEL])[0]
    states[1, agent[0], agent[1], [1, 5, 8]] = 1
    states[2] = 0
    states[2, 4, 1, [AGENT_CHANNEL, HEADING_CHANNEL0 + 2]] = 1
    targets = [np.append(rng.integers(0, int(Action.EOS), n - 1), int(Action.EOS)) for n in (4, 6, 2)]
    return states, targets, np.array([7, 20, 29])


def batch(kind: str, states, targets, cells) -> Seq2SeqBatch:
    padded = torch.full((len(targets), max(map(len, targets))), -1, dtype=torch.long)
    for row, t in enumerate(targets):
        padded[row, : len(t)] = torch.from_numpy(t)
    if kind == "auxloss":
        return AuxLossBatch(COMMANDS, states, padded, torch.from_numpy(cells))
    return Seq2SeqBatch(COMMANDS, states, padded)


@pytest.mark.parametrize(("kind", "settings"), VARIANTS)
def test_teacher_forcing_equals_the_plain_reference(kind, settings):
    """Loss, logits and every gradient of a mixed batch (commands and episodes of three
    lengths, padded, sorted, decoded as shrinking prefixes) equal the reference's, which
    runs each episode alone, word by word and node by node (float64, eval mode)."""
    torch.set_num_threads(1)
    model = build(kind, **settings).double().eval()
    states, targets, cells = episodes()
    out = model(batch(kind, states, targets, cells))
    want, want_logits = reference.loss(model, EPISODES[kind], COMMANDS, states, targets, cells)
    torch.testing.assert_close(out.logits, torch.cat(want_logits), **TIGHT)
    torch.testing.assert_close(out.loss, want, **TIGHT)
    params = list(model.parameters())
    for name, got, expected in zip([n for n, _ in model.named_parameters()], torch.autograd.grad(out.loss, params),
                                   torch.autograd.grad(want, params)):
        torch.testing.assert_close(got, expected, **TIGHT, msg=name)


@pytest.mark.parametrize(("kind", "settings"), VARIANTS)
def test_closed_loop_decodes_as_the_reference_on_its_own_actions(kind, settings):
    """Batched closed-loop decoding (row 1 dropped after step 2, as evaluation drops finished
    episodes) gives, at every step, the reference's logits for the actions it chose."""
    torch.set_num_threads(1)
    model = build(kind, **settings).double().eval()
    states, _, _ = episodes()
    with torch.no_grad():
        rollout = model.rollout([SimpleNamespace(command=c) for c in COMMANDS])
        closed, live = {row: [] for row in range(3)}, [0, 1, 2]
        for step in range(5):
            for row, logits in zip(live, rollout.step(states[live])[0]):
                closed[row].append(logits)
            if step == 2:
                rollout.keep(torch.tensor([0, 2]))
                live = [0, 2]
        for row, logits in closed.items():
            actions = torch.stack(logits).argmax(-1).numpy()
            want, _ = EPISODES[kind](model, COMMANDS[row], states[row], actions)
            torch.testing.assert_close(torch.stack(logits), want, **TIGHT)


def test_target_cells_are_the_situations_target_positions(tiny_dataset):
    """The label AuxLoss learns, read from the cached states, is the target object's cell
    in every episode of every split."""
    eps = list(iter_split(str(tiny_dataset), "train")) + list(iter_split(str(tiny_dataset), "situational_1"))
    store = EpisodeStore(eps, get_parser("semantic", Lexicon.none()))
    want = [e.situation.target_object.position.row * e.situation.grid_size + e.situation.target_object.position.col
            for e in eps]
    assert store.target_cells(np.arange(len(eps))).tolist() == want


@pytest.mark.slow
@pytest.mark.parametrize(("kind", "settings"), VARIANTS)
def test_overfits_20_walk_episodes(kind, settings):
    torch.set_num_threads(1)
    episodes_ = walk_episodes(20, seed=1)
    store = EpisodeStore(episodes_, get_parser("semantic", Lexicon.none()))
    dropouts = {"auxloss": ("dropout", "cnn_dropout"),
                "lcgn": ("dropout", "cnn_dropout", "embedding_dropout", "command_dropout", "read_dropout")}[kind]
    model = build(kind, **settings, **dict.fromkeys(dropouts, 0.0))
    update = TrainStep(model, torch.optim.Adam(model.parameters(), lr=3e-3), store)
    batches = iterate_batches(store, 20, "mixed", seed=0, cursor=EpochCursor())
    exact, step, loss = train_to_exact_match(update, batches, model, episodes_, batch_size=20, max_updates=400)
    assert exact == 100.0, f"closed-loop exact match {exact} after {step} updates (loss {loss:.4f})"


@pytest.mark.parametrize("kind", EPISODES)
def test_checkpoint_round_trip_and_policy(tmp_path, kind):
    model = build(kind, target_loss_weight=0.5) if kind == "auxloss" else build(kind, rounds=2)
    path = tmp_path / "m.pt"
    save_checkpoint(path, checkpoint_dict(model, parser="semantic", lexicon=Lexicon.none(), step=3, metrics={}))
    policy = Policy.from_checkpoint(path)
    assert policy.metadata["kind"] == kind and policy.model.cfg == model.cfg
    for key, value in model.state_dict().items():
        assert torch.equal(value, policy.model.state_dict()[key]), key
    states, _, _ = episodes()
    model.eval()
    graphs = [SimpleNamespace(command=c) for c in COMMANDS]
    assert torch.equal(model.rollout(graphs).step(states)[0], policy.model.rollout(graphs).step(states)[0])
    policy.reset(policy.parse(COMMANDS[1]))  # what policy_node does per episode
    assert policy.step(states[1]).action in Action
    with pytest.raises(CheckpointError, match="differs"):
        restore_model(read_checkpoint(path), build(kind))
    ckpt = read_checkpoint(path)
    ckpt["model_config"]["cnn_channels"] = 0
    save_checkpoint(path, ckpt)
    with pytest.raises(CheckpointError, match="cnn_channels must be a positive integer"):
        read_checkpoint(path)


@pytest.mark.parametrize(("kind", "setting"), [("auxloss", {"target_loss_weight": -1}),
                                               ("auxloss", {"think_scorer": "bilinear"}),
                                               ("lcgn", {"command_dim": 63}), ("lcgn", {"hidden_size": 8}),
                                               ("lcgn", {"rounds": 100000}), ("seq2seq", {"hidden": 100000}),
                                               ("auxloss", {"embedding_dim": 513})])
def test_a_bad_model_setting_is_a_config_error(kind, setting):
    with pytest.raises(ConfigError, match=next(iter(setting))):
        TrainConfig(model_kind=kind, model=setting)


@pytest.mark.parametrize("kind", EPISODES)
def test_train_with_the_config_file_then_evaluate(tiny_dataset, tmp_path, kind):
    torch.set_num_threads(1)
    run = tmp_path / "run"
    assert main(["train", "--config", str(CONFIGS / f"{kind}.yaml"), "--data", str(tiny_dataset), "--out", str(run),
                 "--quiet", "--set", "max_updates=2", "--set", "batch_size=16", "--set", "validate_every=2",
                 "--set", "checkpoint_every=2", "--set", "max_dev_examples=4", "--set", "threads=1",
                 "--set", "lexicon=none"]) == 0
    ckpt = read_checkpoint(run / "last.pt")
    assert ckpt["kind"] == kind and ckpt["step"] == 2
    out = tmp_path / "eval"
    assert main(["evaluate", "--checkpoint", str(run / "model.pt"), "--data", str(tiny_dataset), "--splits",
                 "visual", "--max-examples", "3", "--out", str(out), "--quiet", "--threads", "1"]) == 0
    assert json.loads((out / "results.json").read_text())["splits"]["visual"]["examples"] == 3
