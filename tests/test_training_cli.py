"""`gscan-ros train` / `evaluate` end to end on a tiny generated dataset (resume included)."""
import json
from pathlib import Path

import pytest
import torch

from gscan_ros.cli import main
from gscan_ros.model.checkpoint import read_checkpoint


@pytest.fixture
def dataset(tiny_dataset):
    return tiny_dataset


def run_train(dataset, out, *extra):
    return main(["train", "--data", str(dataset), "--out", str(out), "--quiet", "--set", "batch_size=16",
                 "--set", "validate_every=2", "--set", "checkpoint_every=2", "--set", "log_every=1",
                 "--set", "threads=1", "--set", "max_dev_examples=8", "--set", "lexicon=none", *extra])


@pytest.mark.parametrize("kind", ["compositional", "seq2seq"])
def test_train_resume_evaluate(dataset, tmp_path, kind):
    torch.set_num_threads(1)
    run = tmp_path / "run"
    assert run_train(dataset, run, "--set", "max_updates=2", "--set", f"model_kind={kind}",
                     "--set", "snapshot_every=3") == 0
    assert read_checkpoint(run / "last.pt")["step"] == 2
    assert run_train(dataset, run, "--set", "max_updates=3", "--set", f"model_kind={kind}", "--resume",
                     "--set", "snapshot_every=3") == 0
    ckpt = read_checkpoint(run / "last.pt")
    assert ckpt["step"] == 3 and ckpt["kind"] == kind and ckpt["parser"] == "semantic"
    snapshot = read_checkpoint(run / "step_3.pt")  # the weights at update 3, without training state
    assert snapshot["step"] == 3 and "optimizer" not in snapshot
    assert all(torch.equal(snapshot["state_dict"][k], v) for k, v in ckpt["state_dict"].items())
    assert not (run / "step_2.pt").exists()
    events = [json.loads(line)["event"] for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert events.count("start") == 2 and "validation" in events
    assert (run / "learning_curve.png").stat().st_size > 0
    out = tmp_path / "eval"
    assert main(["evaluate", "--checkpoint", str(run / "model.pt"), "--data", str(dataset), "--splits", "test",
                 "visual", "--max-examples", "5", "--out", str(out), "--quiet", "--threads", "1", "--attention"]) == 0
    results = json.loads((out / "results.json").read_text())
    assert set(results["splits"]) == {"test", "visual"}
    assert results["splits"]["visual"]["letter"] == "C" and results["splits"]["test"]["examples"] == 5
    preds = json.loads((out / "predictions.json").read_text())
    assert len(preds) == 10 and {"input", "prediction", "target", "situation", "attention_weights",
                                 "accuracy", "exact_match"} <= set(preds[0])
    if kind == "compositional":  # per-word maps; the seq2seq baseline has no word modules
        assert preds[0]["attention_weights"] and all(len(m) == 36 for maps in preds[0]["attention_weights"].values()
                                                     for m in maps)
    assert (out / "results.md").read_text().count("|") > 10
    for split, summary in results["splits"].items():  # every failed episode has one kind, in the file too
        failed = [p for p in preds if p["split"] == split and not p["exact_match"]]
        assert sum(summary["failures"].values()) == len(failed)
        assert all(p["failure"] in summary["failures"] for p in failed)
    assert all(p["failure"] is None for p in preds if p["exact_match"])
    assert "target not reached" in (out / "results.md").read_text()
    for summary in results["splits"].values():  # each axis of the groups splits the split's episodes
        assert all(sum(v["examples"] for v in values.values()) == 5 for values in summary["by_group"].values())
    assert "| C | moves_target |" in (out / "results.md").read_text()


def test_resume_takes_the_runs_own_settings(dataset, tmp_path):
    """`--resume` without --config starts from RUN_DIR/config.yaml: only the budget needs saying."""
    run = tmp_path / "run"
    assert run_train(dataset, run, "--set", "max_updates=1", "--set", "parser=dependency") == 0
    assert main(["train", "--data", str(dataset), "--out", str(run), "--quiet", "--resume",
                 "--set", "max_updates=2"]) == 0
    ckpt = read_checkpoint(run / "last.pt")
    assert (ckpt["step"], ckpt["parser"]) == (2, "dependency")


def test_resume_with_another_parser_is_refused(dataset, tmp_path, capsys):
    run = tmp_path / "run"
    assert run_train(dataset, run, "--set", "max_updates=1") == 0
    assert run_train(dataset, run, "--set", "max_updates=2", "--set", "parser=dependency", "--resume") == 1
    assert "parser" in capsys.readouterr().err


@pytest.mark.parametrize("parser", ["constituency", "dependency"])
def test_a_run_of_multi_argument_modules_resumes_and_matches_its_own_config(dataset, tmp_path, parser):
    """A run saves every model setting, defaults included: a parse with modules of several
    arguments is not mistaken for a run from before `init_fan_in` (which would read as stale
    to the experiment runner and refuse its own resume)."""
    import yaml

    from gscan_ros.experiments.state import config_changes
    from gscan_ros.training.config import TrainConfig

    run = tmp_path / "run"
    assert run_train(dataset, run, "--set", "max_updates=1", "--set", f"parser={parser}") == 0
    saved = yaml.safe_load((run / "config.yaml").read_text())
    assert saved["model"]["init_fan_in"] == "module"
    plan = TrainConfig.from_dict({**saved, "model": {}, "max_updates": 2})  # a plan leaves defaults out
    assert config_changes(run, plan) == []
    assert run_train(dataset, run, "--set", "max_updates=2", "--set", f"parser={parser}", "--resume") == 0
    assert read_checkpoint(run / "last.pt")["step"] == 2


def test_resume_refuses_another_recipe_and_leaves_config_yaml(dataset, tmp_path, capsys):
    """The keys a resume may change are the runner's (`UNTRACKED_KEYS`: budget, time, threads);
    another recipe is refused in one line naming its keys, before any file is written."""
    run = tmp_path / "run"
    assert run_train(dataset, run, "--set", "max_updates=1") == 0
    files = {p.name: p.read_bytes() for p in run.iterdir()}
    capsys.readouterr()
    assert run_train(dataset, run, "--set", "max_updates=2", "--set", "lr=0.003", "--set", "batching=per_command",
                     "--resume") == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "other settings of batching, lr;" in err[0]
    assert {p.name: p.read_bytes() for p in run.iterdir()} == files
    assert run_train(dataset, run, "--set", "max_updates=2", "--set", "max_minutes=60", "--resume") == 0


def test_resume_from_a_weights_only_checkpoint_is_refused_in_one_line(dataset, tmp_path, capsys):
    """model.pt (like best.pt and step_N.pt) holds no optimizer, batch position or RNGs: put in
    last.pt's place it is named, not a KeyError."""
    run = tmp_path / "run"
    assert run_train(dataset, run, "--set", "max_updates=2", "--set", "max_dev_examples=8") == 0
    (run / "last.pt").write_bytes((run / "model.pt").read_bytes())
    (run / "last.prev.pt").unlink(missing_ok=True)
    lines = (run / "metrics.jsonl").read_text().splitlines()
    (run / "metrics.jsonl").write_text("\n".join(line for line in lines if '"end"' not in line) + "\n")
    capsys.readouterr()
    assert run_train(dataset, run, "--set", "max_updates=4", "--resume") == 1
    (err,) = capsys.readouterr().err.strip().splitlines()
    assert "last.pt holds weights only (no optimizer, cursor, rng, best_dev_exact_match)" in err


def test_a_damaged_last_checkpoint_resumes_from_the_one_before(dataset, tmp_path, caplog):
    """Each save of last.pt keeps the one before as last.prev.pt; a last.pt cut short (a crash
    the rename did not cover) resumes from it, with a warning, and trains on as straight."""
    torch.set_num_threads(1)
    straight, damaged = tmp_path / "straight", tmp_path / "damaged"
    for run in (straight, damaged):
        assert run_train(dataset, run, "--set", "max_updates=4", "--set", "seed=5") == 0
    assert read_checkpoint(damaged / "last.prev.pt")["step"] == 2
    data = (damaged / "last.pt").read_bytes()
    (damaged / "last.pt").write_bytes(data[: len(data) // 2])
    lines = (damaged / "metrics.jsonl").read_text().splitlines()  # the crash came before the end record
    (damaged / "metrics.jsonl").write_text("\n".join(line for line in lines if '"end"' not in line) + "\n")
    assert run_train(dataset, damaged, "--set", "max_updates=4", "--set", "seed=5", "--resume") == 0
    assert any("last.prev.pt, the checkpoint before it" in r.getMessage() for r in caplog.records)
    weights = [read_checkpoint(run / "last.pt")["state_dict"] for run in (straight, damaged)]
    assert all(torch.equal(weights[1][k], v) for k, v in weights[0].items())


def recording_saves(monkeypatch, stop_at: str | None = None) -> list:
    """(file name, update) of every checkpoint the trainer saves, in order; a KeyboardInterrupt
    instead of the first save of `stop_at`."""
    import gscan_ros.training.trainer as trainer

    saves, save = [], trainer.save_checkpoint

    def recorded(path, ckpt, **kwargs):
        if Path(path).name == stop_at:
            raise KeyboardInterrupt
        saves.append((Path(path).name, ckpt["step"]))
        save(path, ckpt, **kwargs)

    monkeypatch.setattr(trainer, "save_checkpoint", recorded)
    return saves


def test_best_pt_is_written_after_the_resume_point_of_its_update(dataset, tmp_path, monkeypatch):
    torch.set_num_threads(1)
    saves = recording_saves(monkeypatch)
    assert run_train(dataset, tmp_path / "run", "--set", "max_updates=4", "--set", "validate_every=1") == 0
    bests = [i for i, (name, _) in enumerate(saves) if name == "best.pt"]
    assert bests and all(saves[i - 1] == ("last.pt", saves[i][1]) for i in bests)


def test_a_stop_between_last_and_best_leaves_a_best_pt_the_resume_writes(dataset, tmp_path, monkeypatch):
    """Stopped after last.pt and before best.pt of a new best: last.pt holds that best's
    weights, and the resume writes best.pt from it."""
    torch.set_num_threads(1)
    run = tmp_path / "run"
    recording_saves(monkeypatch, stop_at="best.pt")
    assert run_train(dataset, run, "--set", "max_updates=2") != 0
    last = read_checkpoint(run / "last.pt")
    assert (last["step"], last["best_step"]) == (2, 2) and not (run / "best.pt").exists()
    monkeypatch.undo()
    assert run_train(dataset, run, "--set", "max_updates=2", "--resume") == 0
    best = read_checkpoint(run / "best.pt")
    assert best["step"] == 2 and all(torch.equal(best["state_dict"][k], v) for k, v in last["state_dict"].items())


def test_unknown_config_key_exits_1(dataset, tmp_path, capsys):
    assert run_train(dataset, tmp_path / "r", "--set", "learning_rate=1") == 1
    assert "learning_rate" in capsys.readouterr().err


def test_a_run_is_reproduced_by_its_seed_and_by_a_resume(dataset, tmp_path):
    """The same config and seed give the same weights, whether trained in one go, again, or
    stopped at a checkpoint and resumed (the batch cursor and every RNG are restored)."""
    torch.set_num_threads(1)
    straight, again, resumed = tmp_path / "straight", tmp_path / "again", tmp_path / "resumed"
    for run in (straight, again):
        assert run_train(dataset, run, "--set", "max_updates=4", "--set", "seed=5") == 0
    assert run_train(dataset, resumed, "--set", "max_updates=2", "--set", "seed=5") == 0
    assert run_train(dataset, resumed, "--set", "max_updates=4", "--set", "seed=5", "--resume") == 0
    weights = {run: read_checkpoint(run / "last.pt")["state_dict"] for run in (straight, again, resumed)}
    for run in (again, resumed):
        assert weights[run].keys() == weights[straight].keys()
        assert all(torch.equal(weights[run][k], v) for k, v in weights[straight].items()), run.name

    def losses(run):
        return [e["loss"] for e in map(json.loads, (run / "metrics.jsonl").read_text().splitlines())
                if e["event"] == "train"]
    assert losses(again) == losses(straight) == losses(resumed)
    assert run_train(dataset, tmp_path / "other", "--set", "max_updates=4", "--set", "seed=6") == 0
    assert losses(tmp_path / "other") != losses(straight)  # the seed matters


def test_a_run_stopped_after_its_checkpoint_logs_each_update_once(dataset, tmp_path):
    """Stopped (killed) some updates after its last checkpoint: the resume trains those updates
    again and its metrics.jsonl has each of them once, as a run trained straight through."""
    torch.set_num_threads(1)
    straight, stopped = tmp_path / "straight", tmp_path / "stopped"
    assert run_train(dataset, straight, "--set", "max_updates=6", "--set", "seed=5") == 0
    assert run_train(dataset, stopped, "--set", "max_updates=3", "--set", "seed=5") == 0  # last.pt at 2
    assert read_checkpoint(stopped / "last.pt")["step"] == 3  # the end writes one too: put it back at 2
    (stopped / "last.pt").unlink()
    assert run_train(dataset, tmp_path / "at2", "--set", "max_updates=2", "--set", "seed=5") == 0
    (tmp_path / "at2" / "last.pt").rename(stopped / "last.pt")
    assert run_train(dataset, stopped, "--set", "max_updates=6", "--set", "seed=5", "--resume") == 0

    def trained(run):
        return [(e["step"], e["loss"]) for e in map(json.loads, (run / "metrics.jsonl").read_text().splitlines())
                if e["event"] == "train"]
    assert trained(stopped) == trained(straight)


def test_a_finished_run_is_not_resumed_and_one_cut_before_its_end_record_finishes_as_it_was(dataset, tmp_path,
                                                                                           capsys):
    """`--resume` of a run that finished says so and changes nothing; a run stopped after its
    last checkpoint and before its end record only writes model.pt and the end, without
    validating the last update again."""
    torch.set_num_threads(1)
    run = tmp_path / "run"
    assert run_train(dataset, run, "--set", "max_updates=2") == 0
    files = {p.name: p.read_bytes() for p in run.iterdir()}
    capsys.readouterr()
    assert run_train(dataset, run, "--set", "max_updates=2", "--resume") == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "finished at update 2 (max_updates 2); raise it to train on" in err[0]
    assert {p.name: p.read_bytes() for p in run.iterdir()} == files
    assert run_train(dataset, run, "--set", "max_updates=1", "--resume") == 1  # last.pt is past the budget
    lines = (run / "metrics.jsonl").read_text().splitlines()
    (run / "metrics.jsonl").write_text("\n".join(line for line in lines if '"end"' not in line) + "\n")
    (run / "model.pt").unlink()
    assert run_train(dataset, run, "--set", "max_updates=2", "--resume") == 0
    events = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [e["step"] for e in events if e["event"] == "validation"] == [2]
    assert [e["event"] for e in events[-2:]] == ["start", "end"] and (run / "model.pt").is_file()


def test_a_resume_on_other_data_is_refused(dataset, tmp_path, capsys):
    """The batch cursor and the best dev score mean something only on the run's own data."""
    import shutil

    run, other = tmp_path / "run", tmp_path / "other_data"
    assert run_train(dataset, run, "--set", "max_updates=1") == 0
    shutil.copytree(dataset, other)
    capsys.readouterr()
    assert run_train(other, run, "--set", "max_updates=2", "--resume") == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"trained on {dataset}, not {other}" in err[0]
    assert run_train(dataset, run, "--set", "max_updates=2", "--resume") == 0


def test_without_best_pt_a_resume_makes_the_next_validation_the_best(dataset, tmp_path):
    """best.pt lost after a resume point: the next validation's weights become best.pt, and
    the score reported as best is theirs, not the lost one's."""
    from gscan_ros.model.checkpoint import save_checkpoint

    torch.set_num_threads(1)
    run = tmp_path / "run"
    assert run_train(dataset, run, "--set", "max_updates=2") == 0
    last = dict(read_checkpoint(run / "last.pt"))
    save_checkpoint(run / "last.pt", {**last, "best_step": 1, "best_dev_exact_match": 100.0})  # best.pt was older
    (run / "best.pt").unlink()
    assert run_train(dataset, run, "--set", "max_updates=3", "--resume") == 0
    events = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    last = [e for e in events if e["event"] == "validation"][-1]
    assert last["step"] == 3 and events[-1]["best_dev_exact_match"] == last["dev_exact_match"]
    assert read_checkpoint(run / "model.pt")["step"] == 3
