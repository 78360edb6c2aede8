"""dataset.txt: streaming reader, writer, fixture in the released format, error messages."""
import json
from pathlib import Path

import pytest

from gscan_ros.data import dataset as ds
from gscan_ros.data.dataset import (
    DatasetHeader,
    Example,
    iter_examples,
    iter_raw_examples,
    read_header,
    write_dataset,
)
from gscan_ros.data.io import iter_episodes
from gscan_ros.errors import DatasetFormatError
from gscan_ros.world import demonstrate
from gscan_ros.world.types import Action, Position

FIXTURE = Path(__file__).parent / "fixtures" / "released_format.txt"


def _released() -> dict:
    return json.loads(FIXTURE.read_text())


def test_fixture_parses_in_file_order():
    found = [(split, index, e.command) for split, index, e in iter_examples(FIXTURE)]
    assert found == [
        ("train", 0, "walk to a circle"),
        ("train", 1, "push a green cylinder hesitantly"),
        ("adverb_1", 0, "push a green small square cautiously"),
    ]


def test_released_example_fields():
    (_, _, example), = iter_examples(FIXTURE, splits=["adverb_1"])
    s = example.situation
    assert s.agent_position == Position(2, 0) and s.agent_direction == 0
    assert len(s.placed_objects) == 12
    assert (s.target_object.color, s.target_object.shape, s.target_object.size) == ("green", "square", 1)
    assert example.referred_target == "small green square" and example.manner == "cautiously"
    # Blocked push: no push action (docs/world.md, "Physics decisions"), and the planner agrees.
    assert Action.PUSH not in example.target_commands
    assert demonstrate(s, example.command) == list(example.target_commands)


def test_header_of_released_layout_is_read_after_the_examples():
    header = read_header(FIXTURE)
    assert header.grid_size == 6 and header.type_grammar == "adverb"
    assert header.vocabulary["nouns"] == {"square": "square", "cylinder": "cylinder", "circle": "circle"}


def test_round_trip_every_example_through_writer_and_reader(tmp_path):
    raw = _released()
    for split, index, example in iter_examples(FIXTURE):
        assert example.to_json() == raw["examples"][split][index]
    by_split = {}
    for split, _, example in iter_examples(FIXTURE):
        by_split.setdefault(split, []).append(example)
    header = read_header(FIXTURE)
    path = write_dataset(tmp_path, header, by_split)
    assert path == tmp_path / "dataset.txt"
    assert json.loads(path.read_text())["examples"]["adverb_1"] == raw["examples"]["adverb_1"]
    assert [(s, i, e) for s, i, e in iter_examples(tmp_path)] == [(s, i, e) for s, i, e in iter_examples(FIXTURE)]
    assert read_header(path) == header


@pytest.mark.parametrize("chunk", [1, 2, 3, 7, 64, 1000])
def test_tiny_buffers_give_the_same_result(monkeypatch, chunk):
    """Every value boundary falls across a buffer refill for some chunk size."""
    monkeypatch.setattr(ds, "_CHUNK_CHARS", chunk)
    raw = _released()
    got = [(s, i, e) for s, i, e in iter_raw_examples(FIXTURE)]
    assert got == [(s, i, e) for s, ex in raw["examples"].items() for i, e in enumerate(ex)]
    assert read_header(FIXTURE).percentage_train == raw["percentage_train"]


def test_split_filter_and_missing_split():
    assert [s for s, _, _ in iter_examples(FIXTURE, splits=["train"])] == ["train", "train"]
    with pytest.raises(DatasetFormatError, match="no examples in split"):
        list(iter_examples(FIXTURE, splits=["visual_hard"]))


