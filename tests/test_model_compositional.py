"""The compositional network on synthetic graphs and random one-hot states: properties the
equality with the reference (test_model_reference.py) does not show."""
import math

import numpy as np
import pytest
import torch

from gscan_ros.language import all_commands, get_parser
from gscan_ros.model.compositional import CompositionalNetwork, antonym_overlap
from gscan_ros.model.config import ModelConfig
from gscan_ros.model.layout import COLUMN_MAJOR_MAX_WIDTH, Layout
from gscan_ros.model.modules import ModuleTable
from gscan_ros.model.sparse_encoder import sparse_states

from model_support import GRAPHS, SIZE_KEY, binary, chain, make_net, random_states, table, teacher_batch

torch.set_num_threads(1)


def synthetic_batch(net, graphs, lengths, seed=0, quantum=1):
    """A TeacherBatch of `graphs` over random states and actions, episode i of lengths[i] steps."""
    rng = np.random.default_rng(seed)
    states = [random_states(rng, int(n)) for n in lengths]
    targets = [rng.integers(0, 7, int(n)) for n in lengths]
    return teacher_batch(net.table, graphs, states, targets, quantum)[0]


def test_step_shapes_and_softmax_maps():
    net = make_net()
    rollout = net.rollout(GRAPHS)
    logits, maps = rollout.step(random_states(np.random.default_rng(0), len(GRAPHS)))
    assert logits.shape == (len(GRAPHS), 7)
    assert maps.shape[0] == len(GRAPHS) and maps.shape[2] == 36
    for row, words in enumerate(rollout.words):
        for slot, _ in words:
            assert maps[row, slot].sum().item() == pytest.approx(1.0, abs=1e-5)


def test_dropping_rows_keeps_the_built_projection_weights_and_their_layout():
    net = make_net()  # levels of 10 columns (narrow) and 20 (wide)
    bound = net.bind(net.layout(GRAPHS))
    built = [bound.feat_w(level) for level in range(len(bound.blocks))]
    narrow = [w.shape[2] <= COLUMN_MAJOR_MAX_WIDTH for w in built]
    assert any(narrow) and not all(narrow)
    rows = torch.tensor([len(GRAPHS) - 1, 0])
    kept = bound.select(rows)
    for w, carried, is_narrow in zip(built, kept._feat_w, narrow):
        torch.testing.assert_close(carried, w.index_select(0, rows))
        assert (carried.stride(1) == 1) == is_narrow  # column-major exactly where it was


def test_parameter_count_matches_the_original():
    # github.com/ylkuo/compositional-gscan: ordinary arity-1 module 14,970 with 9 outputs;
    # ours has 7 (no PAD/SOS): 14,928.
    net = make_net(graphs=[chain(["walk", "circle"])])
    bank = net.bank
    m = net.table.index["walk"]
    module_params = [*bank.gru_x, *bank.gru_h, *bank.gru_bx, *bank.gru_bh, bank.out_w, bank.out_b]
    per_module = sum(p[m].numel() for p in module_params)
    per_unit = sum(getattr(bank, n)[0].numel() for n in ("att_feat_w", "att_feat_b", "att_state_w", "att_state_b",
                                                          "att_out_w", "att_out_b"))
    assert per_module + per_unit == 14_928
    assert sum(p.numel() for p in net.encoder.parameters()) == 60_150


def parse_table(parser: str) -> ModuleTable:
    """The modules of `parser`'s parses of every gSCAN command (no WordNet sharing)."""
    parse = get_parser(parser).parse
    return ModuleTable.from_graphs(parse(command) for command in all_commands())


