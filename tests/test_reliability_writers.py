"""Every writer leaves whole outputs or none: one writer per output (a lock naming its
holder), temporary siblings renamed into place, no symbolic link followed out of the
output folder, nothing replaced without --overwrite, interrupted datasets recognisable as
incomplete by every reader, torn metrics lines repaired, one line on a full disk."""
import contextlib
import errno
import json
import os
import shutil
import subprocess
import sys

import pytest
import torch

from gscan_ros.cli import main
from gscan_ros.data.bag import BagWriter, read_bag_info
from gscan_ros.data.generate import GenerationConfig, generate_dataset
from gscan_ros.data.io import DATASET_MANIFEST, iter_episodes, split_bags
from gscan_ros.outputs import lock_path, write_text

from model_support import tiny_checkpoint

HOLD = "import sys, time\nfrom gscan_ros.outputs import claimed\nwith claimed(sys.argv[1]):\n" \
       "    print('held', flush=True)\n    time.sleep(60)\n"


def _cli(capsys, *argv) -> tuple[int, str, list[str]]:
    try:
        code = main([str(a) for a in argv])
    except SystemExit as exc:
        code = exc.code
    captured = capsys.readouterr()
    return code, captured.out, captured.err.strip().splitlines()


def _refused(capsys, *argv) -> str:
    """The one error line of a refused command (exit 1, no traceback)."""
    code, _, err = _cli(capsys, *argv)
    assert code == 1 and len(err) == 1 and "Traceback" not in err[0], err
    return err[0]


def _files(root) -> dict:
    return {str(p.relative_to(root)): p.read_bytes() if p.is_file() else None for p in sorted(root.rglob("*"))}


def _generate(out, *extra):
    return ["generate", "--out", out, "--examples", "60", "--seed", "5", "--workers", "1", "--quiet",
            "--percentage-dev", "0.2", *extra]


def _train(data, out, *extra):
    return ["train", "--data", data, "--out", out, "--quiet", "--set", "batch_size=8", "--set", "log_every=1",
            "--set", "threads=1", "--set", "max_dev_examples=4", "--set", "lexicon=none", "--set", "max_updates=1",
            *extra]


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """The same 60 examples as dataset.txt and as per-split bags, a dataset without dev
    examples in both formats, and a tiny checkpoint."""
    root = tmp_path_factory.mktemp("writers")
    config = GenerationConfig(seed=5, max_examples=60, percentage_dev=0.2)
    for fmt in ("txt", "mcap"):
        generate_dataset(root / fmt, config, fmt=fmt)
        generate_dataset(root / f"{fmt}_no_dev", GenerationConfig(seed=5, max_examples=60, percentage_dev=0), fmt=fmt)
    tiny_checkpoint(root / "tiny.pt")
    return root


