"""GECA augmentation (`gscan-ros augment --method geca`): the substitution itself, the hold-out
filter, determinism, grounded examples, untouched splits and the CLI's refusals."""
import re

import pytest

from gscan_ros.cli import main
from gscan_ros.cli.verify import check_episode
from gscan_ros.data.dataset import Example, iter_raw_examples, read_header
from gscan_ros.data.geca import HOLD_OUT_SPLITS, augment
from gscan_ros.data.generate import GenerationConfig, generate_dataset
from gscan_ros.data.io import iter_episodes
from gscan_ros.errors import GscanError
from gscan_ros.world import demonstrate
from gscan_ros.world.command import split_command
from gscan_ros.world.types import Heading, Position, Situation, WorldObject


def _example(command: str, shape: str, color: str, agent: tuple[int, int], target: tuple[int, int]) -> Example:
    obj = WorldObject(shape, color, 2, Position(*target))
    situation = Situation(Position(*agent), Heading.EAST, (obj,), target_object=obj)
    return Example(tokens=split_command(command), situation=situation,
                   target_commands=tuple(demonstrate(situation, command)))


# "red" and "yellow" fill the template "walk to a _ circle" with the same route, so they
# are substitutable; "walk to a red square" (another route) then yields "walk to a yellow
# square", which split B (yellow squares called yellow) holds out.
TRAIN = [
    _example("walk to a red circle", "circle", "red", (0, 0), (0, 2)),
    _example("walk to a yellow circle", "circle", "yellow", (0, 0), (0, 2)),
    _example("walk to a red square", "square", "red", (3, 1), (1, 1)),
]


def test_substitutable_fragments_make_a_grounded_new_example():
    report = augment(TRAIN, examples=5, seed=0)
    assert [e.command for e in report.added] == ["walk to a yellow square"]
    new = report.added[0]
    assert new.target_commands == TRAIN[2].target_commands  # the route of the template's example
    target = new.situation.target_object
    assert (target.shape, target.color, target.position) == ("square", "yellow", Position(1, 1))
    assert check_episode(new.to_episode()) is None


def test_a_kind_the_dataset_holds_out_is_dropped_unless_kept():
    dropped = augment(TRAIN, examples=5, seed=0, held_out=["visual_easier"])
    assert dropped.added == [] and dropped.held_out_kinds == {"visual_easier": 1}
    kept = augment(TRAIN, examples=5, seed=0, held_out=["visual_easier"], keep_held_out=True)
    assert [e.command for e in kept.added] == ["walk to a yellow square"] and kept.keep_held_out == ["visual_easier"]


SOUTH_WEST = [*TRAIN[:2], _example("walk to a red square", "square", "red", (0, 3), (2, 1))]


@pytest.mark.parametrize(("keep", "added"), [
    (True, 1), (["visual_easier"], 0), (["situational_1"], 0), (["visual_easier", "situational_1"], 1)])
def test_named_kinds_are_kept_when_every_split_claiming_the_example_is_named(keep, added):
    """The yellow square south-west of the agent is claimed by B and D: both must be kept."""
    report = augment(SOUTH_WEST, examples=5, seed=0, held_out=["visual_easier", "situational_1"], keep_held_out=keep)
    assert report.held_out_kinds == {"visual_easier": 1, "situational_1": 1} and len(report.added) == added


def test_keeping_a_split_the_dataset_does_not_hold_out_is_refused():
    with pytest.raises(GscanError, match=r"--keep-held-out visual: not a hold-out split of the dataset "
                                         r"\(those are: visual_easier\)"):
        augment(TRAIN, examples=5, seed=0, held_out=["visual_easier"], keep_held_out=["visual"])


