"""Learning-rate schedule, gradient clipping, stopping at a target, and run-directory safety."""
import dataclasses
import json

import pytest
import torch

from gscan_ros.cli import main
from gscan_ros.model.checkpoint import read_checkpoint
from gscan_ros.training.config import ConfigError, TrainConfig


def test_warmup_then_cosine_decay_to_the_floor():
    cfg = TrainConfig(lr=2e-3, warmup_updates=4, lr_decay="cosine", decay_updates=14, min_lr_ratio=0.1)
    f = [cfg.lr_factor(s) for s in range(20)]
    assert f[:4] == [0.25, 0.5, 0.75, 1.0]
    assert f[4] == 1.0 and f[9] == pytest.approx(0.55)  # half way down: 0.1 + 0.9 * 0.5
    assert all(a >= b for a, b in zip(f[4:], f[5:]))
    assert f[14:] == [pytest.approx(0.1)] * 6


def test_linear_decay_and_constant_default():
    assert [TrainConfig().lr_factor(s) for s in (0, 10, 10_000)] == [1.0, 1.0, 1.0]
    cfg = TrainConfig(lr_decay="linear", decay_updates=10, min_lr_ratio=0.0)
    assert cfg.lr_factor(5) == pytest.approx(0.5) and cfg.lr_factor(10) == 0.0


@pytest.mark.parametrize("override", ["lr=nan", "lr=0", "grad_clip=-1", "min_lr_ratio=2", "warmup_updates=-3",
                                      "lr_decay=step", "target_dev_exact_match=101", "max_minutes=inf"])
def test_bad_schedule_settings_are_named(override):
    with pytest.raises(ConfigError, match=override.split("=")[0]):
        TrainConfig.load(None, [override])


def test_a_decay_that_would_end_within_the_warm_up_is_refused():
    """The factor would drop from 1 to min_lr_ratio in one update at the warm-up's end."""
    with pytest.raises(ConfigError, match=r"decay_updates \(50\) must come after warmup_updates \(100\)"):
        TrainConfig.load(None, ["warmup_updates=100", "decay_updates=50", "lr_decay=cosine"])
    TrainConfig.load(None, ["warmup_updates=100", "decay_updates=50", "lr_decay=none"])  # no decay: nothing to end


@pytest.fixture
def dataset(tiny_dataset):
    return tiny_dataset


def run_train(dataset, out, *extra):
    return main(["train", "--data", str(dataset), "--out", str(out), "--quiet", "--set", "batch_size=16",
                 "--set", "log_every=1", "--set", "threads=1", "--set", "max_dev_examples=8",
                 "--set", "lexicon=none", *extra])


def test_schedule_is_applied_and_resumed(dataset, tmp_path):
    torch.set_num_threads(1)
    run = tmp_path / "run"
    common = ["--set", "lr=0.004", "--set", "warmup_updates=2", "--set", "lr_decay=linear",
              "--set", "decay_updates=4", "--set", "min_lr_ratio=0.25", "--set", "grad_clip=0.5",
              "--set", "validate_every=3", "--set", "checkpoint_every=3"]
    assert run_train(dataset, run, *common, "--set", "max_updates=3") == 0
    assert run_train(dataset, run, *common, "--set", "max_updates=5", "--resume") == 0
    lrs = [r["lr"] for r in map(json.loads, (run / "metrics.jsonl").read_text().splitlines())
           if r["event"] == "train"]
    # the lr logged after update s is the one update s+1 uses, lr_factor(s): 1, 1, 0.625, 0.25, 0.25 (s = 1..5)
    assert lrs == pytest.approx([0.004, 0.004, 0.0025, 0.001, 0.001])


def test_a_resumed_run_logs_the_losses_of_the_run_left_unstopped(dataset, tmp_path):
    """A checkpoint between two `train` records keeps the updates since the first: the next
    record after the resume means them too, as in the run left unstopped."""
    torch.set_num_threads(1)
    common = ["--set", "log_every=4", "--set", "validate_every=6", "--set", "checkpoint_every=6"]
    straight, resumed = tmp_path / "straight", tmp_path / "resumed"
    assert run_train(dataset, straight, *common, "--set", "max_updates=12") == 0
    assert run_train(dataset, resumed, *common, "--set", "max_updates=6") == 0  # stops mid-window (5..8)
    assert run_train(dataset, resumed, *common, "--set", "max_updates=12", "--resume") == 0

    def losses(run):
        return [(r["step"], r["loss"]) for r in map(json.loads, (run / "metrics.jsonl").read_text().splitlines())
                if r["event"] == "train"]

    assert losses(resumed) == losses(straight) and [s for s, _ in losses(straight)] == [4, 8, 12]


def test_a_resume_may_not_move_the_end_of_the_decay(dataset, tmp_path, capsys):
    """With `decay_updates` 0 the decay ends at `max_updates`: a resume with another budget
    would bend the schedule under the run, so it is refused; with its own end it may grow."""
    run = tmp_path / "run"
    common = ["--set", "lr_decay=cosine", "--set", "validate_every=2", "--set", "checkpoint_every=2"]
    assert run_train(dataset, run, *common, "--set", "max_updates=2") == 0
    capsys.readouterr()
    assert run_train(dataset, run, *common, "--set", "max_updates=4", "--resume") == 1
    assert "other settings of max_updates;" in capsys.readouterr().err
    ends_itself = tmp_path / "ends_itself"
    assert run_train(dataset, ends_itself, *common, "--set", "decay_updates=2", "--set", "max_updates=2") == 0
    assert run_train(dataset, ends_itself, *common, "--set", "decay_updates=2", "--set", "max_updates=4",
                     "--resume") == 0


