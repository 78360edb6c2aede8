"""`gscan-ros explain --progression` (Fig. 4) and `--metrics` on a tiny dataset and a 4-update run."""
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402

from gscan_ros.analysis.explain import evenly, snapshots, trace  # noqa: E402
from gscan_ros.analysis.figures import progression_figure  # noqa: E402
from gscan_ros.cli import main  # noqa: E402
from gscan_ros.data.io import iter_episodes  # noqa: E402
from gscan_ros.model.policy import Policy  # noqa: E402


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("data")
    assert main(["generate", "--out", str(out), "--examples", "300", "--seed", "0", "--workers", "1", "--quiet"]) == 0
    return out


@pytest.fixture(scope="module")
def run(dataset, tmp_path_factory):
    """Snapshots at updates 2 and 4 (WordNet lexicon: big|small share a module)."""
    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("run")
    assert main(["train", "--data", str(dataset), "--out", str(out), "--quiet", "--set", "max_updates=4",
                 "--set", "snapshot_every=2", "--set", "batch_size=16", "--set", "validate_every=2",
                 "--set", "threads=1", "--set", "max_dev_examples=8"]) == 0
    return out


def size_example(dataset):
    """Index and episode of the first train example with a size word (the tiny run knows its words)."""
    return next((i, e) for i, e in enumerate(iter_episodes(dataset, ["train"]))
                if {"big", "small"} & set(e.command.split()))


def test_progression_figure_has_a_row_per_word_and_a_column_per_snapshot(dataset, run):
    _, episode = size_example(dataset)
    paths = snapshots(run)
    assert [step for step, _ in paths] == [2, 4]
    columns = []
    for step, path in paths:
        tr = trace(Policy.from_checkpoint(path), episode.situation, episode.command, until=0)
        columns.append((f"update {step}", tr.steps[0]))
    fig = progression_figure(columns, tr.graph)
    try:
        words = [tr.graph.node(n).word for n in tr.graph.postorder()]
        rows = [t.get_text() for t in fig.texts if t.get_text() in words + ["size ordering"]]
        assert rows == words + ["size ordering"]
        titles = [ax.get_title() for ax in fig.axes if ax.get_title()]
        assert titles == ["world", "update 2", "update 4"]
        assert len(fig.axes) == 1 + len(rows) * len(columns)
    finally:
        plt.close(fig)


def test_explain_progression_writes_fig4(dataset, run, tmp_path, capsys):
    index, _ = size_example(dataset)
    out = tmp_path / "fig4.png"
    assert main(["explain", "--progression", str(run), "--data", str(dataset), "--split", "train",
                 "--index", str(index), "--out", str(out), "--threads", "1"]) == 0
    assert "2 snapshots (updates 2, 4)" in capsys.readouterr().out and out.stat().st_size > 0


def test_metrics_for_a_model_and_along_snapshots(dataset, run, capsys):
    assert main(["explain", "--metrics", "--data", str(dataset), "--splits", "test", "visual",
                 "--max-examples", "5", "--threads", "1"]) == 0
    out = capsys.readouterr().out
    metrics, colours, *heads = out.split("\n\n")
    assert [line.split("|")[1].strip() for line in metrics.splitlines()[2:] if line.startswith("| ")] == \
        ["A test", "C visual", "all"]
    assert colours.splitlines()[1].startswith("| noun | ")
    size_rows = int(metrics.splitlines()[-1].split("|")[8])  # "all": episodes with a size word
    assert len(heads) <= 1 and (heads or not size_rows)  # a size word's episodes give the heads' table
    assert not heads or heads[0].splitlines()[1] == "| head | maps | median range (max − min) |"
    assert main(["explain", "--metrics", "--progression", str(run), "--data", str(dataset), "--splits", "test",
                 "--threads", "1"]) == 0
    lines = capsys.readouterr().out.splitlines()
    rows = [line for line in lines if line.startswith("| ") and "update" not in line]
    assert [r.split("|")[1].strip() for r in rows] == ["2", "4"]
    header = next(line for line in lines if line.startswith("| update"))
    assert header.rstrip(" |").endswith("noun's weakest colour")
    assert all(r.count("|") == header.count("|") for r in rows)


def test_evenly_keeps_first_and_last():
    assert evenly(list(range(10)), 4) == [0, 3, 6, 9]
    assert evenly([1, 2], 8) == [1, 2]