def test_a_route_across_a_large_grid_is_placed_where_it_fits():
    """Routes are measured on no grid at all, so one of 10 cells on a 12x12 grid (more than
    half the largest grid) is kept, not dropped as 'no layout for its route'."""
    from gscan_ros.data.geca import _route
    from gscan_ros.world.types import Action

    assert _route((Action.TURN_LEFT, *(Action.WALK,) * 10)) == (-10, 0)
    walk, right, push = Action.WALK, Action.TURN_RIGHT, Action.PUSH
    assert _route((*(walk,) * 9, right, walk, walk, push, walk)) == (2, 9)

    def far(command, shape, color, agent, target):
        obj = WorldObject(shape, color, 2, Position(*target))
        situation = Situation(Position(*agent), Heading.EAST, (obj,), target_object=obj, grid_size=12)
        return Example(tokens=split_command(command), situation=situation,
                       target_commands=tuple(demonstrate(situation, command)))

    train = [far("walk to a red circle", "circle", "red", (0, 0), (0, 10)),
             far("walk to a yellow circle", "circle", "yellow", (0, 0), (0, 10)),
             far("walk to a red square", "square", "red", (11, 1), (1, 1))]
    report = augment(train, examples=5, seed=0)
    assert [e.command for e in report.added] == ["walk to a yellow square"]
    assert report.added[0].target_commands == train[2].target_commands and report.dropped == {}


def test_an_empty_split_of_the_input_is_copied_and_holds_its_kinds_out(dataset, tmp_path):
    """A small dataset may leave hold-out splits empty: they stay in the output, in the
    input's order, and still claim their kinds (none of them is added to train)."""
    import json

    from gscan_ros.data.dataset import write_dataset_json

    emptied = ("visual", "dev")
    lines = {}
    for split, _, example in iter_raw_examples(dataset):
        lines.setdefault(split, [])
        if split not in emptied:
            lines[split].append(json.dumps(example))
    header = read_header(dataset)
    header.extra["gscan_ros"]["split_sizes"] = {split: len(texts) for split, texts in lines.items()}
    (tmp_path / "small").mkdir()
    write_dataset_json(tmp_path / "small" / "dataset.txt", header, lines)
    before: dict[str, int] = {}
    list(iter_raw_examples(tmp_path / "small", sizes=before))
    empty = [s for s, n in before.items() if n == 0]
    assert set(empty) == set(emptied)
    path = _augmented(tmp_path / "small", tmp_path / "out", 0)
    after: dict[str, int] = {}
    list(iter_raw_examples(path, sizes=after))
    assert list(after) == list(before) and all(after[s] == 0 for s in empty)
    record = read_header(path).extra["gscan_ros"]["augmentation"]
    assert set(record["held_out"]) == set(before) & HOLD_OUT_SPLITS and set(empty) & HOLD_OUT_SPLITS


def test_a_dataset_too_small_for_any_template_is_refused_and_nothing_written(tmp_path, capsys):
    """A copy without a single added example would pass for an augmented dataset."""
    generate_dataset(tmp_path / "tiny", GenerationConfig(seed=0, max_examples=2), workers=1)
    argv = ["augment", "--data", str(tmp_path / "tiny"), "--out", str(tmp_path / "out"), "--method", "geca",
            "--examples", "5", "--quiet"]
    assert main(argv) == 1
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith("gscan-ros augment: error:") and "no GECA example could be made" in line
    assert not (tmp_path / "out" / "dataset.txt").exists()


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("base")
    generate_dataset(out, GenerationConfig(seed=3, max_examples=2000), workers=1)
    return out


def _augmented(dataset, out, seed: int, *extra: str):
    argv = ["augment", "--data", str(dataset), "--out", str(out), "--method", "geca", "--examples", "40",
            "--seed", str(seed), "--quiet", *extra]
    assert main(argv) == 0
    return out / "dataset.txt"


def _splits(path) -> dict[str, list[dict]]:
    out: dict[str, list[dict]] = {}
    for split, _, raw in iter_raw_examples(path):
        out.setdefault(split, []).append(raw)
    return out


