"""Readers of user files bound what they read before they allocate it, and an error
quotes a user's value short (docs/reliability.md, "Bounded memory")."""
import json
import os
import re
import subprocess
import sys
import tracemalloc
import zipfile
from contextlib import contextmanager
from pathlib import Path

import pytest
import torch

from gscan_ros.data.bag_metadata import MAX_METADATA_BYTES, read_bag_info
from gscan_ros.data.dataset import iter_examples
from gscan_ros.data.generate import GenerationConfig, generate_dataset
from gscan_ros.data.splits import ALL_TEST_SPLITS
from gscan_ros.errors import CheckpointError, DatasetFormatError, GscanError, SituationError, quoted
from gscan_ros.experiments.plan import PlanError, load_plan
from gscan_ros.model.checkpoint import MAX_CHECKPOINT_ENTRIES, read_checkpoint
from gscan_ros.training.config import ConfigError, TrainConfig
from gscan_ros.user_files import MAX_YAML_BYTES, MAX_YAML_DEPTH
from gscan_ros.world.types import situation_from_json

from model_support import tiny_checkpoint

FIXTURES = Path(__file__).parent / "fixtures"
REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "configs/semantic.yaml"
SHORT_LINE = 300  # characters: what an error quoting a value may take


@contextmanager
def peak_memory():
    """{"peak": bytes} that Python allocated at most inside the block."""
    measured = {}
    tracemalloc.start()
    try:
        yield measured
    finally:
        measured["peak"] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()


def alias_bomb(levels: int = 6) -> str:
    """A YAML flow list whose last item stands for 9**levels strings ("billion laughs"):
    ~300 bytes that a plain SafeLoader turns into a structure whose text is ~4 MB."""
    items = [f"&l0 [{', '.join(['lol'] * 9)}]"]
    items += [f"&l{i} [{', '.join([f'*l{i - 1}'] * 9)}]" for i in range(1, levels + 1)]
    return f"[{', '.join(items)}]"


def test_quoted_cuts_a_long_value_and_says_how_big_it_was():
    assert quoted("walk") == "'walk'"
    text = quoted("x" * 5_000_000)
    assert len(text) < 120 and text.endswith("… (5,000,000 characters)")
    nested = ["lol"]
    for _ in range(30):  # 9**30 strings, were it written out
        nested = [nested] * 9
    with peak_memory() as memory:
        text = quoted(nested)
    assert len(text) < 120 and memory["peak"] < 100_000


def _config(tmp_path, text):
    path = tmp_path / "config.yaml"
    path.write_text(text)
    return lambda: TrainConfig.load(path)


def _plan(tmp_path, text):
    path = tmp_path / "plan.yaml"
    path.write_text(text)
    return lambda: load_plan(path)


def _situation(tmp_path, shape):
    situation = json.loads((FIXTURES / "real_situation.json").read_text())
    situation["placed_objects"]["0"]["object"]["shape"] = shape
    return lambda: situation_from_json(situation)


def _dataset(tmp_path, command):
    dataset = json.loads((FIXTURES / "released_format.txt").read_text())
    dataset["examples"]["train"][0]["command"] = command
    (tmp_path / "dataset.txt").write_text(json.dumps(dataset))
    return lambda: list(iter_examples(tmp_path / "dataset.txt"))


HUGE = "x" * 200_000  # within the file bounds, so it reaches the checks that quote it
HUGE_VALUES = {
    "config": (lambda tmp: _config(tmp, f"model_kind: {HUGE}\n"), ConfigError),
    "config_list": (lambda tmp: _config(tmp, f"lr: [{', '.join(['1'] * 50_000)}]\n"), ConfigError),
    "override": (lambda tmp: lambda: TrainConfig.load(None, [f"lexicon={HUGE}"]), ConfigError),
    "plan": (lambda tmp: _plan(tmp, f"datasets: {{d: {{}}}}\nruns: [{{name: '{HUGE}!', config: {CONFIG}, "
                                    "data: d, seeds: [0]}]\n"), PlanError),
    "situation": (lambda tmp: _situation(tmp, HUGE), SituationError),
    "dataset_command": (lambda tmp: _dataset(tmp, f"walk,,{HUGE}"), DatasetFormatError),
}


@pytest.mark.parametrize("reader", HUGE_VALUES)
def test_an_error_quotes_a_huge_user_value_in_a_short_line(tmp_path, reader):
    make, error = HUGE_VALUES[reader]
    with pytest.raises(error) as info:
        make(tmp_path)()
    message = str(info.value)
    assert len(message) < SHORT_LINE and "\n" not in message, message[:SHORT_LINE]
    assert re.search(r"\([\d,]+ (characters|items)\)", message)  # and says how big the value was


