"""Checkpoints: bit-exact round trip, weights_only loading, clear errors on mismatch."""
import numpy as np
import pytest
import torch

from gscan_ros.errors import CheckpointError, GraphError
from gscan_ros.language.lexicon import Concept, Lexicon
from gscan_ros.model.checkpoint import checkpoint_dict, read_checkpoint, restore_model, save_checkpoint
from gscan_ros.model.compositional import CompositionalNetwork
from gscan_ros.model.config import ModelConfig
from gscan_ros.model.policy import Policy

from model_support import GRAPHS, chain, random_states, table

LEXICON = Lexicon((Concept(("big", "small"), ((0, 1),)),))


def saved(tmp_path, cfg=None, graphs=GRAPHS):
    torch.manual_seed(0)
    net = CompositionalNetwork(cfg or ModelConfig(), table(graphs))
    path = tmp_path / "m.pt"
    save_checkpoint(path, checkpoint_dict(net, parser="semantic", lexicon=LEXICON, step=7, metrics={"em": 1.5}))
    return net, path


def test_round_trip_is_bit_exact(tmp_path):
    net, path = saved(tmp_path)
    raw = torch.load(path, weights_only=True)  # plain dicts and tensors only
    assert raw["parser"] == "semantic" and raw["step"] == 7 and raw["metrics"] == {"em": 1.5}
    policy = Policy.from_checkpoint(path)
    for key, value in net.state_dict().items():
        assert torch.equal(value, policy.model.state_dict()[key]), key
    obs = random_states(np.random.default_rng(0), len(GRAPHS))
    net.eval()
    assert torch.equal(net.rollout(GRAPHS).step(obs)[0], policy.model.rollout(GRAPHS).step(obs)[0])
    assert policy.lexicon == LEXICON and policy.parser_name == "semantic"


def test_policy_steps_with_attention_per_word(tmp_path):
    _, path = saved(tmp_path)
    policy = Policy.from_checkpoint(path)
    graph = chain(["walk", "small", "circle"])
    policy.reset(graph)
    out = policy.step(random_states(np.random.default_rng(1), 1)[0])
    assert set(out.attention) == {"walk", "small", "circle"}
    assert all(m.shape == (6, 6) and m.dtype == np.float32 for m in out.attention.values())
    assert int(out.action) in range(7)
    with pytest.raises(GraphError, match="zigzagging"):
        policy.reset(chain(["while zigzagging", "walk", "circle"]))


def test_mismatched_config_or_vocabulary_is_a_checkpoint_error(tmp_path):
    _, path = saved(tmp_path)
    ckpt = read_checkpoint(path)
    with pytest.raises(CheckpointError, match="rnn_dim"):
        restore_model(ckpt, CompositionalNetwork(ModelConfig(rnn_dim=40), table()))
    with pytest.raises(CheckpointError, match="vocabulary"):
        restore_model(ckpt, CompositionalNetwork(ModelConfig(), table(GRAPHS[:2])))
    ckpt["state_dict"]["bank.out_w"] = ckpt["state_dict"]["bank.out_w"][:, :, :3]
    with pytest.raises(CheckpointError, match="bank.out_w"):
        restore_model(ckpt)


def test_a_checkpoint_written_before_a_setting_existed_resumes_with_its_default(tmp_path):
    net, path = saved(tmp_path)
    ckpt = read_checkpoint(path)
    del ckpt["model_config"]["size_map"]  # as written before model.size_map was added
    restore_model(ckpt, CompositionalNetwork(ModelConfig(), table()))
    with pytest.raises(CheckpointError, match="size_map"):
        restore_model(ckpt, CompositionalNetwork(ModelConfig(size_map="minmax"), table()))


@pytest.mark.parametrize("content", [b"not a checkpoint", None])
def test_unreadable_checkpoint(tmp_path, content):
    path = tmp_path / "bad.pt"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(CheckpointError, match="bad.pt"):
        Policy.from_checkpoint(path)


class Pickled:
    """A class torch's weights_only unpickler refuses (it would run code on load)."""


def test_a_checkpoint_whose_tensor_bytes_are_corrupt_is_refused_naming_it(tmp_path):
    """torch.load checks no CRC: 100 flipped bytes inside a tensor used to load (and
    evaluate) as other weights without a word."""
    from gscan_ros.model.policy import default_checkpoint_path

    data = bytearray(default_checkpoint_path().read_bytes())
    data[400_000:400_100] = bytes(b ^ 0x5A for b in data[400_000:400_100])
    path = tmp_path / "flip.pt"
    path.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match=r"checkpoint '.*flip\.pt' is corrupt: the CRC of \S+/data/\d+ does not"):
        read_checkpoint(path)
    read_checkpoint(default_checkpoint_path())  # the file it was copied from loads


def test_a_checkpoint_with_pickled_objects_is_refused_without_unsafe_advice(tmp_path):
    path = tmp_path / "pickled.pt"
    torch.save({"format": 1, "payload": Pickled()}, path)
    with pytest.raises(CheckpointError) as info:
        read_checkpoint(path)
    message = str(info.value)
    assert "pickled.pt" in message and "Pickled" in message  # what was refused
    assert "weights_only" not in message and "trust" not in message  # torch's advice to load it anyway
    assert "\n" not in message
