"""World benchmarks: planner throughput and closed-loop step+encode throughput.

    .venv/bin/python bench/world.py [--cases 2000] [--seconds 2] [--seed 0]

Cases are random 6x6 situations (2, 6 or 12 objects as in the generator, agent
facing east, not on an object) with a random verb, adverb and a referring form
that picks the target uniquely. Single process, single thread.
"""
from __future__ import annotations

import argparse
import random
import time

from gscan_ros.errors import SituationError
from gscan_ros.world import Action, CommandFrame, Heading, Position, Situation, World, WorldObject, demonstrate
from gscan_ros.world.planner import resolve_target
from gscan_ros.world.types import ADVERBS, COLORS, SHAPES, SIZES, VERBS, WORLD_ACTIONS

N = 6


def random_case(rng: random.Random) -> tuple[Situation, CommandFrame]:
    while True:
        cells = rng.sample([Position(r, c) for r in range(N) for c in range(N)], rng.choice((2, 6, 12)) + 1)
        agent, *cells = cells
        objects = tuple(WorldObject(rng.choice(SHAPES), rng.choice(COLORS), rng.choice(SIZES), p) for p in cells)
        target = objects[0]
        forms = [(None, None), (target.color, None), (None, "small"), (None, "big"),
                 (target.color, "small"), (target.color, "big")]
        rng.shuffle(forms)
        verb, manner = rng.choice(VERBS), rng.choice((None,) + ADVERBS)
        situation = Situation(agent, Heading.EAST, objects, target)
        for color, size in forms:
            frame = CommandFrame(verb, manner, color, size, target.shape)
            try:
                if resolve_target(situation, frame) == target:
                    return situation, frame
            except SituationError:
                continue


def rate(fn, seconds: float) -> tuple[float, int]:
    """Calls per second of fn() (which returns how many units it did), over ~seconds."""
    done, start = 0, time.perf_counter()
    while (elapsed := time.perf_counter() - start) < seconds:
        done += fn()
    return done / elapsed, done


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=2000)
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rng = random.Random(args.seed)
    cases = [random_case(rng) for _ in range(args.cases)]
    texts = [(s, f.text) for s, f in cases]
    lengths = [len(demonstrate(s, f)) for s, f in cases]
    print(f"cases: {len(cases)} (seed {args.seed}); mean target length {sum(lengths) / len(lengths):.1f}, "
          f"max {max(lengths)}")

    def planner(batch):
        def run():
            for s, c in batch:
                demonstrate(s, c)
            return len(batch)
        return run

    per_s, n = rate(planner(cases), args.seconds)
    print(f"demonstrate(situation, CommandFrame): {per_s:,.0f} calls/s ({n} calls)")
    per_s, n = rate(planner(texts), args.seconds)
    print(f"demonstrate(situation, command text): {per_s:,.0f} calls/s ({n} calls)")

    episodes = [(s, [rng.choice(WORLD_ACTIONS) for _ in range(40)]) for s, _ in cases[:200]]

    def closed_loop():
        steps = 0
        for s, actions in episodes:
            world = World(s)
            world.encode()
            for a in actions:
                world.step(a)
                world.encode()
            steps += len(actions)
        return steps

    per_s, n = rate(closed_loop, args.seconds)
    print(f"World.step + World.encode (random actions, incl. World() per 40 steps): {per_s:,.0f} steps/s ({n} steps)")
    tokens = [(s, [a.token for a in actions]) for s, actions in episodes]

    def replay_tokens():
        steps = 0
        for s, actions in tokens:
            world = World(s)
            for a in actions:
                world.step(a)
                world.encode()
            steps += len(actions)
        return steps

    per_s, n = rate(replay_tokens, args.seconds)
    print(f"World.step(token str) + World.encode: {per_s:,.0f} steps/s ({n} steps)")
    assert all(isinstance(a, Action) for a in demonstrate(*cases[0]))


if __name__ == "__main__":
    main()