def test_output_is_the_input_plus_grounded_geca_examples(dataset, tmp_path):
    path = _augmented(dataset, tmp_path / "a", 0)
    before, after = _splits(dataset), _splits(path)
    assert list(after) == list(before)
    assert all(after[s] == before[s] for s in before if s != "train")
    base = len(before["train"])
    assert after["train"][:base] == before["train"] and len(after["train"]) == base + 40
    record = read_header(path).extra["gscan_ros"]["augmentation"]
    assert record["added"] == 40 and record["train_indices"] == [base, base + 40]
    for index, raw in enumerate(after["train"][base:], start=base):
        example = Example.from_json(raw)
        assert check_episode(example.to_episode("train", index)) is None, example.command


def test_same_seed_same_bytes_other_seed_other_examples(dataset, tmp_path):
    first = _augmented(dataset, tmp_path / "a", 0).read_bytes()
    assert _augmented(dataset, tmp_path / "b", 0).read_bytes() == first
    other = _augmented(dataset, tmp_path / "c", 1).read_bytes()
    assert other != first


def test_an_existing_output_needs_overwrite(dataset, tmp_path, capsys):
    path = _augmented(dataset, tmp_path / "a", 0)
    mine = path.read_bytes()
    argv = ["augment", "--data", str(dataset), "--out", str(tmp_path / "a"), "--method", "geca", "--quiet"]
    assert main(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--overwrite" in err[0]
    assert path.read_bytes() == mine
    assert _augmented(dataset, tmp_path / "a", 1, "--overwrite").read_bytes() != mine


@pytest.mark.parametrize("content, names", [
    ("{}", "no train examples"),
    ('{"examples": {"train": [{"command": "walk,to,a,circle"}]}}', "example 0 of split 'train'"),
])
def test_bad_input_is_one_line_exit_1_and_writes_nothing(tmp_path, capsys, content, names):
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "dataset.txt").write_text(content)
    argv = ["augment", "--data", str(tmp_path / "in"), "--out", str(tmp_path / "out"), "--method", "geca", "--quiet"]
    assert main(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("gscan-ros augment: error:") and names in err[0], err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(("keep", "error"), [
    (["bogus"], "--keep-held-out bogus: not a hold-out split of any dataset (those are: adverb_1, "),
    (["visual", "target_lengths"],
     "--keep-held-out target_lengths: not a hold-out split of the dataset (those are: adverb_1, "),
])
def test_keeping_an_unknown_split_is_one_line_exit_1(dataset, tmp_path, capsys, keep, error):
    """A name no dataset holds out is refused before the input is read; one the input lacks
    (compositional data has no target_lengths) after, with the splits it has."""
    argv = ["augment", "--data", str(dataset), "--out", str(tmp_path / "out"), "--method", "geca", "--quiet",
            "--keep-held-out", *keep]
    assert main(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and error in err[0], err
    assert not (tmp_path / "out" / "dataset.txt").exists()


def test_named_kept_splits_are_recorded_and_reported(dataset, tmp_path, capsys):
    path = _augmented(dataset, tmp_path / "a", 0, "--keep-held-out", "visual", "visual_easier")
    record = read_header(path).extra["gscan_ros"]["augmentation"]
    assert record["keep_held_out"] == ["visual", "visual_easier"] and "situational_1" in record["held_out"]
    kinds = dict(re.findall(r"proposals of the kind of (\w+): \d+ \((\w+)\)", capsys.readouterr().out))
    assert "situational_1" in kinds and all((state == "kept") == (split in ("visual", "visual_easier"))
                                            for split, state in kinds.items()), kinds


def test_the_output_folder_may_not_be_the_input_folder(dataset, capsys):
    assert main(["augment", "--data", str(dataset), "--out", str(dataset), "--method", "geca", "--quiet"]) == 1
    assert "input" in capsys.readouterr().err


def test_bag_data_is_read_too(tmp_path):
    bags = tmp_path / "bags"
    generate_dataset(bags, GenerationConfig(seed=3, max_examples=600), workers=1, fmt="mcap")
    path = _augmented(bags, tmp_path / "a", 0)
    before = sum(1 for _ in iter_episodes(bags, ["train"]))
    assert read_header(path).extra["gscan_ros"]["augmentation"]["train_indices"] == [before, before + 40]
    assert all(check_episode(ep) is None for ep in iter_episodes(path, ["train"]))
