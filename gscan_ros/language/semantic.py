"""Semantic parser: the logical form of the paper's Fig. 2(c), a chain of content words.

The command is parsed with gSCAN's own grammar; its content words (function words
'to'/'a' are bare terminals and drop out) are nested predicate over argument:
adverb over verb over color over size over noun, e.g.
`while spinning(walk(red(small(circle))))` (GSCAN_SPEC §8.3, the original's
`to_arg_tree` + `reorg_arg_tree`). Root = the adverb, else the verb; every word has
arity 1 except the noun (0); word modules are keyed by word (or lexicon concept).
"""
from __future__ import annotations

from nltk.tree import Tree

from gscan_ros.language.grammar import gscan_grammar, parse_tree
from gscan_ros.language.graph import CommandGraph
from gscan_ros.language.parser import GraphAssembler, GrammarParser

ARG_LABEL = "arg"
# Outermost first: which preterminal category takes which as its argument.
CHAIN_ORDER = ("RB", "VV_intrans", "VV_trans", "JJ_color", "JJ_size", "NN")
_RANK = {category: rank for rank, category in enumerate(CHAIN_ORDER)}


class SemanticParser(GrammarParser):
    name = "semantic"

    def _graph(self, tokens: tuple[str, ...]) -> CommandGraph:
        tree = parse_tree(gscan_grammar(), tokens)
        content = [
            (sub.label(), sub[0])
            for sub in tree.subtrees(lambda t: len(t) == 1 and not isinstance(t[0], Tree))
        ]
        chain = [word for _, word in sorted(content, key=lambda cw: _RANK[cw[0]])]
        asm = GraphAssembler()
        ids = [asm.reserve() for _ in chain]
        for i, word in enumerate(chain):
            module, head = self.lexicon.module_for(word)
            children = [(ARG_LABEL, ids[i + 1])] if i + 1 < len(chain) else []
            asm.add(ids[i], word, module, children, head)
        return asm.build(" ".join(tokens), self.name, ids[0])