@pytest.fixture
def dead_pid():
    """The id of a process that has exited."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


@contextlib.contextmanager
def held_elsewhere(path):
    """`path` claimed by another process; yields its pid."""
    proc = subprocess.Popen([sys.executable, "-c", HOLD, str(path)], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "held"
        yield proc.pid
    finally:
        proc.kill()
        proc.wait()


# ------------------------------------------------------------------ one writer per output
@pytest.mark.parametrize("command", ["generate", "train", "evaluate", "render"])
def test_a_second_writer_of_an_output_is_refused_naming_the_holder(data, tmp_path, capsys, command):
    out = tmp_path / ("a.png" if command == "render" else "out")
    argv = {"generate": _generate(out),
            "train": _train(data / "txt", out),
            "evaluate": ["evaluate", "--checkpoint", data / "tiny.pt", "--data", data / "txt", "--out", out],
            "render": ["render", data / "txt", "--out", out]}[command]
    with held_elsewhere(out) as pid:
        line = _refused(capsys, *argv)
        assert f"{out} is being written by pid {pid}" in line
        assert not out.exists()
    # the holder was killed: the kernel dropped its lock, the next writer goes ahead and
    # removes the lock file when it is done
    code, _, err = _cli(capsys, *argv, "--quiet" if command == "evaluate" else "--overwrite")
    assert code == 0, err
    assert out.exists() and not lock_path(out).exists()


# ------------------------------------------------------------------ nothing replaced unless told
def test_evaluate_refuses_earlier_results_unless_overwrite(data, tmp_path, capsys):
    argv = ["evaluate", "--checkpoint", data / "tiny.pt", "--data", data / "txt", "--splits", "test",
            "--max-examples", "3", "--out", tmp_path / "eval", "--quiet"]
    assert _cli(capsys, *argv)[0] == 0
    before = _files(tmp_path / "eval")
    assert set(before) == {"results.json", "results.md", "predictions.json"}
    line = _refused(capsys, *argv, "--no-predictions")
    assert "results.json" in line and "--overwrite" in line
    assert _files(tmp_path / "eval") == before
    assert _cli(capsys, *argv, "--no-predictions", "--overwrite")[0] == 0
    assert set(_files(tmp_path / "eval")) == {"results.json", "results.md"}  # no stale predictions.json


@pytest.mark.parametrize("case", ["evaluate", "generate", "train", "render"])
def test_no_writer_follows_a_symbolic_link_out_of_its_output(data, tmp_path, capsys, case):
    victim = tmp_path / "elsewhere" / "victim.txt"
    victim.parent.mkdir()
    victim.write_text("not yours")
    out = tmp_path / "out"
    out.mkdir()
    link, argv = {
        "evaluate": (out / "predictions.json", ["evaluate", "--checkpoint", data / "tiny.pt", "--data", data / "txt",
                                                "--out", out, "--overwrite"]),
        "generate": (out / "dataset.txt", _generate(out, "--overwrite")),
        "train": (out / "metrics.jsonl", _train(data / "txt", out, "--overwrite")),
        "render": (out / "a.png", ["render", data / "txt", "--out", out / "a.png", "--overwrite"]),
    }[case]
    link.symlink_to(victim)
    line = _refused(capsys, *argv)
    assert f"{link} is a symbolic link" in line
    assert victim.read_text() == "not yours" and link.is_symlink()


@pytest.mark.parametrize("fmt, obstacle", [("txt", "dataset.txt"), ("mcap", "train")])
def test_generate_refuses_what_is_in_the_way_in_one_line(tmp_path, capsys, fmt, obstacle):
    """A folder where dataset.txt goes, a file where a split bag goes: refused up front."""
    out = tmp_path / "out"
    out.mkdir()
    if fmt == "txt":
        (out / obstacle).mkdir()
    else:
        (out / obstacle).write_text("mine")
    before = _files(out)
    line = _refused(capsys, *_generate(out, "--format", fmt, "--overwrite"))
    assert f"{out / obstacle} is not a" in line
    assert _files(out) == before


# ------------------------------------------------------------------ interrupted writers
def test_an_interrupted_bag_writer_leaves_a_bag_every_reader_calls_unfinished(data, tmp_path, capsys):
    episodes = list(iter_episodes(data / "txt", ["train"]))[:3]
    with pytest.raises(KeyboardInterrupt), BagWriter(tmp_path / "bag") as writer:
        for episode in episodes:
            writer.write_episode(episode)
        raise KeyboardInterrupt
    assert read_bag_info(tmp_path / "bag").custom["gscan_ros.status"] == "recording"
    code, _, err = _cli(capsys, "verify", tmp_path / "bag", "--quiet")
    assert code == 1 and "the writer did not close the bag" in err[-1]


@pytest.mark.parametrize("stop", [KeyboardInterrupt, OSError(errno.ENOSPC, "No space left on device")])
def test_an_interrupted_generate_keeps_the_old_dataset_whole(data, tmp_path, capsys, monkeypatch, stop):
    out = tmp_path / "data"
    shutil.copytree(data / "mcap", out)
    before = _files(out)
    real = BagWriter.write_episode
    calls = []

    def write_episode(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == 25:  # between two episodes, a few splits in
            raise stop
        return real(self, *args, **kwargs)

    monkeypatch.setattr(BagWriter, "write_episode", write_episode)
    code, _, err = _cli(capsys, *_generate(out, "--format", "mcap", "--seed", "6", "--overwrite"))
    if stop is KeyboardInterrupt:
        assert code == 130
    else:
        assert code == 1 and len(err) == 1 and "No space left on device" in err[0]
    assert _files(out) == before  # the old dataset, untouched; no partial dataset beside it
    assert not lock_path(out).exists()
    monkeypatch.undo()
    assert _cli(capsys, "verify", out, "--quiet")[0] == 0


def test_readers_refuse_a_bag_dataset_whose_manifest_names_a_missing_split(data, tmp_path, capsys):
    out = tmp_path / "data"
    shutil.copytree(data / "mcap", out)
    shutil.rmtree(out / "visual")
    evaluate = ["evaluate", "--checkpoint", data / "tiny.pt", "--data", out, "--out", tmp_path / "e"]
    for argv in (["verify", out], evaluate, _train(out, tmp_path / "run")):
        line = _refused(capsys, *argv)
        assert f"{out} is incomplete (visual missing" in line, line


def test_readers_refuse_an_unfinished_split_bag_without_a_manifest(data, tmp_path, capsys):
    out = tmp_path / "data"
    shutil.copytree(data / "mcap", out)
    (out / DATASET_MANIFEST).unlink()  # as an older version wrote it
    assert _cli(capsys, "verify", out, "--quiet")[0] == 0
    metadata = out / "test" / "metadata.yaml"
    metadata.write_text(metadata.read_text().replace("gscan_ros.status: closed", "gscan_ros.status: recording"))
    assert "the bag(s) of test were not finished" in _refused(capsys, "verify", out)


# ------------------------------------------------------------------ missing splits, as dataset.txt
@pytest.mark.parametrize("fmt", ["txt", "mcap"])
@pytest.mark.parametrize("case", ["train without dev", "evaluate an absent split", "evaluate a typo",
                                  "verify a typo"])
def test_a_missing_split_is_refused_for_bags_as_for_dataset_txt(data, tmp_path, capsys, fmt, case):
    no_dev = data / f"{fmt}_no_dev"
    evaluate = ["evaluate", "--checkpoint", data / "tiny.pt", "--data", no_dev, "--out", tmp_path / "e", "--splits"]
    argv, missing = {"train without dev": (_train(no_dev, tmp_path / "run"), "dev"),
                     "evaluate an absent split": ([*evaluate, "test", "dev"], "dev"),
                     "evaluate a typo": ([*evaluate, "visul"], "visul"),
                     "verify a typo": (["verify", no_dev, "--splits", "visul"], "visul")}[case]
    line = _refused(capsys, *argv)
    assert f"no examples in split(s) {missing} of {no_dev}" in line and "visual" in line  # names the splits it has
    assert not (tmp_path / "run").exists() and not (tmp_path / "e").exists()


# ------------------------------------------------------------------ torn metrics.jsonl
def test_a_torn_last_metrics_line_does_not_block_the_run(data, tmp_path, capsys, caplog):
    torch.set_num_threads(1)
    run = tmp_path / "run"
    assert _cli(capsys, *_train(data / "txt", run, "--set", "validate_every=1"))[0] == 0
    with open(run / "metrics.jsonl", "a") as f:
        f.write('{"event": "train", "step": 2, "lo')  # a kill in the middle of a write
    code, _, err = _cli(capsys, *_train(data / "txt", run, "--set", "validate_every=1", "--set", "max_updates=2",
                                        "--resume"))
    assert code == 0, err
    events = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [e["event"] for e in events].count("start") == 2 and events[-1]["event"] == "end"
    assert sum("torn" in r.getMessage() for r in caplog.records) == 1  # reported once (the resume drops it)


def test_readers_of_metrics_skip_a_torn_line_with_one_warning(tmp_path, caplog):
    from gscan_ros.training.metrics_log import read_events
    from gscan_ros.training.trainer import plot_learning_curve

    metrics = tmp_path / "metrics.jsonl"
    metrics.write_text('{"event": "train", "step": 1, "loss": 2.0}\n{"event": "validation", "st')
    assert read_events(metrics) == [{"event": "train", "step": 1, "loss": 2.0}]
    plot_learning_curve(metrics, tmp_path / "curve.png")
    assert (tmp_path / "curve.png").stat().st_size > 0
    assert sum("skipped 1 line" in r.getMessage() for r in caplog.records) == 1


# ------------------------------------------------------------------ leftovers, full disk
def test_a_dead_writers_scratch_is_removed_and_reported(data, tmp_path, capsys, caplog, dead_pid):
    out = tmp_path / "data"
    scratch = out / f".dataset.partial-{dead_pid}"
    scratch.mkdir(parents=True)
    (scratch / "examples.jsonl").write_bytes(b"x" * 1000)
    partial_png = tmp_path / f".a.partial-{dead_pid}.png"
    partial_png.write_bytes(b"half a png")
    assert _cli(capsys, *_generate(out))[0] == 0
    assert _cli(capsys, "render", out, "--out", tmp_path / "a.png")[0] == 0
    assert not scratch.exists() and not partial_png.exists()
    removed = [r.getMessage() for r in caplog.records if "left by an interrupted writer" in r.getMessage()]
    assert len(removed) == 2 and str(scratch) in removed[0] and str(partial_png) in removed[1]


def test_a_killed_repairs_staging_is_removed_by_the_next_repair(data, tmp_path, capsys, caplog, dead_pid):
    bag = data / "mcap" / "train"
    staging = tmp_path / f".fixed.partial-{dead_pid}"
    (staging / "fixed").mkdir(parents=True)
    (staging / "fixed" / "fixed_0.mcap").write_bytes(b"x" * 1000)
    assert _cli(capsys, "bag", "repair", bag, "--out", tmp_path / "fixed")[0] == 0
    assert not staging.exists() and read_bag_info(tmp_path / "fixed").closed
    assert any(str(staging) in r.getMessage() for r in caplog.records if "interrupted writer" in r.getMessage())


def test_a_checkpoint_the_disk_refuses_is_one_line_and_leaves_nothing(tmp_path, monkeypatch):
    """torch reports a full disk as a RuntimeError from its zip writer."""
    from gscan_ros.errors import CheckpointError
    from gscan_ros.model.checkpoint import save_checkpoint

    def full(obj, path):
        open(path, "wb").write(b"half")
        raise RuntimeError("[enforce fail at inline_container.cc:603] . unexpected pos 64 vs 0\nfile write failed")

    monkeypatch.setattr(torch, "save", full)
    with pytest.raises(CheckpointError, match=r"^cannot write checkpoint '.*last.pt': file write failed$"):
        save_checkpoint(tmp_path / "last.pt", {"step": 1})
    assert list(tmp_path.iterdir()) == []


def test_a_checkpoint_reaches_the_disk_before_its_rename_and_keeps_the_one_before(tmp_path, monkeypatch):
    """The file is synced before the rename and the folder after it, so a power cut leaves the
    old checkpoint or the new one; `keep_previous` moves the old one aside first."""
    from gscan_ros.model.checkpoint import save_checkpoint

    calls, fsync, replace = [], os.fsync, os.replace

    def synced(fd):
        calls.append(("fsync", os.path.basename(os.readlink(f"/proc/self/fd/{fd}"))))
        fsync(fd)

    def renamed(src, dst):
        calls.append(("rename", os.path.basename(src), os.path.basename(dst)))
        replace(src, dst)

    monkeypatch.setattr(os, "fsync", synced)
    monkeypatch.setattr(os, "replace", renamed)
    save_checkpoint(tmp_path / "last.pt", {"format": 0, "step": 1}, keep_previous=True)
    save_checkpoint(tmp_path / "last.pt", {"format": 0, "step": 2}, keep_previous=True)
    assert calls == [("fsync", "last.pt.tmp"), ("rename", "last.pt.tmp", "last.pt"), ("fsync", tmp_path.name)] + [
        ("fsync", "last.pt.tmp"), ("rename", "last.pt", "last.prev.pt"), ("rename", "last.pt.tmp", "last.pt"),
        ("fsync", tmp_path.name)]
    steps = [torch.load(tmp_path / name, weights_only=True)["step"] for name in ("last.prev.pt", "last.pt")]
    assert steps == [1, 2]
    calls.clear()
    write_text(tmp_path / "config.yaml", "a: 1\n")  # every replaced output goes the same way
    assert [c[0] for c in calls] == ["fsync", "rename", "fsync"] and calls[1][2] == "config.yaml"


@pytest.mark.parametrize("command", ["generate", "train", "evaluate"])
def test_a_full_disk_is_one_line(data, tmp_path, capsys, monkeypatch, command):
    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "out" / "file"))

    target, argv = {
        "generate": ("gscan_ros.data.generate._run_tasks", _generate(tmp_path / "out")),
        "train": ("gscan_ros.training.trainer.append_event", _train(data / "txt", tmp_path / "out")),
        "evaluate": ("gscan_ros.training.evaluation_files.write_text",
                     ["evaluate", "--checkpoint", data / "tiny.pt", "--data", data / "txt", "--out", tmp_path / "out",
                      "--max-examples", "2", "--quiet"]),
    }[command]
    monkeypatch.setattr(target, full)
    line = _refused(capsys, *argv)
    assert f"while writing {tmp_path / 'out'}: No space left on device" in line


@pytest.mark.parametrize("command", ["verify", "evaluate"])
def test_an_input_that_cannot_be_read_is_one_line_naming_it(data, tmp_path, capsys, monkeypatch, command):
    """Not a traceback, and not reported as a failure to write the output."""
    unreadable = str(data / "txt" / "dataset.txt")

    def denied(*args, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied", unreadable)

    monkeypatch.setattr("gscan_ros.data.dataset._walk", denied)
    argv = {"verify": ["verify", data / "txt"],
            "evaluate": ["evaluate", "--checkpoint", data / "tiny.pt", "--data", data / "txt", "--out",
                         tmp_path / "out", "--max-examples", "2", "--quiet"]}[command]
    line = _refused(capsys, *argv)
    assert line == f"gscan-ros {command}: error: {unreadable}: Permission denied"


def test_a_bag_dataset_manifest_lists_every_split_bag(data):
    manifest = json.loads((data / "mcap" / DATASET_MANIFEST).read_text())
    assert {s for s, n in manifest["splits"].items() if n} == set(split_bags(data / "mcap"))
    assert manifest["header"]["grid_size"] == 6
