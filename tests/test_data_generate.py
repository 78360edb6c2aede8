"""Dataset generation end to end: sampling rules, splits, determinism, CLIs."""
import json
from collections import Counter, defaultdict
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gscan_ros.cli import main
from gscan_ros.data.commands import parse_command
from gscan_ros.data.dataset import iter_examples, iter_raw_examples, read_header
from gscan_ros.data.generate import GenerationConfig, generate_dataset
from gscan_ros.data.sampling import (
    ALL_OBJECTS,
    DIAGONAL_DIRECTIONS,
    STRAIGHT_DIRECTIONS,
    ObjectSpec,
    possible_targets,
    sample_placements,
)
from gscan_ros.data.splits import held_out_splits
from gscan_ros.errors import GscanError
from gscan_ros.world import resolve_target

N = 2500
# The smallest world (4x4, one layout per direction and distance): a full set in seconds.
SMALL_WORLD = {"grid_size": 4, "num_resampling": 1}
# Its length split with a cut-off that 4x4 targets exceed, so every split has examples.
SMALL_LENGTH = {"split_kind": "length", "cut_off_target_length": 6, **SMALL_WORLD}


@pytest.fixture(scope="module")
def compositional(tmp_path_factory):
    out = tmp_path_factory.mktemp("compositional")
    report = generate_dataset(out, GenerationConfig(seed=7, max_examples=N, k_shot=3), workers=1)
    examples = list(iter_examples(report.path))
    return report, examples


def test_placements_cover_directions_and_distances():
    layouts = sample_placements(np.random.default_rng(0), 6, 5)
    per_direction = Counter(p.direction for p in layouts)
    assert all(per_direction[d] == 17 for d in STRAIGHT_DIRECTIONS)
    assert all(per_direction[d] == 41 for d in DIAGONAL_DIRECTIONS)
    for p in layouts:
        dr, dc = p.target.row - p.agent.row, p.target.col - p.agent.col
        assert abs(dr) + abs(dc) == p.distance
        assert 0 <= p.agent.row < 6 and 0 <= p.target.col < 6
        assert ("n" in p.direction) == (dr < 0) and ("e" in p.direction) == (dc > 0)
        assert (1 <= p.distance <= 5) if len(p.direction) == 1 else (2 <= p.distance <= 10)
        assert len(p.direction) == 1 or (dr != 0 and dc != 0)


def test_possible_targets():
    assert {t.size for t in possible_targets(parse_command("walk to a small circle"))} == {1, 2, 3}
    assert {t.size for t in possible_targets(parse_command("walk to a big circle"))} == {2, 3, 4}
    assert len(possible_targets(parse_command("walk to a circle"))) == 16
    assert len(possible_targets(parse_command("walk to a red big circle"))) == 3
    assert len(ALL_OBJECTS) == 48


def test_candidate_and_split_counts_match_released(compositional):
    report, _ = compositional
    assert report.candidates == 835_200 and report.dropped_multiple_rules == 97_731


def test_situations_follow_the_generator_rules(compositional):
    _, examples = compositional
    expected_count = {(False, False): 2, (True, False): 6, (False, True): 12, (True, True): 12}
    for _, _, e in examples:
        command, s = parse_command(e.tokens), e.situation
        assert len(s.placed_objects) == expected_count[bool(command.color), bool(command.size)]
        assert s.agent_direction == 0
        assert s.agent_position not in {o.position for o in s.placed_objects}
        assert resolve_target(s, command.frame) == s.target_object  # unique referent
        assert e.derivation == command.derivation and e.referred_target == command.referred_target
        if command.size:  # an obligatory comparison object of the target's color and shape
            assert any(o != s.target_object and o.shape == command.noun and o.color == s.target_object.color
                       for o in s.placed_objects)


def test_split_membership_follows_rules(compositional):
    report, examples = compositional
    k_shot = set(read_header(report.path).extra["gscan_ros"]["k_shot_train_indices"])
    assert len(k_shot) == 3
    for split, index, e in examples:
        t = e.situation.target_object
        rules = held_out_splits(parse_command(e.tokens), ObjectSpec(t.size, t.color, t.shape),
                                e.situation.direction_to_target)
        if split == "train" and index in k_shot:
            assert rules == ("adverb_1",)
        elif split in ("train", "dev", "test"):
            assert rules == ()
        else:
            assert rules == (split,)
    sizes = report.split_sizes
    assert sizes["test"] > 0 and sizes["dev"] > 0 and all(sizes[k] > 0 for k in ("visual", "adverb_2"))


