"""language layer: tokens, canonical commands, grammars, parsers -> CommandGraph, WordNet lexicon
and synonyms (docs/language.md)."""
from gscan_ros.language.canonical import Canonical, WordMapping, canonicalize
from gscan_ros.language.dependency import graph_from_dependencies
from gscan_ros.language.grammar import all_commands, gscan_grammar, phrase_grammar
from gscan_ros.language.graph import CommandGraph, GraphEdge, GraphNode
from gscan_ros.language.lexicon import LEXICONS, Concept, Lexicon
from gscan_ros.language.parser import Parser
from gscan_ros.language.registry import BUILTIN_PARSERS, DEFAULT_PARSER, available_parsers, get_parser, register_parser
from gscan_ros.language.synonyms import SynonymTable, synonym_table
from gscan_ros.language.tokens import CONTENT_WORDS, MAX_TOKENS, VOCABULARY, tokenize

__all__ = [
    "ALL_COMMANDS",
    "BUILTIN_PARSERS",
    "CONTENT_WORDS",
    "Canonical",
    "CommandGraph",
    "Concept",
    "DEFAULT_PARSER",
    "GraphEdge",
    "GraphNode",
    "LEXICONS",
    "Lexicon",
    "MAX_TOKENS",
    "Parser",
    "SynonymTable",
    "VOCABULARY",
    "WordMapping",
    "all_commands",
    "available_parsers",
    "canonicalize",
    "get_parser",
    "graph_from_dependencies",
    "gscan_grammar",
    "phrase_grammar",
    "register_parser",
    "synonym_table",
    "tokenize",
]


def __getattr__(name: str):
    if name == "ALL_COMMANDS":  # enumerated from the grammar on first use
        return all_commands()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
