"""`gscan-ros parse`: show how a command is parsed (the network a policy would build for it)."""
from __future__ import annotations

import argparse

from gscan_ros.errors import GscanError


def lexicon_name(text: str) -> str:
    """A `Lexicon.named` name; checked on use, so registering `parse` does not load NLTK."""
    from gscan_ros.language.lexicon import LEXICONS

    if text not in LEXICONS:
        raise argparse.ArgumentTypeError(f"invalid choice {text!r} (choose from {', '.join(LEXICONS)})")
    return text


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "parse",
        help="parse a command into a CommandGraph",
        description="Parse a command and print its graph as an indented tree (or JSON). A paraphrase "
        "(determiners, WordNet synonyms, adjective order) is first rewritten into the gSCAN command "
        "it means, and the rewrites are printed.",
    )
    p.add_argument("words", nargs="+", metavar="COMMAND",
                   help='e.g. "walk to a red small circle cautiously" or "Walk to the big red circle"')
    p.add_argument("--parser", help="a registered parser (default: the semantic parser; --all lists the built-in ones)")
    p.add_argument("--all", action="store_true", help="print the parse of every built-in parser")
    p.add_argument("--json", action="store_true", help="print the graph JSON (one line per parser)")
    p.add_argument(
        "--lexicon",
        type=lexicon_name,
        default="wordnet",
        metavar="NAME",
        help="wordnet: share modules between WordNet-related words (default); none: no sharing",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from gscan_ros.language import BUILTIN_PARSERS, DEFAULT_PARSER, Lexicon, canonicalize, get_parser

    if args.all and args.parser:
        raise GscanError("--all prints every parser's graph; --parser picks one")
    lexicon = Lexicon.named(args.lexicon)
    names = BUILTIN_PARSERS if args.all else (args.parser or DEFAULT_PARSER,)
    text = " ".join(args.words)
    graphs = [get_parser(name, lexicon).parse(text) for name in names]
    canonical = canonicalize(text)
    if canonical.mappings and not args.json:
        print(f"understood: {canonical.canonical}")
        for mapping in canonical.mappings:
            print(f"  {mapping}")
        print()
    for i, graph in enumerate(graphs):
        if args.json:
            print(graph.to_json())
            continue
        if args.all:
            print(("\n" if i else "") + f"{graph.parser}:")
        print(graph.pretty())
    return 0