def test_late_batch_size_takes_over_at_its_update_and_survives_a_resume_there(dataset, tmp_path):
    torch.set_num_threads(1)
    late = ["--set", "late_batch_size=4", "--set", "late_batch_from=2", "--set", "validate_every=2",
            "--set", "checkpoint_every=2"]
    straight, resumed = tmp_path / "straight", tmp_path / "resumed"
    assert run_train(dataset, straight, *late, "--set", "max_updates=4") == 0
    assert run_train(dataset, resumed, *late, "--set", "max_updates=2") == 0  # stops right at the switch
    assert run_train(dataset, resumed, *late, "--set", "max_updates=4", "--resume") == 0
    records = [r for r in map(json.loads, (straight / "metrics.jsonl").read_text().splitlines())
               if r["event"] == "train"]
    assert [r["mean_batch"] for r in records] == [16, 16, 4, 4]
    assert read_checkpoint(straight / "last.pt")["cursor"]["batch"] == 2  # a fresh epoch began at the switch
    weights = [read_checkpoint(run / "last.pt")["state_dict"] for run in (straight, resumed)]
    assert all(torch.equal(weights[1][k], v) for k, v in weights[0].items())


@pytest.mark.parametrize("overrides, named", [(["late_batch_size=100"], "go together"),
                                              (["late_batch_from=5"], "go together"),
                                              (["late_batch_size=-1", "late_batch_from=5"], ">= 0"),
                                              (["late_batch_size=200", "late_batch_from=500", "screen_seeds=8",
                                                "max_updates=40000"], "after the seed screen")])
def test_bad_late_batch_settings_are_named(overrides, named):
    with pytest.raises(ConfigError, match=named):
        TrainConfig.load(None, overrides)
    assert TrainConfig(batch_size=50, late_batch_size=200, late_batch_from=10).batch_size_at(9) == 50
    assert TrainConfig(batch_size=50, late_batch_size=200, late_batch_from=10).batch_size_at(10) == 200


def test_training_stops_once_the_target_is_reached(dataset, tmp_path, monkeypatch):
    """Dev exact match is scripted (0, 0, 60, ...): training stops at the third validation."""
    import gscan_ros.training.trainer as trainer

    real = trainer.evaluate_episodes
    scripted = iter([0.0, 0.0, 60.0, 90.0])

    def evaluate(*args, **kwargs):
        result = real(*args, **kwargs)
        score = next(scripted)
        monkeypatch.setattr(type(result), "exact_match", property(lambda self: score))
        return result

    monkeypatch.setattr(trainer, "evaluate_episodes", evaluate)
    run = tmp_path / "run"
    assert run_train(dataset, run, "--set", "max_updates=40", "--set", "validate_every=2",
                     "--set", "target_dev_exact_match=50") == 0
    records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    validations = [r for r in records if r["event"] == "validation"]
    assert [v["dev_exact_match"] for v in validations] == [0.0, 0.0, 60.0]
    assert records[-1]["event"] == "end" and records[-1]["step"] == 6 and records[-1]["reached_target"] is True
    assert read_checkpoint(run / "last.pt")["step"] == 6
    assert set(validations[0]["dev_by_group"]) == {"verb", "adverb", "size_word", "color_word", "heavy_target",
                                                   "moves_target", "target_length"}


def test_a_new_run_refuses_an_existing_run_directory(dataset, tmp_path, capsys):
    run = tmp_path / "run"
    assert run_train(dataset, run, "--set", "max_updates=1") == 0
    (run / "notes.txt").write_text("mine")
    (run / "results.json").write_text("{}")  # the old model's scores (an evaluation into the run)
    before = {p.name: p.read_bytes() for p in run.iterdir()}
    assert run_train(dataset, run, "--set", "max_updates=1") == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--overwrite" in err[0] and "--resume" in err[0]
    assert {p.name: p.read_bytes() for p in run.iterdir()} == before
    assert run_train(dataset, run, "--set", "max_updates=2", "--overwrite") == 0
    assert read_checkpoint(run / "last.pt")["step"] == 2 and (run / "notes.txt").read_text() == "mine"
    assert not (run / "results.json").exists()  # no old scores beside the new run
    assert sum(json.loads(line)["event"] == "start" for line in (run / "metrics.jsonl").read_text().splitlines()) == 1


def test_a_failed_start_leaves_no_run_directory(tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "dataset.txt").write_text("not json")
    assert main(["train", "--data", str(empty), "--out", str(tmp_path / "run"), "--quiet"]) == 1
    assert not (tmp_path / "run").exists()
    assert "Traceback" not in capsys.readouterr().err


def test_a_diverged_loss_stops_training_with_one_line(dataset, tmp_path, monkeypatch, capsys):
    from gscan_ros.model.compositional import CompositionalNetwork

    real = CompositionalNetwork.teacher_forcing
    calls = []

    def poisoned(self, batch):
        out = real(self, batch)
        calls.append(1)
        if len(calls) == 3:
            return dataclasses.replace(out, loss=out.loss * float("nan"))
        return out

    monkeypatch.setattr(CompositionalNetwork, "teacher_forcing", poisoned)
    run = tmp_path / "run"
    assert run_train(dataset, run, "--set", "max_updates=10", "--set", "checkpoint_every=2",
                     "--set", "validate_every=2") == 1
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert "nan" in line and "update 3" in line
    assert read_checkpoint(run / "last.pt")["step"] == 2
