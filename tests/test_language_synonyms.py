"""The WordNet synonym table: generated from the chosen senses, every entry reaches a trained module."""
import re
from pathlib import Path

import pytest

from gscan_ros.errors import CommandError, LexiconError
from gscan_ros.language import VOCABULARY, canonicalize, get_parser, synonym_table, synonyms
from gscan_ros.language.canonical import DETERMINERS
from gscan_ros.language.grammar import CLAUSE_ADVERBS
from gscan_ros.language.lexicon import wordnet_reader, wordnet_root
from gscan_ros.language.synonyms import EXCLUDED_SENSES, EXCLUDED_WORDS, GSCAN_SENSES
from gscan_ros.language.tokens import CONTENT_WORDS
from gscan_ros.model.policy import Policy
from gscan_ros.world.types import ADVERBS, COLOR_ADJECTIVES, NOUNS, SIZE_ADJECTIVES, VERBS

DOCS = Path(__file__).resolve().parents[1] / "docs" / "language.md"
TABLE = synonym_table()
# A command with one slot for a word of each category.
TEMPLATE = {
    **{v: "{} a circle" for v in VERBS},
    **{n: "push a {}" for n in NOUNS},
    **{c: "push a {} circle" for c in COLOR_ADJECTIVES},
    **{s: "push a {} circle" for s in SIZE_ADJECTIVES},
    **{a: "push a circle {}" for a in ADVERBS},
}


def test_a_sense_is_chosen_for_every_content_word_wordnet_has():
    reader = wordnet_reader()
    assert set(GSCAN_SENSES) == set(CONTENT_WORDS) - set(CLAUSE_ADVERBS)
    for word, sense in GSCAN_SENSES.items():
        assert word in reader.synset(sense).lemma_names(), (word, sense)


def test_synonyms_map_to_gscan_words_and_the_left_out_kinds():
    assert TABLE.lookup("large").target == "big" and TABLE.lookup("little").target == "small"
    assert TABLE.lookup("huge").synset == "huge.s.01" and TABLE.lookup("huge").sense == "large.a.01"
    assert TABLE.lookup("carefully").target == "cautiously"
    assert TABLE.left_out["force"].startswith("ambiguous")  # push.v.01 and pull.v.01
    assert TABLE.left_out["king-size"] == "not a single word"
    assert TABLE.lookup("draw") is None and TABLE.lookup("deep") is None


def test_accepted_words_are_single_words_outside_the_vocabulary():
    for word in TABLE.accepted:
        assert re.fullmatch("[a-z]+", word) and word not in VOCABULARY and word not in DETERMINERS
        assert word not in TABLE.left_out


def test_every_exclusion_still_matches_something_wordnet_generates():
    """An exclusion that no longer removes anything (a WordNet or sense change) must go."""
    reasons = set(TABLE.left_out.values())
    for sense in EXCLUDED_SENSES:
        assert any(reason.startswith(f"{sense}: ") for reason in reasons), sense
    for word in EXCLUDED_WORDS:
        assert TABLE.left_out[word] == EXCLUDED_WORDS[word]


def test_every_synonym_resolves_to_the_trained_module_and_head_of_its_word():
    """With the shipped model: the synonym's graph is its word's graph, and the model has its module."""
    policy = Policy.from_checkpoint()
    trained = {spec.key for spec in policy.model.table.specs}
    for word, synonym in TABLE.accepted.items():
        template = TEMPLATE[synonym.target]
        graph, expected = policy.parse(template.format(word)), policy.parse(template.format(synonym.target))
        assert graph == expected, word
        node = next(n for n in graph.nodes if n.word == synonym.target)
        assert (node.module, node.head) == policy.lexicon.module_for(synonym.target) and node.module in trained


def test_every_synonym_parses_under_every_parser():
    for name in ("constituency", "dependency"):
        parser = get_parser(name)
        for word, synonym in TABLE.accepted.items():
            template = TEMPLATE[synonym.target]
            assert parser.parse(template.format(word)) == parser.parse(template.format(synonym.target)), (name, word)


def test_docs_list_exactly_the_generated_table():
    section = DOCS.read_text().split("<!-- synonyms:begin -->")[1].split("<!-- synonyms:end -->")[0]
    documented = {}
    for row in section.splitlines():
        cells = [c.strip() for c in row.strip().strip("|").split("|")]
        if len(cells) == 3 and cells[0] in GSCAN_SENSES:
            documented[cells[0]] = set() if cells[2] == "—" else set(cells[2].split(", "))
            assert cells[1].startswith(GSCAN_SENSES[cells[0]]), cells
    generated = {word: {s.word for s in TABLE.accepted.values() if s.target == word} for word in GSCAN_SENSES}
    assert documented == generated
    for sense in EXCLUDED_SENSES:
        assert sense in section, sense
    for word in EXCLUDED_WORDS:
        assert word in section, word


def test_without_wordnet_an_unknown_word_says_synonyms_are_unavailable(tmp_path, monkeypatch):
    monkeypatch.setenv("GSCAN_WORDNET_DIR", str(tmp_path))
    with pytest.raises(LexiconError):
        synonym_table()
    assert canonicalize("walk to a circle").canonical == "walk to a circle"  # gSCAN words need no WordNet
    with pytest.raises(CommandError, match=r"unknown word 'large' \(no WordNet synonyms: WordNet 3.0 data not found"):
        canonicalize("walk to a large circle")


def test_a_wordnet_without_a_chosen_sense_is_a_lexicon_error(monkeypatch):
    """Another WordNet version (GSCAN_WORDNET_DIR) may number senses differently."""
    monkeypatch.setattr(synonyms, "GSCAN_SENSES", {"big": "large.a.99"})
    with pytest.raises(LexiconError, match="has no synset large.a.99 .big's sense."):
        synonyms._table.__wrapped__(wordnet_root())
