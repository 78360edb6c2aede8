"""AuxLoss and LCGN one episode, one word, one node and one step at a time: the test oracle of
tests/test_model_baselines.py.

Plain readings of gscan_ros/model/auxloss.py and lcgn.py with none of their batching: no
padding or packing (the BiLSTM runs its two directions word by word), a dense convolution
on the one-hot grid, the LSTM cells' gates written out, the graph's messages summed over
explicit node pairs, and the decoder fed each episode's gold actions one by one. It holds
no parameters of its own: it reads the model's, so gradients land on the same tensors.
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from gscan_ros.language.tokens import tokenize
from gscan_ros.model.lcgn import ATTRIBUTE_CHANNELS


def lstm_step(x, h, c, w_ih, w_hh, b_ih, b_hh):
    """One LSTM step (torch's gate order i, f, g, o)."""
    i, f, g, o = (w_ih @ x + b_ih + w_hh @ h + b_hh).chunk(4)
    c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
    return torch.sigmoid(o) * torch.tanh(c), c


def bilstm(lstm, embedded):
    """[tokens, E] -> forward and backward outputs [tokens, H] each, and both final states."""
    H = lstm.hidden_size
    outputs = []
    for suffix, order in (("", range(len(embedded))), ("_reverse", reversed(range(len(embedded))))):
        weights = [getattr(lstm, f"{name}_l0{suffix}") for name in ("weight_ih", "weight_hh", "bias_ih", "bias_hh")]
        h = c = embedded.new_zeros(H)
        out = [None] * len(embedded)
        for t in order:
            h, c = lstm_step(embedded[t], h, c, *weights)
            out[t] = h
        outputs.append((torch.stack(out), h))
    (fwd, h_fwd), (bwd, h_bwd) = outputs
    return fwd, bwd, h_fwd, h_bwd


def attend(att, query, keys):
    """Bahdanau attention of one query [Q] over keys [K_n, K]: (value [A], logits [K_n])."""
    projected = att.k(keys)
    logits = att.v(torch.tanh(att.q(query) + projected))[:, 0]
    return torch.softmax(logits, 0) @ projected, logits


def conv_features(visual, grid):
    """The 3-branch CNN on one [g, g, C] grid -> [cells, F] (dense conv, ReLU)."""
    x = grid.permute(2, 0, 1)[None]
    branches = [F.conv2d(x, conv.weight, conv.bias, padding=conv.kernel_size[0] // 2) for conv in visual.convs]
    return torch.relu(torch.cat(branches, 1))[0].flatten(1).T


def decode(model, text, world, h, targets, readout):
    """Teacher-forced logits [T+1, actions] of one episode from initial state h (= c)."""
    c, prev, logits = h, model.sos, []
    cell = model.decoder
    for target in targets:
        emb = model.action_embed.weight[prev]
        text_ctx, _ = attend(model.text_att, h, text)
        world_ctx, _ = attend(model.world_att, torch.tanh(model.world_query(torch.cat([h, text_ctx]))), world)
        h, c = lstm_step(torch.cat([emb, text_ctx, world_ctx]), h, c, cell.weight_ih, cell.weight_hh, cell.bias_ih,
                         cell.bias_hh)
        logits.append(readout(emb, h, text_ctx, world_ctx))
        prev = int(target)
    return torch.stack(logits)


def token_embeddings(model, command):
    """[tokens, E]: the command's token embeddings, no padding."""
    return model.embed.weight[[model.index[t] for t in tokenize(command)]]


def auxloss_episode(model, command, state, targets):
    """(action logits [T+1, actions], target-location logits [cells]) of one AuxLoss episode."""
    fwd, bwd, h_fwd, h_bwd = bilstm(model.encoder, token_embeddings(model, command))
    text, final = fwd + bwd, h_fwd + h_bwd
    world = conv_features(model.visual, torch.as_tensor(state, dtype=text.dtype))
    command_summary, _ = attend(model.think_text, final, text)
    query = torch.tanh(model.think_query(torch.cat([final, command_summary])))
    if model.cfg.think_scorer == "dot":  # each cell scored alone: q·k(cell)/√hidden
        q, cells = model.think_world.q(query), model.think_world.k(world)
        target_logits = torch.stack([torch.dot(q, cell) for cell in cells]) / len(q) ** 0.5
        located = torch.softmax(target_logits, 0) @ cells
    else:
        located, target_logits = attend(model.think_world, query, world)
    h = torch.tanh(model.enc_to_dec(final) + model.think_to_dec(torch.cat([command_summary, located])))

    def readout(emb, h, text_ctx, world_ctx):
        return model.out(model.pre_out(torch.cat([emb, h, text_ctx, world_ctx])))

    return decode(model, text, world, h, targets, readout), target_logits


def lcgn_nodes(graph, state, text, final):
    """The node outputs of one [g, g, 16] state as a [g, g, N] grid, node by node."""
    g = state.shape[0]
    occupied = [(r, c) for r in range(g) for c in range(g) if state[r, c].sum() > 0]
    x_loc, x_ctx = {}, {}
    for cell in occupied:
        groups = torch.as_tensor(state[cell], dtype=text.dtype).split(ATTRIBUTE_CHANNELS)
        x_loc[cell] = graph.node_in(torch.cat([embed(group) for embed, group in zip(graph.attributes, groups)]))
        x_ctx[cell] = graph.initial_context
    for t in range(len(graph.round_query)):
        query = graph.round_query[t](torch.relu(graph.command_query(final)))
        words = torch.softmax(torch.stack([graph.word_score(word * query)[0] for word in text]), 0)
        command = sum(w * word for w, word in zip(words, text))
        joint = {n: torch.cat([x_loc[n], x_ctx[n], graph.fuse_loc(x_loc[n]) * graph.fuse_ctx(x_ctx[n])])
                 for n in occupied}
        new_ctx = {}
        for i in occupied:
            senders = [j for j in occupied if j != i]
            message = torch.zeros_like(x_ctx[i])
            if senders:
                scores = torch.stack([graph.receiver(joint[i]) @ (graph.sender(joint[j]) * graph.sender_gate(command))
                                      for j in senders])
                for a, j in zip(torch.softmax(scores, 0), senders):
                    message = message + a * graph.value(joint[j]) * graph.value_gate(command)
            new_ctx[i] = graph.keep_context(x_ctx[i]) + graph.add_message(message)
        x_ctx = new_ctx
    grid = text.new_zeros(g, g, graph.node_out.out_features)
    for cell in occupied:
        grid[cell] = graph.node_out(torch.cat([x_loc[cell], x_ctx[cell]]))
    return grid


def lcgn_episode(model, command, state, targets):
    """(action logits [T+1, actions], None: no target-location logits) of one LCGN episode."""
    fwd, bwd, h_fwd, h_bwd = bilstm(model.encoder, token_embeddings(model, command))
    text, final = torch.cat([fwd, bwd], -1), torch.cat([h_fwd, h_bwd])
    world = conv_features(model.visual, lcgn_nodes(model.graph, state, text, final))
    h = torch.tanh(model.enc_to_dec(final))
    return decode(model, text, world, h, targets, lambda emb, h, text_ctx, world_ctx: model.out(h)), None


def loss(model, episode, commands, states, targets, target_cells=None):
    """The mean over episodes of `episode`'s mean action NLL, plus AuxLoss's weighted
    target-location cross-entropy (mean over episodes); and every episode's action logits."""
    per_episode, aux, logits = [], [], []
    for i, (command, state, episode_targets) in enumerate(zip(commands, states, targets)):
        gold = torch.as_tensor(np.asarray(episode_targets), dtype=torch.long)
        episode_logits, location = episode(model, command, state, gold)
        if location is not None:
            aux.append(F.cross_entropy(location[None], torch.as_tensor([target_cells[i]])))
        per_episode.append(F.cross_entropy(episode_logits, gold))
        logits.append(episode_logits)
    total = torch.stack(per_episode).mean()
    if aux:
        total = total + model.cfg.target_loss_weight * torch.stack(aux).mean()
    return total, logits
