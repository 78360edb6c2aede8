"""The compositional network's fast paths against plain reference computations."""
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from gscan_ros.model.compositional import Layout, ModelConfig, SlotGroups, _keep_mask, _ReluDrop, sparse_states
from tests.model_support import GRAPHS, binary, random_states
from tests.test_model_compositional import make_net

torch.set_num_threads(1)


def test_slot_groups_cover_each_selected_slot_once():
    keys = torch.tensor([[3, -1, 0], [0, 3, 3], [-1, 5, 0], [3, 3, -1]])
    groups = SlotGroups(keys)
    flat = keys.reshape(-1)
    assert groups.keys.tolist() == [0, 3, 5]
    selected = (flat >= 0).nonzero().squeeze(1)
    assert (groups.idx[groups.inv[selected]] == selected).all()  # every slot finds itself
    assert (groups.keys[groups.inv[selected] // groups.width] == flat[selected]).all()  # in its key's group
    assert groups.width == 5  # key 3 occurs five times


def test_slot_groups_of_an_empty_block():
    groups = SlotGroups(torch.full((2, 3), -1))
    assert groups.groups == 1 and groups.inv.shape == (6,)


@pytest.mark.parametrize("message", ["attention", "attention+state"])
def test_grouped_gru_matches_torch_gru_cells_per_slot(message):
    graphs = GRAPHS + [binary()]
    net = make_net(ModelConfig(message=message), graphs=graphs)
    bank, cfg = net.bank, net.cfg
    L, H = cfg.rnn_layers, cfg.rnn_dim
    bound = net.bind(Layout(graphs, net.table))
    if message == "attention":  # only the root's GRU runs
        groups = [(bound.top["root_module"][:, None], bound.gru_root)]
        expected = len(graphs)
    else:  # every real node's, block by block
        groups = [(blk["gru_module"], gru) for blk, gru in zip(bound.blocks, bound.gru)]
        expected = sum(len(g.nodes) for g in graphs)  # no antonym shadow
    gen = torch.Generator().manual_seed(0)
    checked = 0
    for modules, gru in groups:
        n, k = modules.shape
        x = torch.randn(n, k, bank.gru_x[0].shape[1], generator=gen)
        h = torch.randn(n, k, L * H, generator=gen)
        out = gru.run(x, h, L, H)
        for b, j in (modules >= 0).nonzero().tolist():
            m, inp, ref = int(modules[b, j]), x[b, j][None], []
            for layer in range(L):
                cell = torch.nn.GRUCell(inp.shape[1], H)
                with torch.no_grad():
                    cell.weight_ih.copy_(bank.gru_x[layer][m].T)
                    cell.weight_hh.copy_(bank.gru_h[layer][m].T)
                    cell.bias_ih.copy_(bank.gru_bx[layer][m])
                    cell.bias_hh.copy_(bank.gru_bh[layer][m])
                inp = cell(inp, h[b, j, layer * H : (layer + 1) * H][None])
                ref.append(inp[0])
            torch.testing.assert_close(out[b, j], torch.cat(ref), atol=1e-5, rtol=1e-5)
            checked += 1
    assert checked == expected


def test_leaf_maps_match_the_full_formula_with_the_state_term():
    """GSCAN_SPEC §8.4 in full, state input included, for every leaf: the fast path (which
    drops the state term, constant over cells) gives the same maps."""
    net = make_net()
    rows, layout = len(GRAPHS), Layout(GRAPHS, net.table)
    feats = net.encoder(*sparse_states(random_states(np.random.default_rng(5), rows)))
    hidden = torch.randn(rows, layout.num_slots, 40, generator=torch.Generator().manual_seed(2))
    maps = net.step(net.bind(layout), hidden, feats).maps
    bank, S = net.bank, net.bank.max_slots
    leaves = 0
    for b in range(rows):
        for j in range(layout.num_slots):
            if not layout.occupied[b, j] or layout.child[b, j].any():
                continue
            u, h = layout.unit[b, j], hidden[b, layout.src[b, j]]
            feat_part = F.relu(feats[b] @ bank.att_feat_w[u, 0] + bank.att_feat_b[u, 0])  # [cells, A]
            state_part = F.relu(h @ bank.att_state_w[u] + bank.att_state_b[u])  # [A], broadcast
            logits = feat_part @ bank.att_out_w[u, 0] + state_part @ bank.att_out_w[u, S] + bank.att_out_b[u]
            torch.testing.assert_close(maps[b, j], torch.softmax(logits, 0), atol=1e-6, rtol=1e-5)
            leaves += 1
    assert leaves >= rows


def test_relu_drop_matches_relu_times_mask_with_gradients():
    gen = torch.Generator().manual_seed(1)
    x = torch.randn(3, 36, 150, generator=gen)
    keep = torch.rand(3, 36, 150, generator=gen) >= 0.3
    upstream = torch.randn(3, 36, 150, generator=gen)
    fast_in, ref_in = x.clone().requires_grad_(), x.clone().requires_grad_()
    fast = _ReluDrop.apply(fast_in * 1.0, keep.view(torch.uint8))  # in place on a non-leaf, like the encoder
    ref = F.relu(ref_in) * keep
    torch.testing.assert_close(fast, ref)
    (fast * upstream).sum().backward()
    (ref * upstream).sum().backward()
    torch.testing.assert_close(fast_in.grad, ref_in.grad)


def test_drop_mask_rate_and_seeding():
    torch.manual_seed(3)
    keep, p = _keep_mask(200_001, 0.1)  # not a multiple of 4: the last 64-bit word is cut
    assert keep.dtype == torch.uint8 and keep.numel() == 200_001 and set(keep.unique().tolist()) == {0, 1}
    assert abs(p - 0.1) < 1e-4 and abs(1 - keep.float().mean().item() - p) < 0.005
    torch.manual_seed(3)
    assert torch.equal(_keep_mask(200_001, 0.1)[0], keep)  # torch.manual_seed fixes the mask


def test_training_encoder_is_dropout_of_the_dense_reference():
    net = make_net()
    states = random_states(np.random.default_rng(4), 16)
    dense = net.encoder.dense(torch.from_numpy(states))  # eval mode: no dropout
    net.encoder.train()
    torch.manual_seed(0)
    feats = net.encoder(*sparse_states(states))
    positive = dense > 0
    dropped = (feats == 0) & positive
    rate = dropped.sum().item() / positive.sum().item()
    assert 0.08 < rate < 0.12
    kept = positive & ~dropped
    torch.testing.assert_close(feats[kept], dense[kept] / (1 - net.cfg.cnn_dropout), atol=1e-4, rtol=1e-4)
    assert (feats[~positive] == 0).all()
