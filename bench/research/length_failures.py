"""Where split-I episodes fail, for several models on the same episodes.

    .venv/bin/gscan-ros evaluate --checkpoint CKPT --data DATA --splits target_lengths \\
        --max-examples 4000 --seed 1 --out OUT     # once per model: OUT/predictions.json
    .venv/bin/python bench/research/length_failures.py LABEL=OUT/predictions.json [LABEL=...]

Printed for every model, on the episodes all the files share: exact match by whether the
command has a size word, by the target's distance from the agent (cells, rows plus
columns), and by the length of the gold path's first straight leg; for that leg, the share
of episodes where the model turns before its end ("early turns"), and how many of the
model's failures are such a turn. A model that counts cells badly on long walks turns
early more often the longer the leg.
"""
from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/, for the benches' _data
from _data import labelled  # noqa: E402

SIZE_WORDS = ("big", "small")
DISTANCE_BINS = (0, 4, 8, 12, 16)  # lower ends; the last bin is open
LEG_LENGTHS = (2, 4, 6, 8, 10, 11)  # first-leg lengths printed (cells)


def first_leg(actions: list[str]) -> tuple[int, int]:
    """(turns before the first walk, walks in a row after them)."""
    turns = next((i for i, a in enumerate(actions) if not a.startswith("turn")), len(actions))
    walks = next((i for i, a in enumerate(actions[turns:]) if a != "walk"), len(actions) - turns)
    return turns, walks


def turned_early(episode: dict) -> bool:
    """The model started the gold's first leg and left it before its end."""
    gold_turns, gold_walks = first_leg(episode["target"])
    turns, walks = first_leg(episode["prediction"])
    return turns == gold_turns and walks < gold_walks


def distance_bin(episode: dict) -> str:
    distance = int(episode["situation"]["distance_to_target"])
    low = max(b for b in DISTANCE_BINS if b <= distance)
    return f">= {low}" if low == DISTANCE_BINS[-1] else f"{low}-{DISTANCE_BINS[DISTANCE_BINS.index(low) + 1] - 1}"


def percent(hits: int, n: int) -> str:
    return f"{100 * hits / n:5.1f}" if n else "    -"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("predictions", nargs="+", type=labelled("PREDICTIONS"), metavar="LABEL=PREDICTIONS",
                    help="predictions.json written by `gscan-ros evaluate` (without --no-predictions)")
    args = ap.parse_args()
    models = {}
    for label, path in args.predictions:
        try:
            with open(path) as f:
                models[label] = {(p["split"], p["example_id"]): p for p in json.load(f)}
        except (OSError, ValueError, KeyError, TypeError) as exc:
            sys.exit(f"length_failures: cannot read {path}: {exc}")
    shared = set.intersection(*(set(episodes) for episodes in models.values()))
    if not shared:
        sys.exit("length_failures: the files share no episode (evaluate them with the same --max-examples and --seed)")
    print(f"{len(shared)} episodes shared by {', '.join(models)}")
    groups = {
        "size word": lambda p: "with" if any(w in SIZE_WORDS for w in p["input"]) else "without",
        "distance": distance_bin,
    }
    for title, key in groups.items():
        print(f"\nexact match % by {title}")
        rows: dict[str, dict[str, list[int]]] = defaultdict(lambda: defaultdict(lambda: [0, 0]))
        for label, episodes in models.items():
            for ident in shared:
                cell = rows[key(episodes[ident])][label]
                cell[0] += episodes[ident]["exact_match"]
                cell[1] += 1
        for row in sorted(rows, key=lambda r: (len(r), r)):
            n = next(iter(rows[row].values()))[1]
            print(f"  {row:8s} (n={n:5d})  " + "  ".join(f"{label} {percent(*rows[row][label])}" for label in models))
    print("\nearly turns on the gold's first leg, % of episodes, by the leg's length (cells)")
    for label, episodes in models.items():
        by_leg: dict[int, list[int]] = defaultdict(lambda: [0, 0])
        for ident in shared:
            cell = by_leg[first_leg(episodes[ident]["target"])[1]]
            cell[0] += turned_early(episodes[ident])
            cell[1] += 1
        legs = "  ".join(f"{leg}: {percent(*by_leg[leg]).strip()}" for leg in LEG_LENGTHS if by_leg[leg][1])
        failed = [episodes[i] for i in shared if not episodes[i]["exact_match"]]
        early = sum(turned_early(p) for p in failed)
        print(f"  {label}: {legs}; {early} of its {len(failed)} failures ({percent(early, len(failed)).strip()} %)")


if __name__ == "__main__":
    main()