def _bag_with_metadata(tmp_path, note: str) -> Path:
    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "bag_0.mcap").write_bytes(b"")
    (bag / "metadata.yaml").write_text(
        "rosbag2_bagfile_information:\n  version: 9\n  storage_identifier: mcap\n"
        "  relative_file_paths: [bag_0.mcap]\n  topics_with_message_count: []\n  message_count: 0\n"
        "  starting_time: {nanoseconds_since_epoch: 0}\n  duration: {nanoseconds: 0}\n"
        f"  custom_data:\n    gscan_ros.note: {note}\n")
    return bag


BOMBS = {
    "config": (lambda tmp: _config(tmp, f"model_kind: {alias_bomb()}\n"), ConfigError, "config.yaml"),
    "plan_defaults": (lambda tmp: _plan(tmp, f"defaults: {{model: {{message: {alias_bomb()}}}}}\n"),
                      PlanError, "plan.yaml"),
    "override": (lambda tmp: lambda: TrainConfig.load(None, [f"model.message={alias_bomb()}"]),
                 ConfigError, "override"),
    "bag_metadata": (lambda tmp: lambda: read_bag_info(_bag_with_metadata(tmp, alias_bomb(8))),
                     DatasetFormatError, "metadata.yaml"),  # beyond its larger bound
}


@pytest.mark.parametrize("reader", BOMBS)
def test_a_yaml_alias_bomb_is_refused_before_it_expands(tmp_path, reader):
    make, error, where = BOMBS[reader]
    read = make(tmp_path)
    with peak_memory() as memory, pytest.raises(error) as info:
        read()
    message = str(info.value)
    bound = MAX_METADATA_BYTES if reader == "bag_metadata" else MAX_YAML_BYTES
    assert where in message and f"{bound:,}" in message and "aliases" in message
    assert len(message) < SHORT_LINE
    assert memory["peak"] < 1 << 20  # the bomb's text alone would be ~4 MB


def test_anchors_that_share_a_block_still_load(tmp_path):
    plan = _plan(tmp_path, (
        f"datasets: {{d: {{}}}}\nruns:\n"
        f"  - {{name: a, config: {CONFIG}, data: d, seeds: [0], set: &shared {{model.message: state, lr: 0.002}}}}\n"
        f"  - {{name: b, config: {CONFIG}, data: d, seeds: [0], set: *shared}}\n"))()
    assert plan.runs[0].overrides == plan.runs[1].overrides == ("model.message=state", "lr=0.002")


def test_yaml_nested_beyond_the_depth_bound_is_one_error(tmp_path):
    read = _config(tmp_path, "lr: " + "[" * 2000 + "]" * 2000 + "\n")  # a plain SafeLoader: RecursionError
    with pytest.raises(ConfigError, match=f"nests deeper than {MAX_YAML_DEPTH} levels"):
        read()


def test_a_yaml_file_beyond_the_size_bound_is_refused_before_it_is_read(tmp_path):
    read = _config(tmp_path, "lr: 0.002\n# " + "x" * MAX_YAML_BYTES + "\n")
    with peak_memory() as memory, pytest.raises(ConfigError) as info:
        read()
    assert "config.yaml" in str(info.value) and f"{MAX_YAML_BYTES:,} bytes" in str(info.value)
    assert memory["peak"] < MAX_YAML_BYTES // 4


def test_the_metadata_of_a_large_recording_reads(tmp_path):
    """A robot with 1,000 topics, a day split every minute: metadata.yaml (~0.8 MB) beyond
    the bound of configs reads, in about a second."""
    import time

    import yaml

    from gscan_ros.data.bag import write_bag

    from bag_support import make_episodes

    write_bag(tmp_path / "bag", make_episodes(2))
    path = tmp_path / "bag" / "metadata.yaml"
    metadata = yaml.safe_load(path.read_text())
    info = metadata["rosbag2_bagfile_information"]
    topic = info["topics_with_message_count"][0]
    info["topics_with_message_count"] += [
        {**topic, "topic_metadata": {**topic["topic_metadata"], "name": f"/robot/sensor_{i}"}} for i in range(1000)]
    info["files"] += [{**info["files"][0], "path": f"bag_{i}.mcap"} for i in range(1, 1440)]
    path.write_text(yaml.safe_dump(metadata, sort_keys=False))
    assert path.stat().st_size > MAX_YAML_BYTES
    start = time.perf_counter()
    assert len(read_bag_info(tmp_path / "bag").topics) > 1000
    assert time.perf_counter() - start < 10


