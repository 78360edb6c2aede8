"""Semantic parser: the logical form of the paper's Fig. 2(c), a chain of content words.

The command must be a sentence of gSCAN's own grammar; its content words (function
words 'to'/'a' are bare terminals and drop out) are nested predicate over argument:
adverb over verb over color over size over noun, e.g.
`while spinning(walk(red(small(circle))))` (ylkuo/compositional-gscan `language/grammar.py`:
`to_arg_tree` + `reorg_arg_tree`). Root = the adverb, else the verb; every word has
arity 1 except the noun (0); word modules are keyed by word (or lexicon concept).

The chain depends only on each content word's preterminal category, which the grammar
gives every word exactly once, and the grammar's language is the finite set of 675
commands it enumerates. So a parse is a set lookup plus a sort by category, about ten
times cheaper than nltk's chart parse, which is run only to explain a rejection.
"""
from __future__ import annotations

from functools import cache

from gscan_ros.language.grammar import all_commands, gscan_grammar, parse_tree
from gscan_ros.language.graph import CommandGraph
from gscan_ros.language.parser import GrammarParser, GraphAssembler
from gscan_ros.language.tokens import tokenize

ARG_LABEL = "arg"
# Outermost first: which preterminal category takes which as its argument.
CHAIN_ORDER = ("RB", "VV_intrans", "VV_trans", "JJ_color", "JJ_size", "NN")
_RANK = {category: rank for rank, category in enumerate(CHAIN_ORDER)}


@cache
def _gscan_language() -> frozenset[tuple[str, ...]]:
    """The token tuples of the 675 commands `gscan_grammar()` derives."""
    return frozenset(tokenize(command) for command in all_commands())


@cache
def _chain_rank() -> dict[str, int]:
    """Content word -> its place in the chain, from the grammar's preterminal rules."""
    return {
        production.rhs()[0]: _RANK[production.lhs().symbol()]
        for production in gscan_grammar().productions()
        if production.lhs().symbol() in _RANK
    }


class SemanticParser(GrammarParser):
    name = "semantic"

    def _graph(self, tokens: tuple[str, ...]) -> CommandGraph:
        if tokens not in _gscan_language():
            parse_tree(gscan_grammar(), tokens)  # raises the grammar's CommandError
        rank = _chain_rank()
        chain = sorted((word for word in tokens if word in rank), key=rank.__getitem__)
        asm = GraphAssembler()
        ids = [asm.reserve() for _ in chain]
        for i, word in enumerate(chain):
            module, head = self.lexicon.module_for(word)
            children = [(ARG_LABEL, ids[i + 1])] if i + 1 < len(chain) else []
            asm.add(ids[i], word, module, children, head)
        return asm.build(" ".join(tokens), self.name, ids[0])
