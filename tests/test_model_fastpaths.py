"""The compositional network's fast paths against plain reference computations."""
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from gscan_ros.model.compositional import (Layout, ModelConfig, SlotGroups, _keep_mask, _ReluDrop, _SegmentMatmul,
                                           _shared_bits, sparse_states)
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


def _broadcast_logits(bank, u, feats, h):
    """GSCAN_SPEC §8.4 in full: ReLU(feats W + b) ++ ReLU(h W_h + b_h), broadcast, -> Linear."""
    feat_part = F.relu(feats @ bank.att_feat_w[u, 0] + bank.att_feat_b[u, 0])  # [cells, A]
    state_part = F.relu(h @ bank.att_state_w[u] + bank.att_state_b[u])  # [A], broadcast
    return feat_part @ bank.att_out_w[u, 0] + state_part @ bank.att_out_w[u, bank.max_slots] + bank.att_out_b[u]


def _add_logits(bank, u, feats, h):
    """attention_state='add': ReLU(feats W + b + h W_h + b_h) per cell -> Linear (the
    concatenated state column still cancels)."""
    state = h @ bank.att_state_w[u] + bank.att_state_b[u]
    return F.relu(feats @ bank.att_feat_w[u, 0] + bank.att_feat_b[u, 0] + state) @ bank.att_out_w[u, 0]


@pytest.mark.parametrize("attention_state, reference", [("broadcast", _broadcast_logits), ("add", _add_logits)])
def test_leaf_maps_match_the_full_formula_with_the_state_term(attention_state, reference):
    """Every leaf's map against the formula with the state input included: the fast path
    (which drops the broadcast state term, constant over cells) gives the same maps."""
    net = make_net(ModelConfig(attention_state=attention_state))
    rows, layout = len(GRAPHS), Layout(GRAPHS, net.table)
    feats = net.encoder(*sparse_states(random_states(np.random.default_rng(5), rows)))
    hidden = torch.randn(rows, layout.num_slots, 40, generator=torch.Generator().manual_seed(2))
    maps = net.step(net.bind(layout), hidden, feats).maps
    leaves = 0
    for b in range(rows):
        for j in range(layout.num_slots):
            if not layout.occupied[b, j] or layout.child[b, j].any():
                continue
            logits = reference(net.bank, layout.unit[b, j], feats[b], hidden[b, layout.src[b, j]])
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


def episode_like_states(rng: np.random.Generator, lengths: list[int]) -> tuple[np.ndarray, torch.Tensor]:
    """States where most bits persist within an episode (objects) and a few change each
    step (an 'agent' bit moving over the grid), plus each state's episode id."""
    states, groups = [], []
    for ep, n in enumerate(lengths):
        base = random_states(rng, 1)[0]
        for _ in range(n):
            s = base.copy()
            s.reshape(-1, 16)[rng.integers(36), 11 + rng.integers(5)] = 1  # agent + heading channels
            states.append(s)
            groups.append(ep)
    return np.stack(states), torch.tensor(groups)


@pytest.mark.parametrize("train", [False, True])
def test_encoder_with_shared_episode_bits_matches_plain_bags(train):
    net = make_net(ModelConfig(cnn_dropout=0.0))
    net.encoder.train(train)
    states, groups = episode_like_states(np.random.default_rng(7), [5, 1, 8, 3])
    groups[[2, 9]] = -1  # states outside any group keep all their bits
    idx, off = sparse_states(states)
    plain = net.encoder(idx, off)
    shared = net.encoder(idx, off, groups=groups)
    torch.testing.assert_close(shared, plain, atol=1e-5, rtol=1e-5)
    upstream = torch.randn_like(plain)
    grads = [torch.autograd.grad((out * upstream).sum(), list(net.encoder.parameters())) for out in (plain, shared)]
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-4)


def test_shared_bits_are_the_bits_every_state_of_the_group_has():
    states, groups = episode_like_states(np.random.default_rng(8), [4, 6])
    idx, off = sparse_states(states)
    width = 36 * 16 + 1
    (shared, shared_off), own, own_off = _shared_bits(idx, off, groups, width)
    flat = states.reshape(len(states), -1).astype(bool)
    for g in range(2):
        expected = set(np.flatnonzero(flat[(groups == g).numpy()].all(0))) | {width - 1}
        hi = shared_off[g + 1] if g + 1 < len(shared_off) else len(shared)
        assert set(shared[shared_off[g]:hi].tolist()) == expected
    assert len(own) + len(shared) - 2 < len(idx)  # fewer additions than the plain bags
    for n in range(len(states)):  # own bits + the group's bits = the state's bits
        hi = own_off[n + 1] if n + 1 < len(own_off) else len(own)
        g = int(groups[n])
        shi = shared_off[g + 1] if g + 1 < len(shared_off) else len(shared)
        mine = set(own[own_off[n]:hi].tolist()) | set(shared[shared_off[g]:shi].tolist()) - {width - 1}
        assert mine == set(np.flatnonzero(flat[n]))


def test_segment_matmul_gradients():
    gen = torch.Generator().manual_seed(2)
    x = torch.randn(7, 3, 5, dtype=torch.float64, generator=gen, requires_grad=True)
    w = torch.randn(3, 5, 4, dtype=torch.float64, generator=gen, requires_grad=True)
    sizes = [2, 0, 5]  # an empty segment too
    out = _SegmentMatmul.apply(x, w, sizes)
    ref = torch.cat([xs @ w[b] for b, xs in enumerate(x.split(sizes))])
    torch.testing.assert_close(out, ref)
    assert torch.autograd.gradcheck(lambda a, b: _SegmentMatmul.apply(a, b, sizes), (x, w))


@pytest.mark.parametrize("quantum, size_map", [(1, "softmax"), (4, "softmax"), (1, "minmax")])
def test_all_steps_at_once_matches_step_by_step(quantum, size_map):
    from tests.test_model_compositional import synthetic_batch

    graphs = GRAPHS + [binary()]
    net = make_net(ModelConfig(size_map=size_map), graphs=graphs)
    batch, _, _ = synthetic_batch(net, graphs, [4, 7, 3, 6, 5, 2], seed=3, quantum=quantum)
    fast, slow = net._teacher_forcing_parallel(batch), net._teacher_forcing_stepwise(batch)
    torch.testing.assert_close(fast.logits, slow.logits, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(fast.overlap, slow.overlap, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(fast.loss, slow.loss)
    params = [p for p in net.parameters()]
    g_fast = torch.autograd.grad(fast.loss, params, allow_unused=True)
    g_slow = torch.autograd.grad(slow.loss, params, allow_unused=True)
    for (name, _), a, b in zip(net.named_parameters(), g_fast, g_slow):
        a = torch.zeros_like(_) if a is None else a
        b = torch.zeros_like(_) if b is None else b
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-4, msg=name)