@pytest.mark.parametrize("message", ["attention", "state", "attention+state"])
def test_each_module_is_initialised_as_a_linear_of_its_own_size(message):
    """A module's attention output layer and child-state layer start as CG's per-module
    Linear would: uniform within 1/sqrt(fan-in) of its own slots, not of the table's widest
    module (dependency: 2 slots), so a one-slot module's weights reach past the bound the
    widest module's fan-in would give."""
    table_ = parse_table("dependency")
    torch.manual_seed(0)
    bank = CompositionalNetwork(ModelConfig(message=message), table_).bank
    cfg, S = bank.cfg, bank.max_slots
    layers = []
    if cfg.uses_attention:  # per unit: its argument columns, the state column, the bias; fan-in (slots + 1) * A
        w, b = bank.att_out_w, bank.att_out_b
        layers += [(slots, torch.cat([w[u, :slots].flatten(), w[u, S], b[u, None]]), (slots + 1) * cfg.att_dim,
                    (S + 1) * cfg.att_dim) for u, slots in enumerate(bank.unit_slots)]
    if cfg.passes_state:  # per module: its children's rows and the bias; fan-in slots * L * H
        LH = cfg.rnn_layers * cfg.rnn_dim
        layers += [(slots, torch.cat([bank.state_w[m, : slots * LH].flatten(), bank.state_b[m]]), slots * LH, S * LH)
                   for m, slots in enumerate(bank.module_slots)]
    assert S == 2 and {slots for slots, *_ in layers} == {1, 2}
    for _, weights, fan_in, _ in layers:
        assert weights.abs().max() <= 1 / math.sqrt(fan_in)
    narrow = torch.cat([weights for slots, weights, *_ in layers if slots < S])
    assert narrow.abs().max() > 1 / math.sqrt(layers[0][3])


@pytest.mark.parametrize("message", ["attention", "state", "attention+state"])
def test_the_semantic_parse_starts_from_the_same_weights_either_way(message):
    """Its modules take one argument at most: 'module' and 'table' (the initialisation of the
    runs before `init_fan_in`) draw the same weights, bit for bit."""
    table_ = parse_table("semantic")
    nets = []
    for init_fan_in in ("module", "table"):
        torch.manual_seed(0)
        nets.append(CompositionalNetwork(ModelConfig(message=message, init_fan_in=init_fan_in), table_).state_dict())
    assert nets[0].keys() == nets[1].keys() and all(torch.equal(nets[0][k], nets[1][k]) for k in nets[0])


@pytest.mark.parametrize("message", ["attention", "attention+state"])
def test_the_parameter_count_leaves_out_the_slots_a_module_does_not_have(message):
    """Stacked to the widest module (2 slots here), a one-slot module's entries of slot 2 are
    never read: they get no gradient and the count (the `start` record's) leaves them out,
    so it is the sum of per-module counts as CG builds them."""
    from gscan_ros.model.checkpoint import parameter_count

    graphs = [chain(["walk", "circle"]), chain(["push", "big", "square"]), binary()]
    net = make_net(ModelConfig(message=message), graphs=graphs).train()
    cfg, bank = net.cfg, net.bank
    A, F, LH, H = cfg.att_dim, cfg.feature_dim, cfg.rnn_layers * cfg.rnn_dim, cfg.rnn_dim
    per_unit = sum(n * (F * A + A) + (LH * A + A) + ((n + 1) * A + 1) for n in bank.unit_slots)
    per_module = sum(p[0].numel() for p in [*bank.gru_x, *bank.gru_h, *bank.gru_bx, *bank.gru_bh, bank.out_w,
                                            bank.out_b]) * len(net.table)
    if cfg.passes_state:
        per_module += sum(n * LH * H + H for n in bank.module_slots)
    assert parameter_count(net) == 60_150 + per_module + per_unit < sum(p.numel() for p in net.parameters())
    net.teacher_forcing(synthetic_batch(net, graphs, [3, 5, 4])).loss.backward()
    for u, slots in enumerate(bank.unit_slots):
        assert not bank.att_feat_w.grad[u, slots:].any() and not bank.att_out_w.grad[u, slots:bank.max_slots].any()
    if cfg.passes_state:
        assert not any(bank.state_w.grad[m, slots * LH:].any() for m, slots in enumerate(bank.module_slots))


@pytest.mark.parametrize("message, attention_state", [("attention", "broadcast"), ("state", "broadcast"),
                                                      ("attention+state", "broadcast"), ("attention", "add")])
