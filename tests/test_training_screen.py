"""Seed screening: candidates trained in turn, the first with right-signed maps kept, and
the kept candidate training on exactly as a run of its own seed."""
import json

import pytest
import torch

from gscan_ros.cli import main
from gscan_ros.model.checkpoint import read_checkpoint
from gscan_ros.training.config import ConfigError, TrainConfig


def run_train(dataset, out, *extra):
    return main(["train", "--data", str(dataset), "--out", str(out), "--quiet", "--set", "batch_size=16",
                 "--set", "log_every=1", "--set", "threads=1", "--set", "max_dev_examples=8",
                 "--set", "lexicon=none", "--set", "validate_every=100", "--set", "checkpoint_every=100", *extra])


def script_localization(monkeypatch, values):
    """The screen reads these localization %s in turn (chance 19 %: a pass above 9.5 %)."""
    import gscan_ros.training.trainer as trainer

    scripted = iter(values)
    monkeypatch.setattr(trainer, "summarize", lambda readings: {"all": {
        "localization": next(scripted), "localization_chance": 19.0, "size_spearman": float("nan")}})


def records(run):
    return [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]


def weights(path):
    return read_checkpoint(path)["state_dict"]


def assert_same_weights(a, b):
    wa, wb = weights(a), weights(b)
    assert wa.keys() == wb.keys()
    for name in wa:
        assert torch.equal(wa[name], wb[name]), name


def test_the_first_candidate_above_chance_is_kept_and_trains_as_its_seed(tiny_dataset, tmp_path, monkeypatch):
    torch.set_num_threads(1)
    script_localization(monkeypatch, [2.0, 10.0, 99.0])
    screened = tmp_path / "screened"
    assert run_train(tiny_dataset, screened, "--set", "screen_seeds=3", "--set", "screen_updates=2",
                     "--set", "max_updates=4") == 0
    recs = records(screened)
    screens = [r for r in recs if r["event"] == "screen"]
    assert [(r["candidate"], r["seed"], r["step"], r["passed"]) for r in screens] == [(0, 0, 2, False),
                                                                                        (1, 1000, 2, True)]
    end = next(r for r in recs if r["event"] == "screen_end")
    assert (end["seed"], end["candidates"], end["screen_updates"]) == (1000, 2, 4)
    assert [r["step"] for r in recs if r["event"] == "train"] == [3, 4]
    assert read_checkpoint(screened / "last.pt")["train_seed"] == 1000

    alone = tmp_path / "seed1000"
    assert run_train(tiny_dataset, alone, "--set", "seed=1000", "--set", "max_updates=4") == 0
    assert_same_weights(screened / "last.pt", alone / "last.pt")


def test_without_a_pass_the_best_candidate_is_kept_and_resumes_as_its_seed(tiny_dataset, tmp_path, monkeypatch):
    torch.set_num_threads(1)
    script_localization(monkeypatch, [5.0, 8.0, 3.0])  # all below half of chance (9.5)
    screened = tmp_path / "screened"
    args = ["--set", "screen_seeds=3", "--set", "screen_updates=2"]
    assert run_train(tiny_dataset, screened, *args, "--set", "max_updates=3") == 0
    assert [r["seed"] for r in records(screened) if r["event"] == "screen"] == [0, 1000, 2000]
    assert run_train(tiny_dataset, screened, *args, "--set", "max_updates=5", "--resume") == 0
    assert sum(r["event"] == "screen" for r in records(screened)) == 3  # a resumed run does not screen again
    alone = tmp_path / "seed1000"
    assert run_train(tiny_dataset, alone, "--set", "seed=1000", "--set", "max_updates=5") == 0
    assert_same_weights(screened / "last.pt", alone / "last.pt")


def test_a_screen_stopped_between_candidates_resumes_at_the_next_one(tiny_dataset, tmp_path, monkeypatch):
    """A stop during candidate 2 keeps candidates 0 and 1 (last.pt holds the better, 1000);
    the resumed screen trains only candidate 2 and ends as an unstopped screen does."""
    torch.set_num_threads(1)
    args = ["--set", "screen_seeds=3", "--set", "screen_updates=2", "--set", "max_updates=4"]

    def stop():
        raise KeyboardInterrupt

    readings = iter([5.0, 8.0])  # both below half of chance (9.5): rejected
    import gscan_ros.training.trainer as trainer

    monkeypatch.setattr(trainer, "summarize", lambda readings_: {"all": {
        "localization": next(readings, None) or stop(), "localization_chance": 19.0, "size_spearman": 0.0}})
    stopped = tmp_path / "stopped"
    assert run_train(tiny_dataset, stopped, *args) != 0
    ckpt = read_checkpoint(stopped / "last.pt")
    assert (ckpt["train_seed"], ckpt["step"], ckpt["screen"]) == (1000, 2, {"next_candidate": 2, "localization": 8.0})

    script_localization(monkeypatch, [3.0])
    assert run_train(tiny_dataset, stopped, *args, "--resume") == 0
    screens = [(r["candidate"], r["seed"]) for r in records(stopped) if r["event"] == "screen"]
    assert screens == [(0, 0), (1, 1000), (2, 2000)]
    end = next(r for r in records(stopped) if r["event"] == "screen_end")
    assert (end["seed"], end["candidates"], end["screen_updates"]) == (1000, 3, 6)
    assert "screen" not in read_checkpoint(stopped / "last.pt")

    script_localization(monkeypatch, [5.0, 8.0, 3.0])
    whole = tmp_path / "whole"
    assert run_train(tiny_dataset, whole, *args) == 0
    assert_same_weights(stopped / "last.pt", whole / "last.pt")


@pytest.mark.parametrize("overrides, named", [
    (["screen_seeds=4", "model_kind=seq2seq"], "screen_seeds"),
    (["screen_seeds=4", "model.message=state"], "screen_seeds"),
    (["screen_seeds=4", "screen_updates=1000", "max_updates=1000"], "screen_updates"),
    (["screen_seeds=-1"], "screen_seeds"),
])
def test_screening_settings_that_cannot_work_are_named(overrides, named):
    with pytest.raises(ConfigError, match=named):
        TrainConfig.load(None, overrides)
