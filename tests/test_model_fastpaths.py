"""The compositional network's fast paths, piece by piece, against the plain computations
they replace (the whole network against its reference: test_model_reference.py)."""
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from gscan_ros.model.config import ModelConfig
from gscan_ros.model.fast_ops import (
    BagSum,
    ContiguousGrad,
    GruRecurrence,
    ReluDrop,
    RowGather,
    SegmentMatmul,
    gru_update,
    keep_mask,
)
from gscan_ros.model.layout import SlotGroups
from gscan_ros.model.sparse_encoder import shared_bits, sparse_states

from model_support import episode_states, make_net, random_states

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


def test_relu_drop_matches_relu_times_mask_with_gradients():
    gen = torch.Generator().manual_seed(1)
    x = torch.randn(3, 36, 150, generator=gen)
    keep = torch.rand(3, 36, 150, generator=gen) >= 0.3
    upstream = torch.randn(3, 36, 150, generator=gen)
    fast_in, ref_in = x.clone().requires_grad_(), x.clone().requires_grad_()
    fast = ReluDrop.apply(fast_in * 1.0, keep.view(torch.uint8))  # in place on a non-leaf, like the encoder
    ref = F.relu(ref_in) * keep
    torch.testing.assert_close(fast, ref)
    (fast * upstream).sum().backward()
    (ref * upstream).sum().backward()
    torch.testing.assert_close(fast_in.grad, ref_in.grad)


def test_drop_mask_rate_and_seeding():
    torch.manual_seed(3)
    keep, p = keep_mask(200_001, 0.1)  # not a multiple of 4: the last 64-bit word is cut
    assert keep.dtype == torch.uint8 and keep.numel() == 200_001 and set(keep.unique().tolist()) == {0, 1}
    assert abs(p - 0.1) < 1e-4 and abs(1 - keep.float().mean().item() - p) < 0.005
    torch.manual_seed(3)
    assert torch.equal(keep_mask(200_001, 0.1)[0], keep)  # torch.manual_seed fixes the mask


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
    """The states of several episodes (objects stay, the agent moves), plus each state's episode id."""
    states = [episode_states(rng, n) for n in lengths]
    return np.concatenate(states), torch.tensor(np.repeat(np.arange(len(lengths)), lengths))


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
    (shared, shared_off), own, own_off = shared_bits(idx, off, groups, width)
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


def test_bag_sum_is_the_embedding_bag_with_its_gradient():
    """Empty bags and a row twice in one bag included (the incidence then holds a 2)."""
    torch.manual_seed(0)
    weight = torch.randn(9, 4, dtype=torch.float64, requires_grad=True)
    rows = torch.tensor([3, 1, 3, 0, 8, 8, 2, 5])
    starts = torch.tensor([0, 3, 3, 6, 8])  # bags of 3, 0, 3, 2 and 0 rows
    grad = torch.randn(5, 4, dtype=torch.float64)
    (expected,) = torch.autograd.grad(F.embedding_bag(rows, weight, starts, mode="sum"), weight, grad)
    out = BagSum.apply(rows, weight, starts)
    (got,) = torch.autograd.grad(out, weight, grad)
    assert torch.equal(out, F.embedding_bag(rows, weight, starts, mode="sum"))
    assert torch.allclose(got, expected, atol=1e-12)
    assert got[3].allclose(2 * grad[0]) and got[8].allclose(2 * grad[2])


def test_row_gather_is_the_indexing_gather_with_its_gradient():
    """A row used many times, one used once and one never used (its gradient is 0)."""
    weight = torch.randn(5, 3, dtype=torch.float64, requires_grad=True)
    index = torch.tensor([[4, 0, 4], [1, 4, 0]])
    out = RowGather.apply(weight, index, *RowGather.plan(index, 5))
    assert torch.equal(out, weight[index])
    assert torch.autograd.gradcheck(lambda w: RowGather.apply(w, index, *RowGather.plan(index, 5)), (weight,))
    (grad,) = torch.autograd.grad(out.sum(), weight)
    assert grad[:, 0].tolist() == [2.0, 1.0, 0.0, 0.0, 3.0]


def test_contiguous_grad_is_the_identity_and_hands_back_a_contiguous_gradient():
    x = torch.randn(4, 6, requires_grad=True)
    seen = []
    y = ContiguousGrad.apply(x)
    assert torch.equal(y, x)
    x.register_hook(lambda g: seen.append(g.is_contiguous()))
    y.backward(torch.randn(6, 4).T)  # a transposed, non-contiguous upstream gradient
    assert seen == [True]


@pytest.mark.parametrize("grid", [6, 12])
def test_gathered_toeplitz_weight_is_the_plain_one_with_gradients(grid):
    """`SparseConv.weight` (one gather of canvas rows) against `plain_weight` (sparse
    placement product, permute, bias row), values and conv gradients, with dropout's scale."""
    torch.manual_seed(grid)
    net = make_net(ModelConfig(grid_size=grid))
    enc = net.encoder
    upstream = None
    results = []
    for build in (enc.sparse.weight, enc.sparse.plain_weight):
        enc.zero_grad()
        w = build(enc.convs, 1.25)
        if upstream is None:
            upstream = torch.randn(w.shape)
        w.backward(upstream)
        results.append((w.detach(), [p.grad.clone() for p in enc.convs.parameters()]))
    (fast, fast_grads), (plain, plain_grads) = results
    assert torch.equal(fast, plain)
    for got, want in zip(fast_grads, plain_grads):
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-4)


