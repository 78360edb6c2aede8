"""The fast compositional network against the plain per-graph, per-node reference.

For every setting of `message`, `attention_state`, `size_map` and `overlap`, with and without the
WordNet lexicon's antonym heads, and for graphs of all three parsers: teacher forcing's
logits, antonym overlap, loss and every parameter's gradient, and closed-loop decoding's
logits and maps, equal `ReferenceNetwork`'s on the same parameters (float64, eval mode).
"""
from __future__ import annotations

import functools

import numpy as np
import pytest
import torch

from gscan_ros.language.lexicon import Lexicon
from gscan_ros.language.registry import get_parser
from gscan_ros.model import teacher_forcing
from gscan_ros.model.compositional import CompositionalNetwork
from gscan_ros.model.config import ModelConfig
from gscan_ros.model.modules import ModuleTable
from gscan_ros.model.reference import ReferenceNetwork
from gscan_ros.world.types import Action

from model_support import episode_states, teacher_batch

torch.set_num_threads(1)

COMMANDS = [
    "walk to a red small circle while spinning",
    "push a big square cautiously",
    "pull a green cylinder hesitantly",
    "walk to a circle",
    "push a yellow small square",
    "pull a big cylinder while zigzagging",
]
# (parser, lexicon): the semantic parse with and without shared big|small heads, and the
# constituency and dependency parses (modules of arity 0 to 3, antonym heads on leaves).
PARSES = {"semantic": ("semantic", "wordnet"), "semantic-no-lexicon": ("semantic", None),
          "constituency": ("constituency", "wordnet"), "dependency": ("dependency", "wordnet")}
CONFIGS = [
    *({"message": m, "attention_state": a, "size_map": s}
      for m in ("attention", "attention+state") for a in ("broadcast", "add") for s in ("softmax", "minmax")),
    {"overlap": "cosine"}, {"overlap": "cosine", "size_map": "minmax"},
    {"message": "state", "rnn_dim": 40},  # CG's no-attention config
    {"cnn_kernels": (1, 5, 13)},  # a kernel wider than the grid, cropped by the sparse encoder
]
TIGHT = {"atol": 1e-10, "rtol": 1e-8}


@functools.cache
def _lexicon(name):
    return Lexicon.from_wordnet() if name == "wordnet" else Lexicon.none()


def build(parse: str, settings: dict, seed: int = 0):
    parser, lexicon = PARSES[parse]
    graphs = [get_parser(parser, _lexicon(lexicon)).parse(c) for c in COMMANDS]
    torch.manual_seed(seed)
    net = CompositionalNetwork(ModelConfig(**settings), ModuleTable.from_graphs(graphs, _lexicon(lexicon)))
    return net.double().eval(), graphs


def episodes(n: int, seed: int):
    """n episodes of 2-7 steps: states where objects stay and the agent moves, random
    actions then EOS."""
    rng = np.random.default_rng(seed)
    lengths = rng.integers(2, 8, n)
    states = [episode_states(rng, int(length)) for length in lengths]
    targets = [np.append(rng.integers(0, int(Action.EOS), int(length) - 1), int(Action.EOS)) for length in lengths]
    return states, targets


def gradients(loss: torch.Tensor, net: torch.nn.Module) -> list[torch.Tensor]:
    params = list(net.parameters())
    grads = torch.autograd.grad(loss, params, allow_unused=True)
    return [torch.zeros_like(p) if g is None else g for p, g in zip(params, grads)]


def _id(settings: dict) -> str:
    return ",".join(f"{k}={v}" for k, v in settings.items())