def test_no_test_example_equivalent_to_train(compositional):
    _, examples = compositional

    def key(e):
        return e.command, e.target_commands, e.situation.target_object.position

    train = {key(e) for split, _, e in examples if split == "train"}
    assert not any(key(e) in train for split, _, e in examples if split == "test")


@pytest.mark.slow
def test_same_seed_same_bytes_any_worker_count(compositional, tmp_path):
    report, _ = compositional
    again = generate_dataset(tmp_path, GenerationConfig(seed=7, max_examples=N, k_shot=3), workers=2)
    assert again.path.read_bytes() == report.path.read_bytes()
    other = generate_dataset(tmp_path / "other", GenerationConfig(seed=8, max_examples=N, k_shot=3))
    assert other.path.read_bytes() != report.path.read_bytes()


@pytest.mark.slow
def test_length_split(tmp_path):
    report = generate_dataset(tmp_path, GenerationConfig(seed=1, split_kind="length", max_examples=1500))
    header = read_header(report.path)
    assert header.extra["gscan_ros"]["cut_off_target_length"] == 15
    seen = Counter()
    for split, _, e in iter_examples(report.path):
        seen[split] += 1
        assert not parse_command(e.tokens).adverb
        assert ("stay" not in [a.token for a in e.target_commands])
        assert (len(e.target_commands) > 15) == (split == "target_lengths")
    assert set(seen) == {"train", "dev", "test", "target_lengths"}


def test_cli_generate_then_verify_reports_no_mismatch(tmp_path, capsys):
    assert main(["generate", "--out", str(tmp_path), "--examples", "300", "--seed", "2",
                 "--workers", "1", "--quiet"]) == 0
    assert main(["verify", str(tmp_path), "--quiet"]) == 0
    assert "0 mismatch(es)" in capsys.readouterr().out


def test_cli_verify_reports_a_wrong_target(tmp_path, capsys):
    report = generate_dataset(tmp_path, GenerationConfig(seed=4, max_examples=50))
    data = json.loads((tmp_path / "dataset.txt").read_text())
    example = data["examples"]["train"][0]
    example["target_commands"] = "stay," + example["target_commands"]
    (tmp_path / "dataset.txt").write_text(json.dumps(data))
    assert main(["verify", str(tmp_path), "--quiet"]) == 1
    out = capsys.readouterr().out
    assert "MISMATCH example 0 of split 'train'" in out and "differs at step 0" in out
    assert f"verified {sum(report.split_sizes.values())} examples: 1 mismatch(es)" in out


def test_cli_errors_are_one_line(tmp_path, capsys):
    (tmp_path / "dataset.txt").write_text('{"examples": {"train": [{"command": "walk,to,a,circle"}]}}')
    assert main(["verify", str(tmp_path), "--quiet"]) == 1
    err = capsys.readouterr().err.strip()
    assert err == (f"gscan-ros verify: error: {tmp_path / 'dataset.txt'}: example 0 of split 'train': "
                   "field 'situation': missing")
    with pytest.raises(SystemExit) as exit_info:
        main(["generate", "--out", str(tmp_path), "--examples", "0"])
    assert exit_info.value.code == 1
    assert "argument --examples: must be an integer >= 1" in capsys.readouterr().err


def test_cli_render_png_and_gif(compositional, tmp_path):
    report, _ = compositional
    from PIL import Image

    assert main(["render", str(report.path), "--split", "adverb_1", "--index", "1",
                 "--out", str(tmp_path / "a.gif")]) == 0
    assert main(["render", str(report.path), "--split", "train", "--out", str(tmp_path / "a.png")]) == 0
    assert Image.open(tmp_path / "a.gif").n_frames > 1
    assert Image.open(tmp_path / "a.png").size[0] > 0
    assert main(["render", str(report.path), "--split", "train", "--index", "100000",
                 "--out", str(tmp_path / "b.png")]) == 1


