import json
from pathlib import Path

import pytest

from gscan_ros.errors import LexiconError
from gscan_ros.language import CONTENT_WORDS, Concept, Lexicon
from gscan_ros.language.lexicon import DEFAULT_WORDNET_DIR, _open_wordnet


@pytest.fixture(scope="module")
def wordnet() -> Lexicon:
    return Lexicon.from_wordnet(CONTENT_WORDS)


def test_default_wordnet_lexicon_shares_only_big_and_small(wordnet):
    assert wordnet.concepts == (Concept(("big", "small"), ((0, 1),)),)
    assert wordnet.module_for("big") == ("big|small", 0)
    assert wordnet.module_for("small") == ("big|small", 1)
    assert wordnet.module_for("red") == ("red", 0)
    assert wordnet.num_heads("big|small") == 2 and wordnet.num_heads("red") == 1
    assert wordnet.antonym_heads("big|small") == [(0, 1)] and wordnet.antonym_heads("red") == []


def test_per_arity_module_keys_resolve_to_their_concept(wordnet):
    assert wordnet.num_heads("big|small_0") == 2 and wordnet.antonym_heads("big|small_0") == [(0, 1)]
    assert wordnet.num_heads("red_0") == 1 and wordnet.num_heads("NP_2") == 1


def test_verb_switch_adds_push_and_pull():
    lexicon = Lexicon.from_wordnet(CONTENT_WORDS, parts_of_speech=("a", "s", "v"))
    assert lexicon.module_for("pull") == ("pull|push", 0)
    assert lexicon.antonym_heads("pull|push") == [(0, 1)]


def test_every_part_of_speech_finds_no_other_links_among_gscan_words():
    lexicon = Lexicon.from_wordnet(CONTENT_WORDS, parts_of_speech="asrvn")
    assert [c.words for c in lexicon.concepts] == [("big", "small"), ("pull", "push")]


def test_adverbs_link_quickly_and_slowly():
    lexicon = Lexicon.from_wordnet(["quickly", "slowly", "cautiously"], parts_of_speech="r")
    assert [c.words for c in lexicon.concepts] == [("quickly", "slowly")]


def test_synonyms_join_a_concept_without_an_antonym_pair():
    lexicon = Lexicon.from_wordnet(["big", "large", "small"])
    assert lexicon.concepts[0].words == ("big", "large", "small")
    assert lexicon.antonym_heads("big|large|small") == [(0, 2), (1, 2)]


def test_none_shares_nothing():
    lexicon = Lexicon.none()
    assert lexicon.module_for("small") == ("small", 0) and lexicon.num_heads("small") == 1


def test_dict_round_trip_through_json(wordnet):
    assert Lexicon.from_dict(json.loads(json.dumps(wordnet.to_dict()))) == wordnet


@pytest.mark.parametrize(
    "d, message",
    [
        ({"format": 2}, "not a lexicon of format 1"),
        ({"format": 1, "parts_of_speech": []}, "malformed lexicon"),
        ({"format": 1, "parts_of_speech": [], "concepts": [{"words": ["small", "big"], "antonyms": []}]}, "sorted"),
        ({"format": 1, "parts_of_speech": [], "concepts": [{"words": ["a", "b"], "antonyms": [[0, 2]]}]},
         "out of range"),
        ({"format": 1, "parts_of_speech": [], "concepts": [{"words": ["a", "b"], "antonyms": []},
                                                           {"words": ["b", "c"], "antonyms": []}]}, "two concepts"),
    ],
)
def test_bad_dicts_raise_lexicon_error(d, message):
    with pytest.raises(LexiconError, match=message):
        Lexicon.from_dict(d)


def test_missing_wordnet_says_how_to_install_it(tmp_path: Path):
    with pytest.raises(LexiconError, match=r"missing index.noun.*apt-get install -y wordnet-base"):
        Lexicon.from_wordnet(["big"], wordnet_dir=tmp_path)


def test_wordnet_dir_from_environment(monkeypatch, tmp_path: Path):
    monkeypatch.setenv("GSCAN_WORDNET_DIR", str(tmp_path))
    with pytest.raises(LexiconError, match=str(tmp_path)):
        Lexicon.from_wordnet(["big"])


def test_unknown_part_of_speech():
    with pytest.raises(LexiconError, match="unknown WordNet parts of speech"):
        Lexicon.from_wordnet(["big"], parts_of_speech=("x",))


def test_symlinked_wordnet_dir_is_resolved(tmp_path: Path):
    link = tmp_path / "wordnet"
    link.symlink_to(Path(DEFAULT_WORDNET_DIR).resolve())
    assert Lexicon.from_wordnet(["big", "small"], wordnet_dir=link).module_for("small") == ("big|small", 1)


def test_reader_serves_the_lexnames_debian_omits():
    reader = _open_wordnet(str(Path(DEFAULT_WORDNET_DIR).resolve()))
    assert reader.synset("circle.n.01").lexname() == "noun.shape"
    assert reader.synset("walk.v.01").lexname() == "verb.motion"
    assert reader.synset("small.a.01").lexname() == "adj.all"