# A checkpoint that declares more than the (lowered) bound, loaded in a child process
# whose peak RSS is measured: torch would inflate the 48 MiB tensor before any check.
_LOAD_BOMB = """
import resource, sys
import gscan_ros.model.checkpoint as checkpoint
from gscan_ros.errors import CheckpointError
checkpoint.MAX_CHECKPOINT_BYTES = 16 << 20
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
try:
    checkpoint.read_checkpoint(sys.argv[1])
    message = "loaded"
except CheckpointError as exc:
    message = str(exc)
print((resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) * 1024, message)
"""


def test_a_zip_bomb_checkpoint_is_refused_before_torch_unpacks_it(tmp_path):
    ckpt = torch.load(tiny_checkpoint(tmp_path / "tiny.pt"), weights_only=True)
    ckpt["state_dict"]["padding"] = torch.zeros(12 << 20)  # 48 MiB of zeros
    torch.save(ckpt, tmp_path / "plain.pt")
    bomb = tmp_path / "bomb.pt"
    with zipfile.ZipFile(tmp_path / "plain.pt") as plain, zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED) as out:
        for info in plain.infolist():
            out.writestr(info.filename, plain.read(info))
    assert bomb.stat().st_size < 1 << 20
    result = subprocess.run([sys.executable, "-c", _LOAD_BOMB, str(bomb)], capture_output=True, text=True,
                            check=True, timeout=120)
    grown, message = result.stdout.strip().split(" ", 1)
    assert "bomb.pt" in message and "declares" in message and f"{16 << 20:,}" in message
    assert int(grown) < 16 << 20  # the inflated tensor alone is 48 MiB


def test_a_checkpoint_with_too_many_files_is_refused_before_they_are_listed(tmp_path):
    path = tmp_path / "many.pt"
    with zipfile.ZipFile(path, "w") as archive:
        for i in range(MAX_CHECKPOINT_ENTRIES + 1):
            archive.writestr(f"many/data/{i}", b"")
    with pytest.raises(CheckpointError, match=f"{MAX_CHECKPOINT_ENTRIES + 1:,} files"):
        read_checkpoint(path)


@pytest.fixture(scope="module")
def dataset_with_a_lost_split(tmp_path_factory):
    """Per-split bags whose bag of one test split was cut inside its first chunk: its
    metadata and the manifest still count its episodes, none can be read. Returns the
    dataset, a tiny checkpoint, an intact test split and the lost one."""
    root = tmp_path_factory.mktemp("lost_split")
    generate_dataset(root / "data", GenerationConfig(seed=5, max_examples=60), fmt="mcap")
    counts = json.loads((root / "data" / "manifest.json").read_text())["splits"]
    kept, lost = [split for split in ALL_TEST_SPLITS if counts.get(split)][:2]
    for mcap in (root / "data" / lost).glob("*.mcap"):
        os.truncate(mcap, 3000)
    return root / "data", tiny_checkpoint(root / "tiny.pt"), kept, lost


def test_a_split_whose_bag_lost_every_episode_fails_the_command_naming_it(dataset_with_a_lost_split, tmp_path,
                                                                          capsys):
    """evaluate, replay and augment used to exit 0 without the split (a warning on stderr)."""
    from gscan_ros.cli import main
    from gscan_ros.data.io import iter_episodes

    data, checkpoint, kept, lost = dataset_with_a_lost_split
    evaluate = ["evaluate", "--checkpoint", checkpoint, "--data", data, "--max-examples", "1", "--quiet", "--out"]
    commands = {
        "evaluate --splits": [*evaluate, tmp_path / "e1", "--splits", kept, lost],
        "evaluate": [*evaluate, tmp_path / "e2"],  # every test split the dataset counts
        "replay": ["replay", data, "--checkpoint", checkpoint, "--splits", kept, lost],
        "augment": ["augment", "--method", "geca", "--data", data, "--out", tmp_path / "aug", "--examples", "5",
                    "--quiet"],
    }
    for name, argv in commands.items():
        code = main([str(a) for a in argv])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 1 and len(err) == 1, (name, err)
        assert f"no episodes of split(s) {lost} could be read from {data}" in err[0], name
        assert f"{data / lost}: truncated" in err[0], name
    assert not (tmp_path / "e1").exists() and not (tmp_path / "aug").exists()
    assert list(iter_episodes(data, [kept]))  # the intact split reads


def test_a_results_json_nested_too_deeply_is_one_report_error(tmp_path):
    from gscan_ros.experiments.tables import load_runs

    run = tmp_path / "run"
    run.mkdir()
    (run / "results.json").write_text("[" * 100_000 + "]" * 100_000)  # json.loads: RecursionError
    with pytest.raises(GscanError, match="results.json"):
        load_runs([tmp_path])
