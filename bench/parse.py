"""Parses per second of each built-in parser over the 675 gSCAN commands.

cold: a fresh parser per pass, every command a cache miss (tokenize + chart parse +
graph build and validation); warm: repeated commands, answered from the per-parser
cache on the normalized token tuple (what the training loop and parser_node see).

    .venv/bin/python bench/parse.py [--passes 3] [--lexicon wordnet|none]
"""
from __future__ import annotations

import argparse
import time

from gscan_ros.language import Lexicon, all_commands, available_parsers, get_parser


def rate(parse_pass, passes: int, n: int) -> float:
    start = time.perf_counter()
    for _ in range(passes):
        parse_pass()
    return passes * n / (time.perf_counter() - start)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--passes", type=int, default=3, help="passes over the 675 commands per measurement")
    ap.add_argument("--lexicon", choices=("wordnet", "none"), default="wordnet")
    args = ap.parse_args()

    start = time.perf_counter()
    lexicon = Lexicon.from_wordnet() if args.lexicon == "wordnet" else Lexicon.none()
    print(f"lexicon ({args.lexicon}) built in {time.perf_counter() - start:.2f} s")
    commands = all_commands()
    print(f"{'parser':<14}{'cold parses/s':>16}{'warm parses/s':>16}")
    for name in available_parsers():
        def cold() -> None:
            parser = get_parser(name, lexicon)
            for command in commands:
                parser.parse(command)

        warm_parser = get_parser(name, lexicon)

        def warm() -> None:
            for command in commands:
                warm_parser.parse(command)

        warm()  # fill the cache
        cold_rate, warm_rate = rate(cold, args.passes, len(commands)), rate(warm, args.passes, len(commands))
        print(f"{name:<14}{cold_rate:>16,.0f}{warm_rate:>16,.0f}")


if __name__ == "__main__":
    main()
