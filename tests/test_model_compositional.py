"""The compositional network on synthetic graphs and random one-hot states."""
import numpy as np
import pytest
import torch

from gscan_ros.model.compositional import (CompositionalNetwork, Layout, ModelConfig, TeacherBatch,
                                           sparse_states)
from tests.model_support import GRAPHS, SIZE_KEY, binary, chain, random_states, table

torch.set_num_threads(1)


def make_net(cfg=ModelConfig(), graphs=GRAPHS, seed=0):
    torch.manual_seed(seed)
    return CompositionalNetwork(cfg, table(graphs)).eval()


def synthetic_batch(net, graphs, lengths, seed=0, quantum=1):
    """A TeacherBatch over random states (rows must be given sorted by length, descending)."""
    rng = np.random.default_rng(seed)
    order = np.argsort(-np.asarray(lengths), kind="stable")
    graphs, lengths = [graphs[i] for i in order], np.asarray(lengths)[order]
    t_max = int(lengths[0])
    alive = np.array([(lengths > t).sum() for t in range(t_max)])
    active = np.minimum(-(-alive // quantum) * quantum, len(graphs))
    rows = np.concatenate([np.arange(n) for n in active])
    steps = np.repeat(np.arange(t_max), active)
    valid = steps < lengths[rows]
    per_row_states = [random_states(rng, int(n)) for n in lengths]
    per_row_targets = [rng.integers(0, 7, int(n)) for n in lengths]
    states = np.stack([per_row_states[r][s] if v else np.zeros((6, 6, 16), np.uint8)
                       for r, s, v in zip(rows, steps, valid)])
    targets = np.array([per_row_targets[r][s] if v else -1 for r, s, v in zip(rows, steps, valid)])
    idx, off = sparse_states(states)
    batch = TeacherBatch(Layout(graphs, net.table), idx, off, torch.from_numpy(targets), torch.from_numpy(rows),
                         torch.from_numpy(valid), torch.from_numpy(lengths.astype(np.float32)), list(map(int, active)))
    return batch, per_row_states, order


def test_sparse_encoder_matches_dense_conv():
    net = make_net()
    states = random_states(np.random.default_rng(1), 12)
    sparse = net.encoder(*sparse_states(states))
    dense = net.encoder.dense(torch.from_numpy(states))
    assert sparse.shape == (12, 36, 150)
    torch.testing.assert_close(sparse, dense, atol=1e-5, rtol=1e-5)


def test_large_kernel_is_cropped_to_the_grid():
    net = make_net(ModelConfig(cnn_kernels=(1, 5, 13)))
    states = random_states(np.random.default_rng(2), 4)
    torch.testing.assert_close(net.encoder(*sparse_states(states)), net.encoder.dense(torch.from_numpy(states)),
                               atol=1e-5, rtol=1e-5)


def test_step_shapes_and_softmax_maps():
    net = make_net()
    rollout = net.rollout(GRAPHS)
    logits, maps = rollout.step(random_states(np.random.default_rng(0), len(GRAPHS)))
    assert logits.shape == (len(GRAPHS), 7)
    assert maps.shape[0] == len(GRAPHS) and maps.shape[2] == 36
    for row, words in enumerate(rollout.words):
        for slot, _ in words:
            assert maps[row, slot].sum().item() == pytest.approx(1.0, abs=1e-5)


def test_parameter_count_matches_the_original():
    # GSCAN_SPEC §8.4: ordinary arity-1 module 14,970 with 9 outputs; ours has 7 (no PAD/SOS): 14,928.
    net = make_net(graphs=[chain(["walk", "circle"])])
    bank = net.bank
    m = net.table.index["walk"]
    per_module = sum(p[m].numel() for p in [*bank.gru_x, *bank.gru_h, *bank.gru_bx, *bank.gru_bh, bank.out_w, bank.out_b])
    per_unit = sum(getattr(bank, n)[0].numel() for n in ("att_feat_w", "att_feat_b", "att_state_w", "att_state_b",
                                                          "att_out_w", "att_out_b"))
    assert per_module + per_unit == 14_928
    assert sum(p.numel() for p in net.encoder.parameters()) == 60_150


@pytest.mark.parametrize("message, attention_state", [("attention", "broadcast"), ("state", "broadcast"),
                                                      ("attention+state", "broadcast"), ("attention", "add")])
def test_gradients_reach_every_module_used(message, attention_state):
    graphs = [chain(["walk", "circle"]), chain(["push", "big", "square"]), binary()]
    net = make_net(ModelConfig(message=message, attention_state=attention_state), graphs=graphs).train()
    batch, _, _ = synthetic_batch(net, graphs, [3, 5, 4])
    net.teacher_forcing(batch).loss.backward()
    bank, used = net.bank, {net.table.index[k] for g in graphs for k in g.modules()}
    if attention_state == "add":  # a module's state shapes its own map: every GRU matters
        assert (bank.att_state_w.grad.flatten(1).abs().sum(1) > 0).sum() >= len(used)
    if message == "attention" and attention_state == "broadcast":
        # Only maps leave a module, and its own state cancels in its attention's softmax
        # (GSCAN_SPEC §8.4 broadcasts it over cells): only root GRUs can get gradient.
        # (Before the fast path skipped the inert GRUs, the others got ~1e-8 rounding noise.)
        used_gru = {net.table.index[g.node(g.root).module] for g in graphs}
    else:
        used_gru = used
    for m in range(len(net.table)):
        grad = bank.gru_x[0].grad[m].abs().sum() + bank.gru_h[-1].grad[m].abs().sum()
        assert (grad > 0) == (m in used_gru), net.table.specs[m].key
    assert net.encoder.convs[2].weight.grad.abs().sum() > 0
    if message != "state":
        assert (bank.att_feat_w.grad.flatten(1).abs().sum(1) > 0).sum() >= len(used)


def test_padded_steps_contribute_nothing():
    graphs = [chain(["while spinning", "walk", "red", "small", "circle"]), chain(["walk", "small", "square"]),
              chain(["push", "big", "circle"])]
    net = make_net(graphs=graphs)
    exact, _, _ = synthetic_batch(net, graphs, [9, 2, 5], quantum=1)
    padded, _, _ = synthetic_batch(net, graphs, [9, 2, 5], quantum=8)  # finished rows ride along
    assert len(padded.rows) > len(exact.rows)
    out_exact, out_padded = net.teacher_forcing(exact), net.teacher_forcing(padded)
    torch.testing.assert_close(out_exact.loss, out_padded.loss)
    assert (out_padded.nll[~padded.valid] == 0).all() and (out_padded.overlap[~padded.valid] == 0).all()
    assert out_padded.overlap[padded.valid].sum() > 0  # the size words do produce an overlap term
    out_padded.loss.backward()  # and gradients stay finite
    assert all(torch.isfinite(p.grad).all() for p in net.parameters() if p.grad is not None)


def test_antonym_heads_differ_and_overlap_is_penalised():
    net = make_net()
    layout = Layout([chain(["walk", "small", "circle"]), chain(["walk", "big", "circle"])], net.table)
    bound = net.bind(layout)
    obs = random_states(np.random.default_rng(3), 1).repeat(2, 0)
    feats = net.encoder(*sparse_states(obs))
    res = net.step(bound, net.initial_hidden(2, layout.num_slots), feats)
    (word_a, shadow_a), (word_b, shadow_b) = layout.pairs[0, 0].tolist(), layout.pairs[1, 0].tolist()
    # 'small' in row 0 and 'big' in row 1 see identical inputs: their maps swap roles.
    torch.testing.assert_close(res.maps[0, word_a], res.maps[1, shadow_b])
    torch.testing.assert_close(res.maps[0, shadow_a], res.maps[1, word_b])
    assert not torch.allclose(res.maps[0, word_a], res.maps[0, shadow_a])
    assert (res.overlap > 0).all()
    spec = net.table.spec(SIZE_KEY)
    assert spec.num_heads == 2 and spec.antonyms == ((0, 1),)


@pytest.mark.parametrize("cfg", [ModelConfig(), ModelConfig(attention_state="add")], ids=["broadcast", "add"])
def test_mixed_batch_equals_per_command_batches(cfg):
    graphs = GRAPHS + [binary()]
    net = make_net(cfg, graphs=graphs)
    lengths = [4, 7, 3, 6, 5, 2]
    mixed, states, order = synthetic_batch(net, graphs, lengths, seed=5, quantum=4)
    out = net.teacher_forcing(mixed)
    for row, g_index in enumerate(order):
        graph, n = graphs[g_index], lengths[g_index]
        layout = Layout([graph], net.table)
        single = net.rollout([graph])
        per_step = [single.step(states[row][t : t + 1])[0][0] for t in range(n)]
        mine = out.logits[(mixed.rows == row) & mixed.valid]
        torch.testing.assert_close(torch.stack(per_step), mine, atol=1e-5, rtol=1e-5)
        assert layout.batch == 1


def test_rollout_keep_drops_rows_without_changing_the_others():
    net = make_net()
    obs = random_states(np.random.default_rng(7), len(GRAPHS))
    full = net.rollout(GRAPHS)
    full.step(obs)
    part = net.rollout(GRAPHS)
    part.step(obs)
    part.keep(torch.tensor([1, 3]))
    obs2 = random_states(np.random.default_rng(8), len(GRAPHS))
    torch.testing.assert_close(part.step(obs2[[1, 3]])[0], full.step(obs2)[0][[1, 3]], atol=1e-6, rtol=1e-6)


def test_unknown_module_is_a_graph_error():
    from gscan_ros.errors import GraphError

    net = make_net()
    with pytest.raises(GraphError, match="zigzag"):
        net.rollout([chain(["while zigzagging", "walk", "circle"])])


def test_layouts_of_a_new_table_never_reuse_another_tables_levels():
    """Level entries are cached per table: a table built after another one was freed (and
    possibly at the same address) must index its own modules."""
    import gc

    for graphs_first, graphs_then in [(GRAPHS, GRAPHS[-1:]), (GRAPHS[-1:], GRAPHS)] * 10:
        first = table(graphs_first)
        Layout(graphs_first, first)
        del first
        gc.collect()
        then = table(graphs_then)
        layout = Layout(graphs_then, then)
        assert int(layout.module.max()) < len(then.specs)


def test_minmax_size_maps_pass_the_normalised_map_to_the_parent():
    """size_map='minmax' (the original's quirk Q16): a big|small slot's map is its softmax
    map min-max normalised; every other slot's map is unchanged."""
    from gscan_ros.model.compositional import minmax_normalize

    soft, mm = make_net(ModelConfig()), make_net(ModelConfig(size_map="minmax"))
    layout = Layout(GRAPHS, soft.table)
    obs = random_states(np.random.default_rng(9), len(GRAPHS))
    feats = soft.encoder(*sparse_states(obs))
    maps = {}
    for name, net in (("softmax", soft), ("minmax", mm)):
        bound = net.bind(layout)
        maps[name] = net.step(bound, net.initial_hidden(len(GRAPHS), layout.num_slots), feats).maps
    size_slots = layout.has_antonyms
    assert size_slots.any() and (~size_slots & layout.occupied).any()
    first_size_block = next(i for i, (lo, hi) in enumerate(layout.blocks) if size_slots[:, lo:hi].any())
    lo, hi = layout.blocks[first_size_block]
    # blocks up to and including the first size block see identical inputs in both nets
    torch.testing.assert_close(maps["minmax"][:, lo:hi][size_slots[:, lo:hi]],
                               minmax_normalize(maps["softmax"][:, lo:hi][size_slots[:, lo:hi]]))
    torch.testing.assert_close(maps["minmax"][:, :lo], maps["softmax"][:, :lo])
    later = ~size_slots[:, hi:] & layout.occupied[:, hi:]  # parents read the normalised map
    assert not torch.allclose(maps["minmax"][:, hi:][later], maps["softmax"][:, hi:][later])


@pytest.mark.parametrize("attention_state", ["broadcast", "add"])
def test_a_modules_state_moves_its_map_only_when_added(attention_state):
    net = make_net(ModelConfig(attention_state=attention_state))
    layout = Layout(GRAPHS, net.table)
    bound = net.bind(layout)
    feats = net.encoder(*sparse_states(random_states(np.random.default_rng(4), len(GRAPHS))))
    zero = net.step(bound, net.initial_hidden(len(GRAPHS), layout.num_slots), feats).maps
    noise = torch.randn(len(GRAPHS), layout.num_slots, 40, generator=torch.Generator().manual_seed(1))
    moved = net.step(bound, noise, feats).maps
    assert torch.allclose(zero, moved, atol=1e-6) == (attention_state == "broadcast")


@pytest.mark.parametrize("kwargs, message", [
    ({"attention_state": "multiply"}, "attention_state"),
    ({"attention_state": "add", "message": "state"}, "needs attention maps"),
])
def test_bad_attention_state_is_named(kwargs, message):
    with pytest.raises(ValueError, match=message):
        ModelConfig(**kwargs)