def test_segment_matmul_gradients():
    gen = torch.Generator().manual_seed(2)
    x = torch.randn(7, 3, 5, dtype=torch.float64, generator=gen, requires_grad=True)
    w = torch.randn(3, 5, 4, dtype=torch.float64, generator=gen, requires_grad=True)
    sizes = [2, 0, 5]  # an empty segment too
    out = SegmentMatmul.apply(x, w, sizes)
    ref = torch.cat([xs @ w[b] for b, xs in enumerate(x.split(sizes))])
    torch.testing.assert_close(out, ref)
    assert torch.autograd.gradcheck(lambda a, b: SegmentMatmul.apply(a, b, sizes), (x, w))


@pytest.mark.parametrize("lanes", [[4, 4, 3, 3, 1], [2], [3, 1, 1, 1]])
def test_gru_recurrence_is_the_cell_unrolled_with_gradients(lanes):
    """Packed time-major steps whose lanes shrink (finished rows leave), each lane with its
    own recurrent weights: the same states and gradients as `gru_update` step by step."""
    gen = torch.Generator().manual_seed(3)
    H, R = 3, lanes[0]
    gx = torch.randn(sum(lanes), 3 * H, dtype=torch.float64, generator=gen, requires_grad=True)
    wh = torch.randn(R, H, 3 * H, dtype=torch.float64, generator=gen, requires_grad=True)
    bh = torch.randn(R, 1, 3 * H, dtype=torch.float64, generator=gen, requires_grad=True)
    h, ref = torch.zeros(R, 1, H, dtype=torch.float64), []
    for n, gx_t in zip(lanes, gx.split(lanes)):
        h = gru_update(gx_t[:, None], torch.baddbmm(bh[:n], h[:n], wh[:n]), h[:n])
        ref.append(h[:, 0])
    torch.testing.assert_close(GruRecurrence.apply(gx, wh, bh, lanes), torch.cat(ref))
    assert torch.autograd.gradcheck(lambda a, b, c: GruRecurrence.apply(a, b, c, lanes), (gx, wh, bh))




def grid_episode_states(rng: np.random.Generator, g: int, lengths: list[int]) -> tuple[np.ndarray, torch.Tensor]:
    """Episodes on a g x g grid (objects stay, the agent moves) and each state's episode id."""
    episodes = []
    for length in lengths:
        objects = np.zeros((g, g, 16), dtype=np.uint8)
        for c in rng.choice(g * g, size=6, replace=False):
            r, col = divmod(int(c), g)
            objects[r, col, [rng.integers(0, 4), 4 + rng.integers(0, 3), 7 + rng.integers(0, 4)]] = 1
        states = np.repeat(objects[None], length, 0)
        for t in range(length):
            r, col = divmod(int(rng.integers(g * g)), g)
            states[t, r, col, [11, 12 + rng.integers(0, 4)]] = 1
        episodes.append(states)
    return np.concatenate(episodes), torch.tensor(np.repeat(np.arange(len(lengths)), lengths))


@pytest.mark.parametrize("grid", [8, 12])
@pytest.mark.parametrize("grouped", [False, True])
def test_per_cell_training_encoder_matches_the_dense_conv_with_gradients(grid, grouped):
    net = make_net(ModelConfig(grid_size=grid, cnn_kernels=(1, 5, 13), cnn_dropout=0.0))
    assert net.encoder.sparse.per_cell  # wide grids train through the canvas bags
    states, groups = grid_episode_states(np.random.default_rng(grid), grid, [4, 1, 6])
    groups[2] = -1  # a state outside any group keeps all its bits
    net.encoder.train()
    fast = net.encoder(*sparse_states(states), groups=groups if grouped else None)
    dense = net.encoder.dense(torch.from_numpy(states))
    torch.testing.assert_close(fast, dense, atol=1e-4, rtol=1e-4)
    upstream = torch.randn_like(dense)
    params = list(net.encoder.parameters())
    for a, b in zip(torch.autograd.grad((fast * upstream).sum(), params),
                    torch.autograd.grad((dense * upstream).sum(), params), strict=True):
        torch.testing.assert_close(a, b, atol=1e-3, rtol=1e-4)


def test_per_cell_and_toeplitz_training_paths_drop_the_same_features():
    net = make_net(ModelConfig(grid_size=8))
    states, groups = grid_episode_states(np.random.default_rng(3), 8, [5, 3])
    bags = sparse_states(states)
    net.encoder.train()
    out = []
    for per_cell in (True, False):
        net.encoder.sparse.per_cell = per_cell
        torch.manual_seed(5)
        out.append(net.encoder(*bags, groups=groups))
    torch.testing.assert_close(out[0], out[1], atol=1e-5, rtol=1e-5)
    assert (out[0] == 0).float().mean() > 0.1  # the dropout (p = 0.1) applied to both
