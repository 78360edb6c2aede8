"""The shipped model acts on a paraphrase exactly as on its canonical command (fixed situations)."""
import random
from dataclasses import replace

import numpy as np

from gscan_ros.data.commands import parse_command
from gscan_ros.data.episode import Episode
from gscan_ros.data.sampling import possible_targets, sample_placements, sample_situations
from gscan_ros.data.sources import sample_episode
from gscan_ros.language.paraphrase import paraphrase
from gscan_ros.model.policy import Policy
from gscan_ros.training.evaluate import evaluate_episodes
from gscan_ros.world import demonstrate

# Typed commands (the first is the paper's Fig. 1) -> the gSCAN command each means.
TYPED = {
    "Push the small blue cylinder": "push a blue small cylinder",
    "walk to a large circle": "walk to a big circle",
    "walk to the big red circle": "walk to a red big circle",
}


def episode_for(command: str, seed: int) -> Episode:
    """A situation generated for `command`, as the world node's random source draws one."""
    rng = np.random.default_rng(seed)
    parsed = parse_command(command)
    targets = possible_targets(parsed)
    placements = sample_placements(rng)
    situation = sample_situations(rng, parsed, targets[rng.integers(len(targets))], (placements[0],))[0]
    return Episode(command, situation, tuple(demonstrate(situation, command)), split="test")


def test_paraphrases_give_the_canonical_commands_actions():
    canonical = [episode_for(command, seed) for seed, command in enumerate(TYPED.values())]
    canonical += [sample_episode(seed) for seed in range(9)]
    typed = list(TYPED) + [paraphrase(ep.command, random.Random(i)) for i, ep in enumerate(canonical[3:])]
    assert all(t != ep.command for t, ep in zip(typed, canonical))
    policy = Policy.from_checkpoint()
    expected = evaluate_episodes(policy, canonical).predictions
    got = evaluate_episodes(policy, [replace(ep, command=t) for t, ep in zip(typed, canonical)]).predictions
    assert [p.actions for p in got] == [p.actions for p in expected]
    assert all(p.actions for p in got)