@pytest.mark.parametrize("workers", [1, 2])
def test_mcap_format_holds_the_same_episodes(tmp_path, workers):
    """Every split's bag holds the text format's episodes, in order, whether the bags are
    written one after another or in parallel worker processes."""
    config = GenerationConfig(seed=5, max_examples=60, percentage_dev=0.2)
    txt = generate_dataset(tmp_path / "txt", config)
    report = generate_dataset(tmp_path / "bags", config, fmt="mcap", workers=workers)
    from gscan_ros.data.io import iter_episodes

    episodes = list(iter_episodes(txt.path))
    splits = [s for s, n in report.split_sizes.items() if n]
    assert len(splits) >= 3
    for split in splits:
        expected = [e for e in episodes if e.split == split]
        got = list(iter_episodes(tmp_path / "bags" / split))
        assert [(e.command, e.situation, e.actions) for e in got] == \
            [(e.command, e.situation, e.actions) for e in expected], split


def test_mcap_bags_written_in_parallel_are_byte_identical(tmp_path):
    config = GenerationConfig(seed=5, max_examples=60, percentage_dev=0.2)
    report = generate_dataset(tmp_path / "one", config, fmt="mcap", workers=1)
    generate_dataset(tmp_path / "two", config, fmt="mcap", workers=2)
    files = sorted(p.relative_to(tmp_path / "one") for p in (tmp_path / "one").rglob("*") if p.is_file())
    assert len([f for f in files if f.suffix == ".mcap"]) == sum(1 for n in report.split_sizes.values() if n)
    assert files == sorted(p.relative_to(tmp_path / "two") for p in (tmp_path / "two").rglob("*") if p.is_file())
    for f in files:
        assert (tmp_path / "one" / f).read_bytes() == (tmp_path / "two" / f).read_bytes(), f


def _generate(out, *extra) -> int:
    return main(["generate", "--out", str(out), "--examples", "60", "--seed", "5", "--workers", "1", "--quiet",
                 *extra])


