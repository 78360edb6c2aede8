"""Constituency parser: the English phrase-structure tree (paper Fig. 2a) as a CommandGraph.

The chart parse of `phrase_grammar()` is reduced like the original's walk over its
ELMo parser's tree (ylkuo/compositional-gscan `language/parse.py`): S and determiners/prepositions are skipped, a PP
stands for its object NP, a clause adverb (SBAR, "while spinning") or ADVP is one leaf
named by its text. Phrases become modules keyed by label and arity ("VP_3", "NP_2");
words are arity-0 leaves keyed by word (or lexicon concept). Arc label = the child's
category; slots follow the phrase's word order, which the grammar fixes per label.
"""
from __future__ import annotations

from nltk.tree import Tree

from gscan_ros.language.grammar import parse_tree, phrase_grammar
from gscan_ros.language.graph import CommandGraph
from gscan_ros.language.parser import GrammarParser, GraphAssembler

SKIPPED_TAGS = frozenset({"DT", "TO", "IN"})  # function words carry no module
LEAF_PHRASES = frozenset({"ADVP", "SBAR"})  # adverbials are single leaves named by their text
TRANSPARENT_PHRASES = {"S": "VP", "PP": "NP"}  # phrase -> the child that stands for it


def tag(tree: Tree) -> str:
    """Penn category without the grammar's subcategory ("JJ-COLOR" -> "JJ")."""
    return tree.label().split("-")[0]


class ConstituencyParser(GrammarParser):
    name = "constituency"

    def _graph(self, tokens: tuple[str, ...]) -> CommandGraph:
        asm = GraphAssembler()
        root = self._convert(_skip_transparent(parse_tree(phrase_grammar(), tokens)), asm)
        return asm.build(" ".join(tokens), self.name, root)

    def _convert(self, tree: Tree, asm: GraphAssembler) -> int:
        node_id = asm.reserve()
        if _is_word(tree):
            word = " ".join(tree.leaves())
            module, head = self.lexicon.module_for(word)
            return asm.add(node_id, word, module, head=head)
        children = [
            (tag(child), self._convert(_skip_transparent(child), asm))
            for child in tree
            if tag(child) not in SKIPPED_TAGS
        ]
        return asm.add(node_id, tag(tree), f"{tag(tree)}_{len(children)}", children)


def _is_word(tree: Tree) -> bool:
    return tag(tree) in LEAF_PHRASES or all(isinstance(child, str) for child in tree)


def _skip_transparent(tree: Tree) -> Tree:
    while tag(tree) in TRANSPARENT_PHRASES:
        tree = next(child for child in tree if tag(child) == TRANSPARENT_PHRASES[tag(tree)])
    return tree
