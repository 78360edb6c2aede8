"""The seq2seq baseline: closed-loop decoding computes what teacher forcing computes."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch

from gscan_ros.model.config import Seq2SeqConfig
from gscan_ros.model.decoder import Seq2SeqBatch, command_vocabulary
from gscan_ros.model.seq2seq import Seq2Seq

from model_support import random_states

COMMANDS = ["walk to a circle", "push a big red square while spinning", "pull a small cylinder cautiously"]


def test_closed_loop_follows_teacher_forcing_on_its_own_actions():
    """Decode greedily, then teacher-force the decoded actions: the logits agree at every
    step, also after `keep` drops a row (the key projections cached per sequence are
    selected with it)."""
    torch.manual_seed(0)
    model = Seq2Seq(Seq2SeqConfig(), command_vocabulary()).eval()
    states = random_states(np.random.default_rng(0), len(COMMANDS))
    steps = 6
    with torch.no_grad():
        rollout = model.rollout([SimpleNamespace(command=c) for c in COMMANDS])
        closed, actions = [], []
        for t in range(steps):
            logits, _ = rollout.step(states)
            closed.append(logits)
            actions.append(logits.argmax(-1))
            if t == 2:  # row 1 finishes early
                rollout.keep(torch.tensor([0, 2]))
        targets = torch.full((len(COMMANDS), steps), -1, dtype=torch.long)
        for t, a in enumerate(actions):
            rows = [0, 1, 2] if t <= 2 else [0, 2]
            targets[rows, t] = a
        forced = model.teacher_forcing(Seq2SeqBatch(COMMANDS, states, targets))
    # teacher forcing packs the valid steps row-major: row 0's steps, row 1's, row 2's
    lengths = (targets >= 0).sum(1).tolist()
    per_row = forced.logits.split(lengths)
    for row, got in enumerate(per_row):
        want = [closed[t][row if t <= 2 else [0, 2].index(row)] for t in range(lengths[row])]
        torch.testing.assert_close(got, torch.stack(want), rtol=1e-5, atol=1e-5)


def test_a_command_encodes_the_same_alone_and_beside_a_longer_one():
    """The encoder runs on packed sequences: padding changes neither the outputs at a
    command's own tokens nor its final state (the decoder's initial state)."""
    torch.manual_seed(0)
    model = Seq2Seq(Seq2SeqConfig(), command_vocabulary()).eval()
    with torch.no_grad():
        alone, final_alone, _ = model.encode_commands([COMMANDS[0]])
        batch, final_batch, mask = model.encode_commands(COMMANDS[:2])
    n = alone.shape[1]
    assert mask[0].sum() == n and not mask[0, n:].any()
    torch.testing.assert_close(batch[0, :n], alone[0])
    torch.testing.assert_close(final_batch[0], final_alone[0])