def test_gradients_reach_every_module_used(message, attention_state):
    graphs = [chain(["walk", "circle"]), chain(["push", "big", "square"]), binary()]
    net = make_net(ModelConfig(message=message, attention_state=attention_state), graphs=graphs).train()
    batch = synthetic_batch(net, graphs, [3, 5, 4])
    net.teacher_forcing(batch).loss.backward()
    bank, used = net.bank, {net.table.index[k] for g in graphs for k in g.modules()}
    if attention_state == "add":  # a module's state shapes its own map: every GRU matters
        assert (bank.att_state_w.grad.flatten(1).abs().sum(1) > 0).sum() >= len(used)
    if message == "attention" and attention_state == "broadcast":
        # Only maps leave a module, and its own state cancels in its attention's softmax
        # (the original broadcasts it over cells): only root GRUs can get gradient.
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
    exact = synthetic_batch(net, graphs, [9, 2, 5], quantum=1)
    padded = synthetic_batch(net, graphs, [9, 2, 5], quantum=8)  # finished rows ride along
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
    (word_a, shadow_a), (word_b, shadow_b) = layout.antonym_pairs[0, 0].tolist(), layout.antonym_pairs[1, 0].tolist()
    # 'small' in row 0 and 'big' in row 1 see identical inputs: their maps swap roles.
    torch.testing.assert_close(res.maps[0, word_a], res.maps[1, shadow_b])
    torch.testing.assert_close(res.maps[0, shadow_a], res.maps[1, word_b])
    assert not torch.allclose(res.maps[0, word_a], res.maps[0, shadow_a])
    assert (res.overlap > 0).all()
    spec = net.table.spec(SIZE_KEY)
    assert spec.num_heads == 2 and spec.antonyms == ((0, 1),)


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


def test_a_flat_head_escapes_the_minmax_overlap_but_not_the_cosine_one():
    """Worked by hand on 36 cells: min-max normalises a flat map to ~0, so its overlap with
    any map is ~0 (the way out Dependency's "small" head takes); the cosine overlap of a
    flat map and a one-hot map is (1/36) / (1/6 · 1) = 1/6, and 0 only for disjoint peaks."""
    flat, one_hot, other = torch.full((36,), 1 / 36), torch.zeros(36), torch.zeros(36)
    one_hot[3], other[20] = 1.0, 1.0
    minmax, cosine = ModelConfig(), ModelConfig(overlap="cosine")
    assert antonym_overlap(flat, one_hot, minmax).item() == pytest.approx(0.0, abs=1e-5)
    assert antonym_overlap(one_hot, one_hot, minmax).item() == pytest.approx(1 / 36, rel=1e-3)
    assert antonym_overlap(flat, one_hot, cosine).item() == pytest.approx(1 / 6)
    assert antonym_overlap(one_hot, other, cosine).item() == 0.0
    assert antonym_overlap(one_hot, one_hot, cosine).item() == pytest.approx(1.0)
    with pytest.raises(ValueError, match="overlap must be one of"):
        ModelConfig(overlap="sum")


@pytest.mark.parametrize("lexicon", ["wordnet", "none"])
def test_a_state_message_tells_big_from_small_only_with_a_module_each(lexicon):
    """A shared big|small module tells its words apart by their attention heads alone, and
    a state message reads no head: under WordNet sharing "big" and "small" act the same,
    which is why training refuses message 'state' with a shared lexicon."""
    from gscan_ros.language.lexicon import Lexicon

    parse = get_parser("semantic", Lexicon.named(lexicon)).parse
    graphs = [parse("push a big square"), parse("push a small square")]
    torch.manual_seed(0)
    net = CompositionalNetwork(ModelConfig(message="state"), ModuleTable.from_graphs(graphs)).eval()
    states = random_states(np.random.default_rng(0), 1)
    with torch.no_grad():
        logits = [net.rollout([g]).step(states)[0] for g in graphs]
    assert torch.equal(logits[0], logits[1]) == (lexicon == "wordnet")
