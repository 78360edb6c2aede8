"""Parses per second of each built-in parser over the 675 gSCAN commands, and error paths.

cold: a fresh parser per pass, every command a cache miss (tokenize + parse + graph
build and validation); warm: repeated commands, answered from the per-parser cache on
the normalized token tuple (what the training loop and parser_node see). "rejects" are
the 675 commands reversed ("circle a to walk"): ungrammatical, so each is a
CommandError, cached like a graph. Last, the cost of rejecting a 10 kB unknown word.

    .venv/bin/python bench/parse.py [--passes 3] [--lexicon wordnet|none]
"""
from __future__ import annotations

import argparse
import time
from collections.abc import Callable

from gscan_ros.errors import CommandError
from gscan_ros.language import LEXICONS, Lexicon, all_commands, available_parsers, get_parser, tokenize


def rate(parse_pass: Callable[[], None], passes: int, n: int) -> float:
    start = time.perf_counter()
    for _ in range(passes):
        parse_pass()
    return passes * n / (time.perf_counter() - start)


def parse_all(parser, commands) -> None:
    for command in commands:
        try:
            parser.parse(command)
        except CommandError:
            pass


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--passes", type=int, default=3, help="passes over the 675 commands per measurement")
    ap.add_argument("--lexicon", choices=LEXICONS, default="wordnet")
    args = ap.parse_args()

    start = time.perf_counter()
    lexicon = Lexicon.named(args.lexicon)
    print(f"lexicon ({args.lexicon}) built in {time.perf_counter() - start:.2f} s")
    commands = all_commands()
    rejects = tuple(" ".join(reversed(tokenize(command))) for command in commands)
    print(f"{'parser':<14}{'cold parses/s':>16}{'warm parses/s':>16}{'cold rejects/s':>16}{'warm rejects/s':>16}")
    for name in available_parsers():
        row = []
        for inputs in (commands, rejects):
            warm_parser = get_parser(name, lexicon)
            parse_all(warm_parser, inputs)  # fill the cache
            def cold(name=name, inputs=inputs):
                return parse_all(get_parser(name, lexicon), inputs)

            def warm(parser=warm_parser, inputs=inputs):
                return parse_all(parser, inputs)

            row += [rate(cold, args.passes, len(inputs)), rate(warm, args.passes, len(inputs))]
        print(f"{name:<14}" + "".join(f"{r:>16,.0f}" for r in row))

    long_word = "walk to a " + "x" * 10_000
    calls = 200
    start = time.perf_counter()
    for _ in range(calls):
        try:
            tokenize(long_word)
        except CommandError:
            pass
    print(f"tokenize rejecting a 10 kB unknown word: {(time.perf_counter() - start) / calls * 1e3:.3f} ms")


if __name__ == "__main__":
    main()