@pytest.mark.parametrize("parse", list(PARSES))
@pytest.mark.parametrize("settings", CONFIGS, ids=_id)
def test_teacher_forcing_equals_the_reference(settings, parse):
    net, graphs = build(parse, settings)
    states, targets = episodes(len(graphs), seed=1)
    ref_loss, traces = ReferenceNetwork(net).loss(graphs, states, targets)
    ref_grads = gradients(ref_loss, net)
    if parse in ("semantic", "constituency") and net.cfg.uses_attention:
        assert sum(t.overlap.sum() for t in traces) > 0  # big|small heads do produce the overlap term
    # The fast paths where they apply (all maps at once: a module's state does not move
    # its map); with quantum 3 finished rows ride along on padded steps.
    paths = [teacher_forcing.stepwise]
    if not net.cfg.runs_every_gru:
        paths.insert(0, teacher_forcing.all_steps)
    elif not net.cfg.state_in_attention:
        paths.insert(0, teacher_forcing.level_major)
    for path in paths:
        for quantum in (1, 3):
            batch, order = teacher_batch(net.table, graphs, states, targets, quantum)
            out = path(net, batch)
            where = f"{path.__name__}, quantum {quantum}"
            for row, episode in enumerate(order):
                mine = (batch.rows == row) & batch.valid
                torch.testing.assert_close(out.logits[mine], traces[episode].logits, **TIGHT, msg=where)
                torch.testing.assert_close(out.overlap[mine], traces[episode].overlap, **TIGHT, msg=where)
            assert (out.nll[~batch.valid] == 0).all() and (out.overlap[~batch.valid] == 0).all()
            torch.testing.assert_close(out.loss, ref_loss, **TIGHT, msg=where)
            for (name, _), mine, ref in zip(net.named_parameters(), gradients(out.loss, net), ref_grads):
                torch.testing.assert_close(mine, ref, **TIGHT, msg=f"{where}: gradient of {name}")


@pytest.mark.parametrize("parse", list(PARSES))
@pytest.mark.parametrize("settings", CONFIGS, ids=_id)
def test_closed_loop_equals_the_reference(settings, parse):
    """Rollout steps (finished rows dropped with `keep`) give the reference's logits, and
    every word's map and antonym map."""
    net, graphs = build(parse, settings, seed=2)
    states, _ = episodes(len(graphs), seed=3)
    with torch.no_grad():
        traces = [ReferenceNetwork(net).episode(g, s) for g, s in zip(graphs, states)]
        rollout = net.rollout(graphs)
        live = list(range(len(graphs)))
        for t in range(max(len(s) for s in states)):
            rows = [r for r, e in enumerate(live) if len(states[e]) > t]
            if len(rows) < len(live):
                rollout.keep(torch.tensor(rows))
                live = [live[r] for r in rows]
            logits, maps = rollout.step(np.stack([states[e][t] for e in live]))
            for row, e in enumerate(live):
                trace = traces[e]
                torch.testing.assert_close(logits[row], trace.logits[t], **TIGHT)
                if maps is None:
                    assert not net.cfg.uses_attention
                    continue
                for node, (slot, _) in zip(graphs[e].nodes, rollout.words[row]):
                    torch.testing.assert_close(maps[row, slot], trace.maps[node.id][t], **TIGHT)
                _, antonyms = rollout.word_maps(maps, row)
                expected = {graphs[e].node(nid).word: m[t] for nid, m in trace.antonym_maps.items()}
                assert antonyms.keys() == expected.keys()
                for word, grid in antonyms.items():
                    np.testing.assert_allclose(grid.reshape(-1), expected[word].numpy(), atol=1e-6)


def test_reference_gru_is_torch_gru():
    """The reference's GRU equations are torch.nn.GRU's, layer by layer."""
    net, graphs = build("semantic", {"message": "attention+state"})
    ref, cfg, bank = ReferenceNetwork(net), net.cfg, net.bank
    H = cfg.rnn_dim
    gen = torch.Generator().manual_seed(0)
    for module in range(len(net.table)):
        x = torch.randn(bank.gru_x[0].shape[1], generator=gen, dtype=torch.float64)
        h = torch.randn(cfg.rnn_layers * H, generator=gen, dtype=torch.float64)
        gru = torch.nn.GRU(x.numel(), H, cfg.rnn_layers).double()
        with torch.no_grad():
            for layer in range(cfg.rnn_layers):
                getattr(gru, f"weight_ih_l{layer}").copy_(bank.gru_x[layer][module].T)
                getattr(gru, f"weight_hh_l{layer}").copy_(bank.gru_h[layer][module].T)
                getattr(gru, f"bias_ih_l{layer}").copy_(bank.gru_bx[layer][module])
                getattr(gru, f"bias_hh_l{layer}").copy_(bank.gru_bh[layer][module])
            _, expected = gru(x[None, None], h.view(cfg.rnn_layers, 1, H))
            torch.testing.assert_close(ref.gru(module, x, h), expected.reshape(-1), **TIGHT)