def test_a_split_our_header_does_not_declare_is_refused_before_any_example(tiny_dataset, capsys):
    """Files this project writes declare their split sizes first: a misspelt split is refused
    at once, also where --limit would stop the stream before its end."""
    from gscan_ros.cli import main

    stream = iter_examples(tiny_dataset, splits=["train", "visaul"])
    with pytest.raises(DatasetFormatError, match=r"no examples in split\(s\) visaul of .* \(it has: train, dev"):
        next(stream)
    assert main(["verify", str(tiny_dataset), "--splits", "train,visaul", "--limit", "3", "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no examples in split(s) visaul" in err[0]


def test_a_header_must_declare_the_split_sizes_it_is_written_with(tmp_path):
    header = ds.DatasetHeader(extra={"gscan_ros": {"split_sizes": {"train": 2}}})
    example = next(iter_examples(FIXTURE, splits=["train"]))[2]
    ds.write_dataset(tmp_path / "ok.txt", header, {"train": [example, example]})
    with pytest.raises(Exception, match=r"declares split sizes \{'train': 2\}, the examples are \{'train': 1\}"):
        ds.write_dataset(tmp_path / "bad.txt", header, {"train": [example]})
    assert not (tmp_path / "bad.txt").exists()


def test_episode_conversion_and_io_dispatch():
    episodes = list(iter_episodes(FIXTURE))
    assert [e.split for e in episodes] == ["train", "train", "adverb_1"]
    assert episodes[1].example_id == 1
    assert episodes[2].actions[-1] is Action.WALK
    assert episodes[2].states().shape == (12, 6, 6, 16)


def _corrupt(tmp_path, edit) -> Path:
    raw = _released()
    edit(raw["examples"]["train"][1])
    path = tmp_path / "dataset.txt"
    path.write_text(json.dumps(raw, indent=4))
    return path


@pytest.mark.parametrize("edit, message", [
    (lambda e: e["situation"]["agent_position"].__setitem__("row", "x"),
     "example 1 of split 'train': field 'situation.agent_position.row': expected an integer string, got 'x'"),
    (lambda e: e.__setitem__("target_commands", "walk,jump"),
     "example 1 of split 'train': field 'target_commands': unknown action 'jump'"),
    (lambda e: e.pop("situation"),
     "example 1 of split 'train': field 'situation': missing"),
    (lambda e: e.__setitem__("command", 7),
     "example 1 of split 'train': field 'command': expected a string, got int"),
    (lambda e: e.__setitem__("command", "walk to a big square while spinning"),  # spaces, not commas
     "example 1 of split 'train': field 'command': expected comma-joined tokens, got 'walk to a big square"),
    (lambda e: e["situation"]["placed_objects"]["0"]["object"].__setitem__("color", "purple"),
     "example 1 of split 'train': field 'situation.placed_objects.0.object.color': unknown color 'purple'"),
])
def test_malformed_example_names_example_and_field(tmp_path, edit, message):
    path = _corrupt(tmp_path, edit)
    with pytest.raises(DatasetFormatError) as info:
        list(iter_examples(path))
    assert str(info.value).startswith(f"{path}: {message}")  # the file too: a run reads several
    assert "\n" not in str(info.value)


def test_truncated_file(tmp_path):
    text = FIXTURE.read_text()
    cut = text.index('"push,a,green,cylinder')  # inside train example 1
    path = tmp_path / "dataset.txt"
    path.write_text(text[:cut + 200])
    with pytest.raises(DatasetFormatError,
                       match=r"dataset.txt: example 1 of split 'train': invalid JSON at character \d+"):
        list(iter_examples(path))


@pytest.mark.parametrize("content, message", [
    ("", "expected '{'"),
    ("[1, 2]", "expected '{'"),
    ('{"examples": {"train": [{}]}}', "example 0 of split 'train': field 'command': missing"),
    ('{"examples": {"train" [1]}}', "expected ':'"),
    ('{"grid_size": 6} {}', "data after the top-level object"),
])
def test_malformed_files(tmp_path, content, message):
    path = tmp_path / "dataset.txt"
    path.write_text(content)
    with pytest.raises(DatasetFormatError, match=message):
        list(iter_examples(path))


def test_missing_file_and_bad_header(tmp_path):
    with pytest.raises(DatasetFormatError, match="no dataset file"):
        list(iter_examples(tmp_path / "nope.txt"))
    path = tmp_path / "dataset.txt"
    path.write_text('{"grid_size": "six", "type_grammar": "adverb", "examples": {}}')
    with pytest.raises(DatasetFormatError, match="header: key 'grid_size'"):
        read_header(path)


def test_default_header_round_trips():
    header = DatasetHeader(extra={"gscan_ros": {"seed": 3}})
    assert DatasetHeader.from_json(json.loads(json.dumps(header.to_json()))) == header


def test_example_from_json_rejects_eos():
    raw = _released()["examples"]["train"][0]
    raw["target_commands"] = "walk,<eos>"
    with pytest.raises(DatasetFormatError, match="'<eos>' is not a gSCAN action"):
        Example.from_json(raw)