def _files(root) -> dict:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_generate_refuses_an_existing_dataset_without_overwrite(tmp_path, capsys):
    (tmp_path / "dataset.txt").write_text('{"grid_size": 6}')
    (tmp_path / "train").mkdir()
    (tmp_path / "train" / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    before = _files(tmp_path)
    for fmt in ("txt", "mcap"):
        assert _generate(tmp_path, "--format", fmt) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "already holds a dataset" in err[0] and "--overwrite" in err[0]
        assert _files(tmp_path) == before


@pytest.mark.parametrize("fmt", ["txt", "mcap"])
def test_a_swap_that_fails_midway_puts_the_old_dataset_back(tmp_path, monkeypatch, fmt):
    """`--overwrite` swaps the new dataset in by renames; when the last one fails (the disk),
    the old dataset is back in place, whole."""
    import errno
    from pathlib import Path

    out = tmp_path / "data"
    generate_dataset(out, GenerationConfig(seed=1, max_examples=10), fmt=fmt, workers=1)
    before = _files(out)
    rename = Path.rename

    def failing(self, target):
        if Path(target).parent == out and self.parent.name == "new" and \
                Path(target).name in ("dataset.txt", "manifest.json"):
            raise OSError(errno.EIO, "I/O error", str(target))
        return rename(self, target)

    monkeypatch.setattr(Path, "rename", failing)
    with pytest.raises(OSError):
        generate_dataset(out, GenerationConfig(seed=2, max_examples=10), fmt=fmt, workers=1, overwrite=True)
    monkeypatch.undo()
    assert _files(out) == before


def test_generate_into_a_bag_is_refused_and_overwrite_replaces_the_bag(tmp_path, capsys):
    """A folder that is a bag reads as that bag, whatever else it holds: writing a dataset
    beside the bag's files would give a dataset no command reads."""
    from gscan_ros.data.bag import write_bag
    from gscan_ros.data.io import iter_episodes

    from bag_support import make_episodes

    write_bag(tmp_path / "rec", make_episodes(3))
    (tmp_path / "rec" / "notes.txt").write_text("mine")
    before = _files(tmp_path / "rec")
    for fmt in ("txt", "mcap"):
        assert _generate(tmp_path / "rec", "--format", fmt) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "already holds a dataset (a rosbag2 bag)" in err[0] and "--overwrite" in err[0]
        assert _files(tmp_path / "rec") == before
    assert _generate(tmp_path / "rec", "--overwrite") == 0
    assert sorted(p.name for p in (tmp_path / "rec").iterdir()) == ["dataset.txt", "notes.txt"]
    written = sum(1 for _ in iter_raw_examples(tmp_path / "rec" / "dataset.txt"))
    assert written and len(list(iter_episodes(tmp_path / "rec"))) == written  # the dataset, not the bag


def test_generate_overwrite_mcap_leaves_no_stale_split(tmp_path):
    """A split that gets no examples this time must not keep the old run's bag."""
    from gscan_ros.data.io import split_bags

    assert _generate(tmp_path, "--format", "txt") == 0
    assert _generate(tmp_path, "--format", "mcap", "--percentage-dev", "0.2", "--overwrite") == 0
    assert "dev" in split_bags(tmp_path) and not (tmp_path / "dataset.txt").exists()
    (tmp_path / "notes.txt").write_text("mine")
    (tmp_path / "dev" / ".cache").mkdir()
    (tmp_path / "dev" / ".cache" / "episodes.npz").write_bytes(b"cache")
    assert _generate(tmp_path, "--format", "mcap", "--percentage-dev", "0", "--overwrite") == 0
    assert "dev" not in split_bags(tmp_path) and not (tmp_path / "dev").exists()
    assert "train" in split_bags(tmp_path) and (tmp_path / "notes.txt").read_text() == "mine"


def test_generate_overwrite_keeps_foreign_files_in_a_split_bag(tmp_path, capsys):
    assert _generate(tmp_path, "--format", "mcap") == 0
    (tmp_path / "train" / "thesis.tex").write_text("years of work")
    before = _files(tmp_path)
    assert _generate(tmp_path, "--format", "mcap", "--overwrite") == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "thesis.tex" in err[0]
    assert _files(tmp_path) == before


@pytest.mark.parametrize("fmt, name, text", [
    ("txt", "manifest.json", "my notes\n"),  # the txt format never writes a manifest
    ("txt", "manifest.json", '{"splits": {"train": 3}}'),  # JSON, not ours
    ("mcap", "dataset.txt", "notes\n"),
    ("txt", "dataset.txt", '{"examples": {}}'),
])
def test_generate_overwrite_refuses_a_users_file_of_a_datasets_name(tmp_path, capsys, fmt, name, text):
    """--overwrite replaces only an earlier dataset's files: a file that merely bears the
    name of one is the user's, refused in one line naming it."""
    (tmp_path / name).write_text(text)
    before = _files(tmp_path)
    for overwrite in ([], ["--overwrite"]):
        assert _generate(tmp_path, "--format", fmt, *overwrite) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"{tmp_path / name} is not a" in err[0] and "Traceback" not in err[0]
        assert _files(tmp_path) == before


def test_generate_overwrite_replaces_an_earlier_datasets_own_files(tmp_path):
    """The manifest of an mcap dataset and the dataset.txt of a txt one (the released
    layout too) go with --overwrite, whichever format comes next."""
    from gscan_ros.data.io import split_bags

    assert _generate(tmp_path, "--format", "mcap") == 0
    assert _generate(tmp_path, "--format", "txt", "--overwrite") == 0
    assert not (tmp_path / "manifest.json").exists() and not split_bags(tmp_path)
    (tmp_path / "dataset.txt").write_bytes((Path(__file__).parent / "fixtures/released_format.txt").read_bytes())
    assert _generate(tmp_path, "--format", "mcap", "--overwrite") == 0
    assert not (tmp_path / "dataset.txt").exists() and (tmp_path / "manifest.json").is_file()


def test_k_shot_beyond_the_adverb_1_examples_is_refused_naming_the_maximum(tmp_path):
    """The maximum is the full set's adverb_1 count, a subset's too; a subset of K
    examples is then the K k-shot examples, all in train."""
    config = GenerationConfig(seed=1, k_shot=1_000_000, **SMALL_WORLD)
    with pytest.raises(GscanError, match=r"--k-shot must be in \[0, \d+\]") as error:
        generate_dataset(tmp_path / "out", config)
    assert not (tmp_path / "out").exists()
    maximum = int(str(error.value).split("[0, ")[1].split("]")[0])
    report = generate_dataset(tmp_path / "out", replace(config, max_examples=maximum, k_shot=maximum))
    header = read_header(report.path).extra["gscan_ros"]
    assert maximum > 0 and report.split_sizes["train"] == maximum and sum(report.split_sizes.values()) == maximum
    assert header["config"]["k_shot"] == len(header["k_shot_train_indices"]) == maximum


def test_a_subset_smaller_than_k_shot_is_refused(tmp_path):
    with pytest.raises(GscanError, match="--examples must be at least --k-shot"):
        generate_dataset(tmp_path / "out", GenerationConfig(seed=1, max_examples=2, k_shot=3))
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("argv, message", [
    (["--k-shot", "5", "--split-kind", "length"], "--k-shot applies to --split-kind compositional only"),
    (["--cut-off-target-length", "12"], "--cut-off-target-length applies to --split-kind length only"),
])
def test_an_option_of_the_other_split_kind_is_refused(tmp_path, capsys, argv, message):
    """It would do nothing, and the header would still record it."""
    from gscan_ros.cli import main

    assert main(["generate", "--out", str(tmp_path / "out"), "--examples", "10", "--quiet", *argv]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
    assert not (tmp_path / "out").exists()


def _examples_by_split(path) -> dict[str, list[str]]:
    """Each split's examples as canonical JSON texts, in file order."""
    out = defaultdict(list)
    for split, _, raw in iter_raw_examples(path):
        out[split].append(json.dumps(raw, sort_keys=True))
    return out


def _assert_sample_of_each_split(subset, full_examples: dict[str, list[str]]) -> dict[str, list[str]]:
    """Every example of `subset` is one of the full set's in the same split, in the full
    set's order; returns the subset's examples."""
    examples = _examples_by_split(subset)
    for split, texts in examples.items():
        remaining = iter(full_examples[split])
        assert all(text in remaining for text in texts), f"{split}: not a subsequence of the full set's {split}"
    return examples


@pytest.fixture(scope="module")
def full_length_sets(tmp_path_factory):
    """Per seed: the full set's report and its examples by split."""
    root = tmp_path_factory.mktemp("full_length")
    reports = {seed: generate_dataset(root / str(seed), GenerationConfig(seed=seed, **SMALL_LENGTH)) for seed in (0, 1)}
    return {seed: (report, _examples_by_split(report.path)) for seed, report in reports.items()}


@pytest.mark.slow
@settings(max_examples=5)
@given(seed=st.sampled_from([0, 1]), size=st.integers(1, 25_000))
def test_a_subset_is_a_sample_of_each_split_of_the_same_seed_full_set(full_length_sets, tmp_path_factory,
                                                                       seed, size):
    """Same examples, same split, same bytes, splits in proportion, the same subset
    again for (seed, N) whatever the worker count."""
    full, full_examples = full_length_sets[seed]
    out = tmp_path_factory.mktemp("subset")
    subset = generate_dataset(out / "one", GenerationConfig(seed=seed, max_examples=size, **SMALL_LENGTH))
    _assert_sample_of_each_split(subset.path, full_examples)
    again = generate_dataset(out / "two", GenerationConfig(seed=seed, max_examples=size, **SMALL_LENGTH), workers=2)
    assert again.path.read_bytes() == subset.path.read_bytes()
    drawn = dict(full.split_sizes, test=full.split_sizes["test"] + full.discarded_equivalent)  # before de-duplication
    total = sum(drawn.values())
    for split, n in subset.split_sizes.items():
        quota = size * drawn[split] / total if size < total else drawn[split]
        assert (n <= quota + 1) if split == "test" else abs(n - quota) < 1, split


@pytest.mark.slow
def test_a_compositional_subset_keeps_the_full_sets_splits_and_k_shot_examples(tmp_path):
    config = GenerationConfig(seed=2, k_shot=3, **SMALL_WORLD)
    full = generate_dataset(tmp_path / "full", config)
    subset = generate_dataset(tmp_path / "subset", replace(config, max_examples=500))
    full_examples = _examples_by_split(full.path)
    train = _assert_sample_of_each_split(subset.path, full_examples)["train"]
    assert set(subset.split_sizes) == set(full.split_sizes) and subset.split_sizes["test"] > 0
    assert train[-3:] == full_examples["train"][-3:]  # the full set's k-shot examples, last
    assert sum("cautiously" in json.loads(text)["command"] for text in train) == 3
    header = read_header(subset.path).extra["gscan_ros"]
    assert header["k_shot_train_indices"] == list(range(len(train) - 3, len(train)))
