"""`gscan-ros verify` on bags: lost data (truncated or corrupt MCAP, dropped episodes) fails
with one line per bag unless `--allow-partial`; an intact bag passes."""
import pytest

from gscan_ros.cli import main
from gscan_ros.data.bag import BagWriter, repair_bag, write_bag
from gscan_ros.data.generate import GenerationConfig, generate_dataset
from gscan_ros.data.io import iter_episodes

from bag_support import damaged_copy, data_end, make_episodes, on_grid, truncated_copy


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    """Planner-consistent episodes (a generated dataset) as one bag of small chunks, and as
    a directory of per-split bags."""
    root = tmp_path_factory.mktemp("verify")
    report = generate_dataset(root / "data", GenerationConfig(seed=3, max_examples=60))
    episodes = list(iter_episodes(report.path))
    with BagWriter(root / "bag", chunk_size=4096) as writer:
        for episode in episodes:
            writer.write_episode(episode)
    for split in ("train", "test"):
        with BagWriter(root / "splits" / split, chunk_size=4096) as writer:
            for episode in episodes:
                if episode.split == split:
                    writer.write_episode(episode)
    return root, episodes


def _verify(capsys, *argv):
    try:
        code = main(["verify", *map(str, argv), "--quiet"])
    except SystemExit as exc:
        code = exc.code
    captured = capsys.readouterr()
    return code, captured.out, captured.err.strip().splitlines()


def test_intact_bag_passes(bags, capsys):
    root, episodes = bags
    code, out, err = _verify(capsys, root / "bag")
    assert code == 0 and err == []
    assert f"verified {len(episodes)} examples: 0 mismatch(es)" in out


def test_truncated_bag_fails_unless_partial_is_allowed(bags, tmp_path, capsys):
    root, episodes = bags
    bag = truncated_copy(root / "bag", tmp_path / "cut", data_end(root / "bag") // 3)
    code, out, err = _verify(capsys, bag)
    assert code == 1
    assert "0 mismatch(es)" in out  # what could be read is right; the loss alone fails
    assert len(err) == 1 and err[0].startswith("gscan-ros verify: error: lost data:")
    assert "truncated" in err[0] and f"complete episodes (of {len(episodes)} recorded)" in err[0]
    assert "--allow-partial" in err[0]
    code, out, err = _verify(capsys, bag, "--allow-partial")
    assert code == 0
    assert len(err) == 1 and err[0].startswith("warning: lost data") and "truncated" in err[0]


def test_corrupt_bag_fails_and_its_repair_passes(bags, tmp_path, capsys):
    root, _ = bags

    def flip(data):
        data[len(data) // 4] ^= 0xFF

    bag = damaged_copy(root / "bag", tmp_path / "flip", flip)
    code, _, err = _verify(capsys, bag)
    assert code == 1 and len(err) == 1 and "corrupt" in err[0] and "lost" in err[0]
    repair_bag(bag, tmp_path / "repaired")
    code, _, err = _verify(capsys, tmp_path / "repaired")
    assert code == 0 and err == []


def test_damaged_split_bag_is_named(bags, tmp_path, capsys):
    root, _ = bags
    splits = tmp_path / "splits"
    truncated_copy(root / "splits" / "train", splits / "train", data_end(root / "splits" / "train") // 2)
    test_bag = splits / "test"
    test_bag.mkdir()
    for path in (root / "splits" / "test").iterdir():
        (test_bag / path.name).write_bytes(path.read_bytes())
    code, _, err = _verify(capsys, splits)
    assert code == 1 and len(err) == 1 and f"{splits / 'train'}: truncated" in err[0]
    assert _verify(capsys, splits, "--splits", "test")[0] == 0


def test_mismatch_still_fails_with_allow_partial(tmp_path, capsys):
    with BagWriter(tmp_path / "random", chunk_size=4096) as writer:
        for episode in make_episodes(30, seed=1):  # random walks: not what the planner does
            writer.write_episode(episode)
    bag = truncated_copy(tmp_path / "random", tmp_path / "cut", data_end(tmp_path / "random") // 2)
    code, out, err = _verify(capsys, bag, "--allow-partial")
    assert code == 1 and "MISMATCH" in out and err[-1].startswith("warning: lost data")


@pytest.mark.parametrize("argv, name", [(["--limit", "-1"], "--limit"), (["--limit", "0"], "--limit"),
                                        (["--show", "-2"], "--show"), (["--limit", "x"], "--limit")])
def test_bad_numbers_are_one_line_errors(bags, capsys, argv, name):
    root, _ = bags
    code, _, err = _verify(capsys, root / "bag", *argv)
    assert code == 1 and len(err) == 1 and name in err[0] and "Traceback" not in "\n".join(err)


def test_limit_judges_the_part_read(bags, tmp_path, capsys):
    root, _ = bags
    bag = truncated_copy(root / "bag", tmp_path / "cut", data_end(root / "bag") // 2)
    code, out, err = _verify(capsys, bag, "--limit", "3")
    assert code == 0 and "verified 3 examples" in out  # the tear lies beyond what was read
    code, out, err = _verify(capsys, bag, "--limit", "10000")
    assert code == 1 and "truncated" in err[0]


def test_a_bag_without_episodes_fails(tmp_path, capsys):
    with BagWriter(tmp_path / "empty"):
        pass
    code, out, err = _verify(capsys, tmp_path / "empty")
    assert code == 1 and out == "" and len(err) == 1
    assert err[0].startswith(f"gscan-ros verify: error: {tmp_path / 'empty'}: no episodes found (")


def test_a_folder_without_a_dataset_says_what_was_looked_for(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("mine")
    code, _, err = _verify(capsys, tmp_path)
    assert code == 1 and len(err) == 1
    assert "no dataset here (looked for dataset.txt, a rosbag2 bag: metadata.yaml or .mcap files" in err[0]


def test_a_bag_on_two_grid_sizes_fails(tmp_path, capsys):
    """What `train` refuses, verify reports: one line naming the sizes found."""
    write_bag(tmp_path / "mixed", make_episodes(3, seed=1) + on_grid(make_episodes(2, seed=2), 8))
    code, _, err = _verify(capsys, tmp_path / "mixed", "--show", "0")
    assert code == 1
    assert err[-1] == (f"gscan-ros verify: error: {tmp_path / 'mixed'}: episodes on 2 grid sizes "
                       "(3 on 6x6, 2 on 8x8); a dataset has one (`train` refuses it)")


def test_the_outcome_line_counts_a_refused_command_but_does_not_claim_it_was_taken(tmp_path):
    """A command refused before any episode began is a `rejected` outcome with no episode:
    `verify`/`replay --include-incomplete` cannot have checked or replayed it."""
    from types import SimpleNamespace

    from gscan_ros.data.bag_report import BagReadReport, incomplete_line

    report = BagReadReport(tmp_path)
    for _ in range(2):
        report.count_outcome("cut", taken=True)
    report.count_refused()
    readers = [SimpleNamespace(report=report)]
    assert report.outcomes == {"cut": 2, "rejected": 1}
    assert incomplete_line(readers, "checked", included=True) == (
        "episodes that did not end complete: 2 cut, 1 rejected (checked: 2 cut; 1 refused before any action, "
        "nothing to take)")
    assert incomplete_line(readers, "replayed", included=False) == \
        "episodes that did not end complete: 2 cut, 1 rejected (not replayed)"
    assert incomplete_line([SimpleNamespace(report=BagReadReport(tmp_path))], "checked", included=True) is None
