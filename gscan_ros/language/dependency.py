"""Dependency parser: head-dependent arcs with Universal Dependencies labels (paper Fig. 2b).

The phrase-structure parse is converted with head rules (a phrase's head child; every
other child's head word depends on it with a label fixed by the pair of categories),
the classic constituency-to-dependency conversion. This gives what an English UD
parser gives for gSCAN commands: the verb is the root, the noun its `obj` (push/pull)
or `obl` (walk to), adjectives `amod`, "cautiously" `advmod`, "while spinning"
`advcl`; function words (`det`, `case`) are dropped as in the original (ylkuo/compositional-gscan `language/parse.py`).

`graph_from_dependencies` turns any (words, heads, labels) analysis into a graph, so a
plugged-in spaCy/Stanza parser can share the conventions: one module per (word, arity),
e.g. "walk_2"; argument slots ordered by `ARG_LABEL_ORDER`, ties by sentence order;
several roots get a dummy root.
"""
from __future__ import annotations

from typing import Sequence

from nltk.tree import Tree

from gscan_ros.errors import GraphError, quoted
from gscan_ros.language.constituency import tag
from gscan_ros.language.grammar import parse_tree, phrase_grammar
from gscan_ros.language.graph import DUMMY_ROOT_WORD, CommandGraph
from gscan_ros.language.lexicon import Lexicon
from gscan_ros.language.parser import GrammarParser, GraphAssembler

# Canonical argument order: core arguments, then modifiers of nouns, then of verbs.
ARG_LABEL_ORDER = ("nsubj", "obj", "iobj", "obl", "nmod", "amod", "nummod", "advmod", "advcl", "xcomp", "conj")
DROPPED_LABELS = frozenset({"det", "case", "mark", "punct", "cc", "aux"})
ROOT_LABEL = "root"
# Head rules for `phrase_grammar()`: the category of each phrase's head child ...
HEAD_CHILD = {"S": "VP", "VP": "VB", "PP": "NP", "NP": "NN", "ADVP": "RB"}
# ... and the arc label of every other child, by (phrase, child category).
DEPENDENT_LABEL = {
    ("VP", "NP"): "obj",
    ("VP", "PP"): "obl",
    ("VP", "ADVP"): "advmod",
    ("VP", "SBAR"): "advcl",
    ("PP", "TO"): "case",
    ("NP", "DT"): "det",
    ("NP", "JJ"): "amod",
}


class DependencyParser(GrammarParser):
    name = "dependency"

    def _graph(self, tokens: tuple[str, ...]) -> CommandGraph:
        heads: list[int | None] = [None] * len(tokens)
        labels = [ROOT_LABEL] * len(tokens)
        _attach(parse_tree(phrase_grammar(), tokens), iter(range(len(tokens))), heads, labels)
        return graph_from_dependencies(" ".join(tokens), self.name, tokens, heads, labels, self.lexicon)


def _attach(tree: Tree, positions, heads: list[int | None], labels: list[str]) -> int:
    """Fill heads/labels for the words under `tree`; return the index of its head word."""
    if all(isinstance(child, str) for child in tree):  # a word (a preterminal, or SBAR's token)
        return next(positions)
    phrase = tag(tree)
    heads_of = [(tag(child), _attach(child, positions, heads, labels)) for child in tree]
    head = next(index for category, index in heads_of if category == HEAD_CHILD[phrase])
    for category, index in heads_of:
        if index != head:
            heads[index] = head
            labels[index] = DEPENDENT_LABEL[phrase, category]
    return head


def graph_from_dependencies(
    command: str,
    parser: str,
    words: Sequence[str],
    heads: Sequence[int | None],
    labels: Sequence[str],
    lexicon: Lexicon | None = None,
) -> CommandGraph:
    """CommandGraph of a dependency analysis: `heads[i]` is the index of word i's head
    (None, or i itself as spaCy writes it, for a root), `labels[i]` its arc label. Words attached by a label in
    `DROPPED_LABELS` are left out; two or more roots are joined under a dummy root.
    """
    lexicon = lexicon if lexicon is not None else Lexicon.none()
    if not len(words) == len(heads) == len(labels):
        raise GraphError(f"{len(words)} words but {len(heads)} heads and {len(labels)} labels")
    kept = [i for i in range(len(words)) if labels[i] not in DROPPED_LABELS]
    dependents: dict[int | None, list[int]] = {i: [] for i in kept} | {None: []}
    for i in kept:
        head = None if heads[i] == i else heads[i]
        if head not in dependents:
            raise GraphError(f"word {quoted(words[i])} depends on a dropped or unknown word (head {head})")
        dependents[head].append(i)
    for i in dependents:
        dependents[i].sort(key=lambda d: (_label_rank(labels[d]), labels[d], d))

    asm = GraphAssembler()
    ids = {i: asm.reserve() for i in kept}
    for i in kept:
        concept, head = lexicon.module_for(words[i])
        children = [(labels[d], ids[d]) for d in dependents[i]]
        asm.add(ids[i], words[i], f"{concept}_{len(children)}", children, head)
    roots = dependents[None]
    if not roots:
        raise GraphError(f"dependency analysis of {quoted(command)} has no root")
    if len(roots) == 1:
        return asm.build(command, parser, ids[roots[0]])
    dummy = asm.add(asm.reserve(), DUMMY_ROOT_WORD, f"{DUMMY_ROOT_WORD}_{len(roots)}",
                    [(ROOT_LABEL, ids[r]) for r in roots])
    return asm.build(command, parser, dummy)


def _label_rank(label: str) -> int:
    base = label.split(":")[0]  # UD subtypes ("obl:tmod") rank with their type
    return ARG_LABEL_ORDER.index(base) if base in ARG_LABEL_ORDER else len(ARG_LABEL_ORDER)
