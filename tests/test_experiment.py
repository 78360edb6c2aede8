"""`gscan-ros experiment` and `gscan-ros report`: a plan of tiny runs is trained,
evaluated, skipped when done, resumed when killed, shared between workers; the report
puts mean ± std over seeds beside the paper's figures, reproducibly."""
import dataclasses
import json
import os
import re
import socket
import subprocess
import sys
import threading
from dataclasses import replace
from pathlib import Path

import pytest
import yaml
from experiment_support import REPO, SPLITS, TINY, TINY_DATA, write_plan

from gscan_ros.cli import main
from gscan_ros.data.dataset import read_header
from gscan_ros.data.io import DATASET_MANIFEST
from gscan_ros.experiments.locks import FileLock
from gscan_ros.experiments.paper_figures import TABLE1, TABLE2
from gscan_ros.experiments.plan import DataRecipe, PlanError, load_plan, resolve_config
from gscan_ros.experiments.runner import Runner, augment_base
from gscan_ros.experiments.state import (
    ExperimentError,
    RunState,
    config_changes,
    run_state,
    seconds_per_update,
    training_left,
    work_order,
)
from gscan_ros.outputs import PARTIAL
from gscan_ros.runtime import MKL_SHIM, available_cpus, mkl_shim_env
from gscan_ros.training.failures import FAILURE_KINDS
from gscan_ros.user_files import file_sha256


def experiment(plan: Path, *extra: str) -> int:
    return main(["experiment", str(plan), "--quiet", *extra])


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """The two-run plan, run once (in parallel where two CPUs are available)."""
    root = tmp_path_factory.mktemp("experiment")
    plan = write_plan(root / "plan.yaml", root)
    assert experiment(plan, "--parallel", str(min(2, available_cpus()))) == 0
    return root, plan


@pytest.mark.slow
def test_runner_generates_trains_and_evaluates_every_run(trained):
    root, _ = trained
    (data,) = (root / "data").iterdir()
    assert (data / "recipe.json").is_file() and (data / "train" / "metadata.yaml").is_file()
    assert (data / "generate.log").read_text().count("gscan-ros generate") == 1  # once for both runs
    # semantic decodes the plan's evaluation.max_examples, state its own max_eval_examples
    for name, column, decoded in (("semantic_s0", "semantic", 5), ("state_s0", "state", 3)):
        run = root / "results" / name
        results = json.loads((run / "results.json").read_text())
        assert results["column"] == column and results["seed"] == 0 and results["updates"] == 2
        assert set(results["splits"]) == set(SPLITS) and results["evaluation"]["max_examples"] == decoded
        assert results["splits"]["test"]["examples"] == decoded and results["data"]["k_shot"] == 1
        assert yaml.safe_load((run / "config.yaml").read_text())["seed"] == 0
        assert not (run / ".lock").exists() and not (run / ".evaluation").exists()
    state = yaml.safe_load((root / "results/state_s0/config.yaml").read_text())
    assert state["model"]["message"] == "state"
    # the trainings started as mkl_shim_env says (on AMD CPUs with the shim built: preloaded)
    start = json.loads((root / "results/semantic_s0/metrics.jsonl").read_text().splitlines()[0])
    assert start["event"] == "start" and start["mkl_shim"] == (MKL_SHIM in mkl_shim_env().get("LD_PRELOAD", ""))
    assert start["data"] == str(data)  # the folder it trained on, for the runner to compare with the plan's


@pytest.mark.slow
def test_rerun_skips_finished_runs_and_resumes_a_killed_one(trained, capsys):
    root, plan = trained
    killed, finished = root / "results/semantic_s0", root / "results/state_s0"
    lines = (killed / "metrics.jsonl").read_text().splitlines()
    assert json.loads(lines[-1])["event"] == "end"
    (killed / "metrics.jsonl").write_text("\n".join(lines[:-1]) + "\n")  # killed after its last checkpoint
    before = {p: p.stat().st_mtime_ns for p in finished.iterdir()}
    capsys.readouterr()
    assert experiment(plan, "--dry-run") == 0
    status = capsys.readouterr().out
    assert re.search(r"resume\s+semantic_s0\s+2/2", status) and re.search(r"done\s+state_s0", status)
    assert experiment(plan) == 0
    assert {p: p.stat().st_mtime_ns for p in finished.iterdir()} == before
    events = [json.loads(line) for line in (killed / "metrics.jsonl").read_text().splitlines()]
    assert [e["resumed"] for e in events if e["event"] == "start"] == [False, True]
    assert events[-1]["event"] == "end" and json.loads((killed / "results.json").read_text())["updates"] == 2
    out = capsys.readouterr().out
    assert "train semantic_s0 (resume, from its last checkpoint, updates logged to 2 of 2)" in out
    assert "2 done, 0 failed, 0 left to others or stale" in out


@pytest.mark.slow
def test_changed_recipe_marks_runs_stale_and_leaves_them(trained, tmp_path, capsys):
    root, _ = trained
    plan = write_plan(tmp_path / "plan.yaml", root, defaults={**TINY, "lr": 0.003})
    before = (root / "results/state_s0/results.json").stat().st_mtime_ns
    assert experiment(plan, "--dry-run") == 0
    assert re.search(r"stale\s+state_s0 .*config changed: lr", capsys.readouterr().out)
    assert experiment(plan) == 0
    assert "0 done, 0 failed, 2 left to others or stale" in capsys.readouterr().out
    assert (root / "results/state_s0/results.json").stat().st_mtime_ns == before


def test_report_with_its_plan_marks_the_cells_of_runs_the_plan_retrains(trained, tmp_path, capsys):
    """The tables show a stale run's numbers until its retrain lands: with --plan its cells
    are marked and the note says why, as `experiment --dry-run` does."""
    root, plan = trained
    changed = write_plan(tmp_path / "plan.yaml", root, runs=[
        {"name": "semantic", "config": str(REPO / "configs/semantic.yaml"), "data": "tiny", "seeds": [0],
         "splits": SPLITS},
        {"name": "state", "config": str(REPO / "configs/semantic.yaml"), "data": "tiny", "seeds": [0],
         "splits": SPLITS, "set": {"model.message": "state", "model.rnn_dim": 40}, "max_eval_examples": 3}])
    out = tmp_path / "t.md"
    assert report([root / "results"], out, "--no-curves", "--plan", str(changed)) == 0
    text = out.read_text()
    assert "- `state_s0` (State): config changed: model.rnn_dim." in text
    (row_a,) = [line for line in text.split("## Table 1")[1].splitlines() if line.startswith("| A |")]
    assert row_a.endswith("| 0.00<br>paper 96.73 ± 0.58 |")  # Semantic: as planned, unmarked
    assert row_a.split(" | ")[1].endswith(" †")  # State
    assert report([root / "results"], tmp_path / "same.md", "--no-curves", "--plan", str(plan)) == 0
    assert "†" not in (tmp_path / "same.md").read_text()


@pytest.mark.slow
def test_a_run_whose_checkpoints_were_lost_starts_over_keeping_the_earlier_attempt(trained, capsys):
    root, plan = trained
    run = root / "results/semantic_s0"
    lines = (run / "metrics.jsonl").read_text().splitlines()
    (run / "metrics.jsonl").write_text("\n".join(lines[:-1]) + "\n")  # killed, and then the machine was replaced
    for checkpoint in run.glob("*.pt"):
        checkpoint.unlink()
    earlier = {name: (run / name).read_bytes() for name in ("metrics.jsonl", "config.yaml", "results.json")}
    capsys.readouterr()
    assert experiment(plan, "--dry-run") == 0
    assert re.search(r"new\s+semantic_s0\s+2/2\s+no last.pt: starts over, these logged updates kept in .replaced/",
                     capsys.readouterr().out)
    assert experiment(plan) == 0
    (archive,) = (run / ".replaced").iterdir()
    assert archive.name.endswith("_2upd")
    assert {name: (archive / name).read_bytes() for name in earlier} == earlier
    events = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [e["resumed"] for e in events if e["event"] == "start"] == [False] and events[-1]["event"] == "end"
    assert json.loads((run / "results.json").read_text())["updates"] == 2
    assert f"the earlier attempt's files moved to {archive}" in capsys.readouterr().out


@pytest.mark.slow
def test_a_stale_run_retrains_beside_its_old_results_which_stay_until_the_retrain_is_evaluated(
        trained, tmp_path, monkeypatch, capsys):
    import shutil

    root, _ = trained
    shutil.copytree(root / "data", tmp_path / "data")
    shutil.copytree(root / "results/state_s0", tmp_path / "results/state_s0")
    run = tmp_path / "results/state_s0"
    old = {name: (run / name).read_bytes() for name in ("results.json", "metrics.jsonl", "config.yaml")}
    runs = [{"name": "state", "config": str(REPO / "configs/semantic.yaml"), "data": "tiny", "seeds": [0],
             "splits": SPLITS, "set": {"model.message": "state"}, "max_eval_examples": 3}]
    plan = write_plan(tmp_path / "plan.yaml", tmp_path, defaults={**TINY, "lr": 0.003}, runs=runs)

    def stopped_before_evaluation(*args, **kwargs):
        raise ExperimentError("stopped")

    monkeypatch.setattr(Runner, "_evaluate", stopped_before_evaluation)
    assert experiment(plan, "--restart-stale") == 1
    # trained in .retrain/; the stale run's files (and its column in the report) are untouched
    assert {name: (run / name).read_bytes() for name in old} == old
    assert json.loads((run / ".retrain/metrics.jsonl").read_text().splitlines()[-1])["event"] == "end"
    assert "train state_s0 (stale, in .retrain/, from update 0 of 2)" in capsys.readouterr().out
    assert experiment(plan, "--dry-run") == 0
    assert re.search(r"evaluate\s+state_s0\s+2/2\s+retrain in .retrain/; the stale run's results stay",
                     capsys.readouterr().out)
    monkeypatch.undo()
    assert experiment(plan) == 0  # a retrain under way goes on without --restart-stale
    (archive,) = (run / ".replaced").iterdir()
    assert {name: (archive / name).read_bytes() for name in old} == old
    assert not (run / ".retrain").exists() and not (run / ".promoting").exists()
    assert yaml.safe_load((run / "config.yaml").read_text())["lr"] == 0.003
    assert json.loads((run / "results.json").read_text())["updates"] == 2 and (run / "model.pt").is_file()
    assert f"state_s0: retrained; the stale run's files moved to {archive}" in capsys.readouterr().out
    assert experiment(plan, "--dry-run") == 0
    assert re.search(r"done\s+state_s0", capsys.readouterr().out)


@pytest.mark.slow
def test_an_evaluation_finished_before_a_stop_is_kept_only_for_the_same_weights(trained, tmp_path, monkeypatch):
    """A runner stopped between `evaluate` and writing results.json keeps the scratch
    results of that model.pt; results of other weights are decoded again."""
    import hashlib
    import shutil

    root, _ = trained
    shutil.copytree(root / "data", tmp_path / "data")
    shutil.copytree(root / "results/semantic_s0", tmp_path / "results/semantic_s0")
    run, (data,) = tmp_path / "results/semantic_s0", (tmp_path / "data").iterdir()
    plan = write_plan(tmp_path / "plan.yaml", tmp_path, runs=[
        {"name": "semantic", "config": str(REPO / "configs/semantic.yaml"), "data": "tiny", "seeds": [0],
         "splits": SPLITS}])
    done = json.loads((run / "results.json").read_text())
    (run / "results.json").unlink()  # stopped after the evaluation, before results.json
    assert main(["evaluate", "--checkpoint", str(run / "model.pt"), "--data", str(data), "--splits", *SPLITS,
                 "--out", str(run / ".evaluation"), "--quiet", "--no-predictions", "--max-examples", "5"]) == 0
    scratch = json.loads((run / ".evaluation/results.json").read_text())
    calls = []
    real_call = Runner._call
    monkeypatch.setattr(Runner, "_call", lambda self, cmd, *a, **k: (calls.append(cmd), real_call(self, cmd, *a, **k)))
    assert experiment(plan) == 0
    assert not any("evaluate" in cmd for cmd in calls)
    kept = json.loads((run / "results.json").read_text())
    assert kept["splits"] == scratch["splits"] == done["splits"]
    digest = hashlib.sha256((run / "model.pt").read_bytes()).hexdigest()  # results.json names the weights
    assert kept["evaluation"]["checkpoint_sha256"] == scratch["checkpoint_sha256"] == digest
    assert done["evaluation"]["checkpoint_sha256"] == digest
    assert not (run / ".evaluation").exists()

    (run / "results.json").unlink()  # the same stop, but the scratch scores other weights
    (run / ".evaluation").mkdir()
    (run / ".evaluation/results.json").write_text(json.dumps({**scratch, "checkpoint_sha256": "0" * 64}))
    assert experiment(plan) == 0
    assert sum("evaluate" in cmd for cmd in calls) == 1
    assert json.loads((run / "results.json").read_text())["splits"] == done["splits"]


def test_a_promotion_cut_short_finishes_without_archiving_the_retrained_files(tmp_path, monkeypatch):
    from gscan_ros.experiments import state

    run = tmp_path / "run"
    (run / ".retrain").mkdir(parents=True)
    for name in ("metrics.jsonl", "results.json"):
        (run / name).write_text(f"old {name}")
        (run / ".retrain" / name).write_text(f"new {name}")
    moved, replace = [], os.replace

    def power_cut_after_one_move(src, dst):
        if moved:
            raise KeyboardInterrupt
        moved.append(src)
        replace(src, dst)

    monkeypatch.setattr(state.os, "replace", power_cut_after_one_move)
    with pytest.raises(KeyboardInterrupt):
        state.promote_retrain(run)
    monkeypatch.undo()
    assert (run / ".promoting").exists()
    assert state.promote_retrain(run) is None  # finishes the move; archives nothing more
    assert {p.name: p.read_text() for p in run.iterdir() if p.is_file()} == {
        "metrics.jsonl": "new metrics.jsonl", "results.json": "new results.json"}
    (archive,) = (run / ".replaced").iterdir()
    assert {p.name: p.read_text() for p in archive.iterdir()} == {
        "metrics.jsonl": "old metrics.jsonl", "results.json": "old results.json"}


GECA_TINY = {**TINY, "model": {"hidden": 8, "embedding_dim": 8, "cnn_channels": 4}}
GECA_DATA = {**TINY_DATA, "augment": "geca"}


def write_geca_plan(root: Path, **data) -> Path:
    runs = [{"name": "geca", "config": str(REPO / "configs/geca.yaml"), "data": "tiny", "seeds": [0],
             "splits": SPLITS}]
    return write_plan(root / "plan.yaml", root, defaults=GECA_TINY, runs=runs, data={**GECA_DATA, **data})


@pytest.mark.slow
@pytest.mark.parametrize("keep", [False, True, ["visual"]], ids=["held-out kinds dropped", "kept", "visual kept"])
def test_runner_augments_the_generated_dataset_and_trains_on_it(tmp_path, keep):
    assert experiment(write_geca_plan(tmp_path, **({"keep_held_out": keep} if keep else {}))) == 0
    (data,) = (tmp_path / "data").iterdir()  # the base dataset's scratch folder is gone
    assert sorted(p.name for p in data.iterdir()) == ["dataset.txt", "generate.log", "recipe.json"]
    base, log = augment_base(data), (data / "generate.log").read_text()
    assert f"gscan-ros generate --out {base} --split-kind compositional --seed 0 --format mcap --examples 300" in log
    flag = "".join(f" {word}" for word in ["--keep-held-out", *(keep if isinstance(keep, list) else [])] if keep)
    assert f"gscan-ros augment --data {base} --out {data} --method geca --seed 0{flag} --quiet\n" in log
    augmentation = read_header(data / "dataset.txt").extra["gscan_ros"]["augmentation"]
    assert augmentation["keep_held_out"] == (augmentation["held_out"] if keep is True else keep or [])
    base_train, train = augmentation["train_indices"]
    assert train > base_train
    run = tmp_path / "results/geca_s0"
    start = json.loads((run / "metrics.jsonl").read_text().splitlines()[0])
    assert start["event"] == "start" and start["train_examples"] == train  # the augmented train split
    results = json.loads((run / "results.json").read_text())
    assert (results["data"]["augment"], results["data"]["augment_seed"], results["data"]["keep_held_out"],
            results["data"]["dir"]) == ("geca", 0, keep, str(data))
    assert set(results["splits"]) == set(SPLITS) and results["splits"]["test"]["examples"] == 5
    assert json.loads((data / "recipe.json").read_text())["augment"] == "geca"


@pytest.mark.slow
@pytest.mark.parametrize("base_finished", [True, False], ids=["killed augmenting", "killed generating the base"])
def test_an_interrupted_augmented_dataset_is_finished_from_its_base(tmp_path, base_finished):
    plan = load_plan(write_geca_plan(tmp_path))
    recipe = plan.datasets["tiny"]
    data = recipe.directory(plan.data_root)
    base = augment_base(data)
    assert main(["generate", "--out", str(base), *recipe.flags(), "--quiet"]) == 0
    if not base_finished:  # killed while its bags were moved in: the manifest comes last
        (base / DATASET_MANIFEST).unlink()
    gone = subprocess.Popen(["true"])
    gone.wait()
    (data / f".augment{PARTIAL}{gone.pid}").mkdir(parents=True)  # the killed augment's scratch
    (data / "generate.log").write_text("# the interrupted start\n")
    assert Runner(plan, progress=False, echo=lambda line: None)._dataset(recipe) == data
    commands = [line for line in (data / "generate.log").read_text().splitlines() if line.startswith("# 2")]
    generated = [] if base_finished else [f"gscan-ros generate --out {base} {' '.join(recipe.flags())} "
                                          "--workers 1 --quiet --overwrite"]
    assert [c.split(" ", 3)[3] for c in commands] == generated + [
        f"gscan-ros augment --data {base} --out {data} --method geca --seed 0 --quiet --overwrite"]
    assert sorted(p.name for p in data.iterdir()) == ["dataset.txt", "generate.log", "recipe.json"]
    assert not base.exists() and read_header(data / "dataset.txt").extra["gscan_ros"]["augmentation"]["seed"] == 0


def test_augment_keys_give_the_dataset_a_folder_of_its_own():
    folders = {name: recipe.directory(Path("d")).name
               for name, recipe in load_plan(REPO / "configs/experiments/paper.yaml").datasets.items()}
    # the folders the plan's datasets had before there was `augment`: not regenerated
    assert {name: folder for name, folder in folders.items() if not name.startswith("compositional_geca")} == {
        "compositional": "compositional-cd3ca4a4", "kshot5": "kshot5-ab3d43cd", "kshot10": "kshot10-585800e1",
        "kshot50": "kshot50-1b0ba1e4", "length": "length-c3a26e31"}
    assert folders["compositional_geca"] == "compositional_geca-a793018d"  # as before `keep_held_out`
    plain, geca = DataRecipe("x", seed=3), DataRecipe("x", seed=3, augment="geca")
    assert geca.augment_seed == 3 and geca.directory(Path("d")) == replace(geca, augment_seed=3).directory(Path("d"))
    kept, visual = replace(geca, keep_held_out=True), replace(geca, keep_held_out=("visual",))
    assert kept.augment_flags() == ["--method", "geca", "--seed", "3", "--keep-held-out"]
    assert visual.augment_flags() == ["--method", "geca", "--seed", "3", "--keep-held-out", "visual"]
    assert "--keep-held-out" not in geca.augment_flags()
    assert len({r.directory(Path("d")) for r in (plain, geca, replace(geca, augment_seed=4), kept, visual)}) == 5


@pytest.mark.parametrize(("dataset", "message"), [
    ({"keep_held_out": True}, "keep_held_out needs datasets.tiny.augment"),
    ({"augment": "geca", "keep_held_out": "yes"}, "keep_held_out has the wrong type"),
    ({"augment": "geca", "keep_held_out": ["visual", "bogus"]},
     r"datasets.tiny.keep_held_out bogus: not a hold-out split of any dataset \(those are: adverb_1, "),
    ({"augment": "geca", "keep_held_out": []}, "keep_held_out must be true, false or a list"),
    ({"augment": "geca", "seed": True}, "seed has the wrong type")])
def test_bad_augment_keys_are_refused_by_name(tmp_path, dataset, message):
    path = write_plan(tmp_path / "plan.yaml", tmp_path, data={**TINY_DATA, **dataset})
    with pytest.raises(PlanError, match=message):
        load_plan(path)


def test_a_live_lock_means_running_and_a_dead_one_is_stale(tmp_path, capsys):
    plan = write_plan(tmp_path / "plan.yaml", tmp_path)
    live, dead = tmp_path / "results/semantic_s0", tmp_path / "results/state_s0"
    gone = subprocess.Popen(["true"])
    gone.wait()
    for run, pid in ((live, os.getpid()), (dead, gone.pid)):
        run.mkdir(parents=True)
        (run / ".lock").write_text(json.dumps({"host": socket.gethostname(), "pid": pid, "child": None}))
    assert experiment(plan, "--dry-run") == 0
    out = capsys.readouterr().out
    assert re.search(rf"running\s+semantic_s0 .*pid {os.getpid()}", out) and re.search(r"new\s+state_s0", out)


def test_two_runners_never_both_take_a_stale_lock(tmp_path, monkeypatch):
    """Taking over a dead holder's lock happens under the flock: a second runner that finds
    the same stale lock between the first one's check and its taking it is refused."""
    gone = subprocess.Popen(["true"])
    gone.wait()
    path = tmp_path / ".lock"
    path.write_text(json.dumps({"host": socket.gethostname(), "pid": gone.pid, "child": None}))
    first, second, taken = FileLock(path), FileLock(path), []
    holder = FileLock.holder

    def second_runner_meanwhile(lock):
        found = holder(lock)
        if lock is first and not taken:
            runner = threading.Thread(target=lambda: taken.append(second.acquire()))
            runner.start()
            runner.join()
        return found

    monkeypatch.setattr(FileLock, "holder", second_runner_meanwhile)
    assert [first.acquire(), *taken] == [True, False]
    assert json.loads(path.read_text())["pid"] == os.getpid()
    first.release()
    assert not path.exists() and second.acquire()
    second.release()


def test_a_killed_holders_lock_is_free_and_an_older_runners_record_holds(tmp_path):
    """The kernel drops a killed holder's flock; a record that names a live process, as
    runners before the flock wrote it (and as a runner's training child outliving it leaves
    it), still holds the lock."""
    path = tmp_path / ".lock"
    hold = ("import time\nfrom gscan_ros.experiments.locks import FileLock\n"
            f"assert FileLock({str(path)!r}).acquire()\nprint(flush=True)\ntime.sleep(60)")
    holder = subprocess.Popen([sys.executable, "-c", hold], stdout=subprocess.PIPE, text=True)
    holder.stdout.readline()
    assert not FileLock(path).acquire() and FileLock(path).holder()["pid"] == holder.pid
    holder.kill()
    holder.wait()
    lock = FileLock(path)
    assert lock.acquire()
    lock.release()
    path.write_text(json.dumps({"host": socket.gethostname(), "pid": os.getpid(), "started": None, "child": None}))
    assert not FileLock(path).acquire() and path.exists()


def test_a_run_whose_last_checkpoint_was_lost_in_its_save_resumes_from_the_one_before(tmp_path, capsys):
    plan = write_plan(tmp_path / "plan.yaml", tmp_path)
    run = tmp_path / "results/semantic_s0"
    run.mkdir(parents=True)
    (run / "metrics.jsonl").write_text(json.dumps({"event": "train", "step": 1, "loss": 1.0}) + "\n")
    (run / "last.prev.pt").write_bytes(b"")  # a crash between the two renames of a save left no last.pt
    assert experiment(plan, "--dry-run") == 0
    assert re.search(r"resume\s+semantic_s0\s+1/2\s*$", capsys.readouterr().out, re.M)


@pytest.mark.parametrize("recorded_in, finished, status", [
    ("results", True, "stale"),  # evaluated on another folder
    ("start", True, "stale"),  # trained on another folder
    ("start", False, "stale"),  # half trained on another folder: not resumed on the plan's
    (None, True, "done"),  # a run that names no folder (before the `start` records did) keeps its state
    (None, False, "resume"),
])
def test_a_run_on_another_dataset_folder_is_stale(tmp_path, recorded_in, finished, status):
    plan = load_plan(write_plan(tmp_path / "plan.yaml", tmp_path))
    spec = plan.runs[0]
    cfg = resolve_config(plan, spec)
    trained_on = replace(spec.data, seed=7).directory(plan.data_root)  # the recipe changed since
    run = tmp_path / "results" / spec.name
    run.mkdir(parents=True)
    (run / "config.yaml").write_text(yaml.safe_dump(cfg.to_dict()))
    start = {"event": "start", "step": 0, **({"data": str(trained_on)} if recorded_in == "start" else {})}
    end = [{"event": "end", "step": cfg.max_updates}] if finished else []
    (run / "metrics.jsonl").write_text("".join(json.dumps(e) + "\n" for e in [start, *end]))
    (run / "last.pt").write_bytes(b"")
    (run / "model.pt").write_bytes(b"")
    (run / "results.json").write_text(json.dumps({
        "updates": cfg.max_updates, "evaluation": {"splits": list(spec.splits), "max_examples": spec.eval_max_examples},
        "data": {"dir": str(trained_on)} if recorded_in == "results" else {}}))
    state = run_state(run, spec, cfg, plan.data_root)
    assert state.status == status
    if status == "stale":
        assert state.detail == f"data changed: {trained_on.name} -> {spec.data.directory(plan.data_root).name}"


def _finished_run(tmp_path):
    """(plan, spec, cfg, run folder) of a run whose training ended, with nothing else."""
    plan = load_plan(write_plan(tmp_path / "plan.yaml", tmp_path))
    spec = plan.runs[0]
    cfg = resolve_config(plan, spec)
    run = tmp_path / "results" / spec.name
    run.mkdir(parents=True)
    (run / "config.yaml").write_text(yaml.safe_dump(cfg.resolved()))
    (run / "metrics.jsonl").write_text("".join(json.dumps(e) + "\n" for e in [
        {"event": "start", "step": 0}, {"event": "end", "step": cfg.max_updates}]))
    return plan, spec, cfg, run


def _results_of(spec, cfg, **evaluation) -> str:
    return json.dumps({"updates": cfg.max_updates, "data": {}, "evaluation": {
        "splits": list(spec.splits), "max_examples": spec.eval_max_examples, **evaluation}})


def test_a_finished_run_without_its_weights_is_stale(tmp_path):
    """A run whose model.pt is gone has numbers nobody can re-check, or none at all: the
    plan retrains it (`--restart-stale`), its old results kept until the retrain is evaluated."""
    plan, spec, cfg, run = _finished_run(tmp_path)
    state = run_state(run, spec, cfg, plan.data_root)
    assert (state.status, state.detail) == ("stale", "no weights (model.pt) to evaluate")
    (run / "results.json").write_text(_results_of(spec, cfg))
    state = run_state(run, spec, cfg, plan.data_root)
    assert (state.status, state.detail) == ("stale", "no weights (model.pt) to re-check its results")
    (run / "model.pt").write_bytes(b"")
    assert run_state(run, spec, cfg, plan.data_root).status == "done"


def test_a_finished_run_under_a_raised_budget_without_its_training_state_is_stale(tmp_path):
    """Committed runs keep model.pt, not last.pt: a larger max_updates cannot resume them,
    and training them again from update 0 would replace their results, so it waits for
    --restart-stale instead of running as `new`."""
    plan, spec, cfg, run = _finished_run(tmp_path)
    (run / "model.pt").write_bytes(b"")
    (run / "results.json").write_text(_results_of(spec, cfg))
    assert run_state(run, spec, cfg, plan.data_root).status == "done"
    more = dataclasses.replace(cfg, max_updates=cfg.max_updates * 2)
    state = run_state(run, spec, more, plan.data_root)
    assert (state.status, state.detail) == (
        "stale", f"trained to {cfg.max_updates} of {more.max_updates} updates, without the training state (last.pt) "
                 "to go on from")
    (run / "last.pt").write_bytes(b"")  # with it, the run trains on
    assert run_state(run, spec, more, plan.data_root).status == "resume"


def test_an_archived_attempt_takes_its_analyses_along(tmp_path):
    """Files written beside a run (an analysis of its weights) go with the attempt they are of."""
    from gscan_ros.experiments.state import archive_attempt

    plan, spec, cfg, run = _finished_run(tmp_path)
    (run / "think_accuracy.json").write_text("{}")
    (run / ".lock").write_text("")
    archive = archive_attempt(run)
    assert sorted(p.name for p in archive.iterdir()) == ["config.yaml", "metrics.jsonl", "think_accuracy.json"]
    assert sorted(p.name for p in run.iterdir()) == [".lock", ".replaced"]


def test_a_done_run_takes_the_labels_the_plan_gives_it_now(tmp_path, capsys):
    """A column renamed in the plan reaches the report without retraining: the runner
    writes the plan's labels into a done run's results.json (and --dry-run changes nothing)."""
    plan, spec, cfg, run = _finished_run(tmp_path)
    (run / "model.pt").write_bytes(b"")
    (run / "results.json").write_text(json.dumps({**json.loads(_results_of(spec, cfg)), "title": "Old name",
                                                  "column": spec.column, "paper_column": spec.paper_column}))
    path = write_plan(tmp_path / "plan.yaml", tmp_path, runs=[
        {"name": "semantic", "config": str(REPO / "configs/semantic.yaml"), "data": "tiny", "seeds": [0],
         "splits": SPLITS, "title": "Semantic, renamed"}])
    assert experiment(path, "--dry-run") == 0
    assert json.loads((run / "results.json").read_text())["title"] == "Old name"
    assert experiment(path) == 0
    assert json.loads((run / "results.json").read_text())["title"] == "Semantic, renamed"
    assert "semantic_s0: labels set from the plan (column 'semantic', title 'Semantic, renamed')" in \
        capsys.readouterr().out


def test_results_of_other_weights_are_evaluated_again(tmp_path):
    """A run retrained by hand (`train --overwrite`) to the same update count keeps the old
    results.json; the weights' digest recorded in it tells them apart."""
    plan, spec, cfg, run = _finished_run(tmp_path)
    (run / "model.pt").write_bytes(b"the retrained weights")
    (run / "results.json").write_text(_results_of(spec, cfg, checkpoint_sha256=file_sha256(run / "model.pt")))
    assert run_state(run, spec, cfg, plan.data_root).status == "done"
    (run / "model.pt").write_bytes(b"weights trained again")
    assert run_state(run, spec, cfg, plan.data_root).status == "evaluate"


def test_a_start_without_a_checkpoint_is_new_and_says_it_starts_over(tmp_path, capsys):
    plan = write_plan(tmp_path / "plan.yaml", tmp_path)
    run = tmp_path / "results/semantic_s0"
    run.mkdir(parents=True)
    (run / "metrics.jsonl").write_text(json.dumps({"event": "train", "step": 1, "loss": 1.0}) + "\n")
    assert experiment(plan, "--dry-run") == 0
    out = capsys.readouterr().out
    assert re.search(r"new\s+semantic_s0\s+1/2\s+no last.pt: starts over, these logged updates kept", out)
    assert re.search(r"new\s+state_s0\s+0/2\s*$", out, re.M)


def test_workers_partition_the_plan_in_seed_rounds(tmp_path, capsys):
    config = str(REPO / "configs/semantic.yaml")
    runs = [{"name": "a", "config": config, "data": "tiny", "seeds": [0, 1, 2]},
            {"name": "b", "config": config, "data": "tiny", "seeds": [5, 6]}]
    plan = load_plan(write_plan(tmp_path / "plan.yaml", tmp_path, runs=runs))
    assert [r.name for r in plan.runs] == ["a_s0", "b_s5", "a_s1", "b_s6", "a_s2"]
    shares = [[r.name for r in plan.share((i, 2))] for i in range(2)]
    assert shares == [["a_s0", "a_s1", "a_s2"], ["b_s5", "b_s6"]]
    assert experiment(tmp_path / "plan.yaml", "--dry-run", "--worker", "1/2") == 0
    out = capsys.readouterr().out
    assert out.startswith("worker 1/2:") and "2 runs: 0 done, 0 running, 2 left" in out and "a_s0" not in out
    # A job array wider than the plan: the workers left without a run say so and succeed.
    for args in (("--dry-run", "--worker", "7/8"), ("--worker", "7/8")):
        assert experiment(tmp_path / "plan.yaml", *args) == 0
        assert "no run of the plan's 5 falls to this worker" in capsys.readouterr().out
    assert not (tmp_path / "results").exists()


BAD_PLANS = [
    ({"results": "r", "colour": 1}, "unknown key colour"),
    ({"runs": [{"name": "x", "config": "{config}", "data": "tiny", "seeds": ["a"]}]}, "runs[0].seeds"),
    ({"runs": [{"name": "x", "config": "{config}", "data": "huge", "seeds": [0]}]}, "runs[0].data 'huge'"),
    ({"runs": [{"name": "x", "config": "{config}", "data": "tiny"}]}, "runs[0].seeds is missing"),
    ({"runs": [{"name": "x", "config": "nowhere.yaml", "data": "tiny", "seeds": [0]}]}, "runs[0].config"),
    ({"runs": [{"name": "x", "config": "{config}", "data": "tiny", "seeds": [0], "splits": ["target_lengths"]}]},
     "runs[0].splits"),
    ({"runs": [{"name": "x", "config": "{config}", "data": "tiny", "seeds": [0], "splits": ["visual", "visual"]}]},
     "runs[0].splits must be a list of distinct"),
    ({"runs": [{"name": "x", "config": "{config}", "data": "tiny", "seeds": [0], "paper": ["semantic"]}]},
     "runs[0].paper"),
    ({"datasets": {"tiny": {"k_shot": -1}}}, "datasets.tiny.k_shot"),
    ({"datasets": {"tiny": {"grid_size": 100}}}, "datasets.tiny: grid size 100 is not supported"),
    ({"datasets": {"tiny": {"percentage_dev": 1.5}}}, "datasets.tiny: percentage_train must be in (0, 1]"),
    ({"datasets": {"tiny": {"examples": "many"}}}, "datasets.tiny.examples"),
    ({"datasets": {"tiny": {"augment": "mixup"}}}, "datasets.tiny.augment"),
    ({"datasets": {"tiny": {"augment_seed": 1}}}, "datasets.tiny.augment_seed needs"),
    ({"datasets": {"tiny": {"augment": "geca", "path": "data"}}}, "a path: dataset is used as it is"),
    ({"datasets": {"tiny": {"path": "data", "examples": 5, "seed": 9}}},
     "datasets.tiny.examples, datasets.tiny.seed would generate one"),
    ({"defaults": {"seed": 3}}, "defaults.seed"),
    ({"defaults": {"learning_rate": 3}}, "learning_rate"),
    ({"runs": [{"name": "x", "config": "{config}", "data": "tiny", "seeds": [0], "set": {"model.rnn_dim": -1}}]},
     "run x_s0"),
    ({"runs": [{"name": "x", "config": "{config}", "data": "tiny", "seeds": [0], "max_eval_examples": -5}]},
     "runs[0].max_eval_examples"),
    ({"results": "{config}"}, "results must be a folder"),
    ({"results": "{config}/runs"}, "results must be a folder, but"),
    ({"data_root": "{config}"}, "data_root must be a folder"),
]


@pytest.mark.parametrize("edit, names", BAD_PLANS, ids=[n for _, n in BAD_PLANS])
def test_bad_plan_is_one_line_naming_the_key(tmp_path, capsys, edit, names):
    path = write_plan(tmp_path / "plan.yaml", tmp_path)
    plan = yaml.safe_load(path.read_text())
    text = yaml.safe_dump({**plan, **edit}).replace("{config}", str(REPO / "configs/semantic.yaml"))
    path.write_text(text)
    assert experiment(path, "--dry-run") == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and names in err[0] and err[0].startswith("gscan-ros experiment: error: plan")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["plan.yaml"]


def test_work_order_finishes_trained_runs_before_training_others(tmp_path):
    specs = load_plan(write_plan(tmp_path / "plan.yaml", tmp_path, runs=[
        {"name": f"r{i}", "config": str(REPO / "configs/semantic.yaml"), "data": "tiny", "seeds": [0],
         "splits": SPLITS} for i in range(5)])).runs
    statuses = ["new", "resume", "done", "evaluate", "resume"]
    order = work_order([RunState(spec, status, 0, 2) for spec, status in zip(specs, statuses)])
    assert [(st.spec.name, st.status) for st in order] == [
        ("r2_s0", "done"), ("r3_s0", "evaluate"), ("r1_s0", "resume"), ("r4_s0", "resume"), ("r0_s0", "new")]


def test_training_left_uses_each_runs_rate_then_its_entrys_then_its_recipes(tmp_path):
    semantic, seq2seq = str(REPO / "configs/semantic.yaml"), str(REPO / "configs/seq2seq.yaml")
    specs = load_plan(write_plan(tmp_path / "plan.yaml", tmp_path, runs=[
        {"name": "a", "config": semantic, "data": "tiny", "seeds": [0, 1], "splits": SPLITS},
        {"name": "b", "config": semantic, "data": "tiny", "seeds": [0], "splits": SPLITS},
        {"name": "c", "config": seq2seq, "data": "tiny", "seeds": [0], "splits": SPLITS}])).runs
    by_name = {spec.name: spec for spec in specs}
    states = [RunState(by_name["a_s0"], "done", 100, 100, seconds_per_update=2.0),
              RunState(by_name["a_s1"], "resume", 40, 100, seconds_per_update=3.0),  # its own rate
              RunState(by_name["b_s0"], "new", 0, 100),  # no entry rate: a's, on the same recipe
              RunState(by_name["c_s0"], "new", 0, 100)]  # another config: nothing to go by
    seconds, unknown = training_left(states)
    assert seconds == 60 * 3.0 + 100 * 2.5 and unknown == ["c_s0"]
    states[1] = RunState(by_name["a_s1"], "stale", 100, 100, seconds_per_update=3.0)  # retrained from 0
    assert training_left(states)[0] == 100 * 3.0 + 100 * 2.5
    events = [{"event": "train", "examples_per_s": 100.0, "mean_batch": 50},
              {"event": "train", "examples_per_s": 50.0}, {"event": "validation"}]
    assert seconds_per_update(events, batch_size=200) == (0.5 + 4.0) / 2  # old logs: the config's batch
    assert seconds_per_update([{"event": "start"}], 50) is None


def test_only_selects_entries_or_runs_and_names_unknown_ones():
    plan = load_plan(REPO / "configs/experiments/paper.yaml")
    assert [r.name for r in plan.share(None, ("semantic_len15", "seq2seq_s0"))] == [
        "semantic_len15_s0", "semantic_len15_s1", "semantic_len15_s2", "seq2seq_s0"]
    # in the order named, so a user decides what trains next; a run named twice keeps its first place
    assert [r.name for r in plan.share(None, ("semantic_s2", "semantic", "state_s0", "semantic_s2"))] == [
        "semantic_s2", "semantic_s0", "semantic_s1", "state_s0"]
    with pytest.raises(PlanError, match="'nope'"):
        plan.share(None, ("nope",))


def test_first_takes_the_runs_it_names_before_the_seed_rounds(tmp_path):
    entries = [{"name": name, "config": str(REPO / "configs/semantic.yaml"), "data": "tiny", "seeds": [0, 1, 2],
                "splits": SPLITS} for name in ("a", "b")]
    path = write_plan(tmp_path / "plan.yaml", tmp_path, runs=entries)
    assert [r.name for r in load_plan(path).runs] == ["a_s0", "b_s0", "a_s1", "b_s1", "a_s2", "b_s2"]
    doc = yaml.safe_load(path.read_text())
    path.write_text(yaml.safe_dump({**doc, "first": ["a_s2", "b"]}))
    runs = load_plan(path).runs
    assert [r.name for r in runs] == ["a_s2", "b_s0", "b_s1", "b_s2", "a_s0", "a_s1"]
    assert [r.index for r in runs] == list(range(6))  # worker shares follow the new order
    path.write_text(yaml.safe_dump({**doc, "first": ["c_s0"]}))
    with pytest.raises(PlanError, match="no run or runs\\[\\] entry named 'c_s0'"):
        load_plan(path)


def test_paper_plan_covers_every_column_with_one_recipe():
    plan = load_plan(REPO / "configs/experiments/paper.yaml")
    seeds: dict[tuple, set] = {}
    for run in plan.runs:
        seeds.setdefault((run.column, run.entry), set()).add(run.seed)
    budgets = {run.column: resolve_config(plan, run).max_updates for run in plan.runs}
    longer = {budgets.pop(column) for column in ("seq2seq_160k", "auxloss_160k", "semantic_k10_160k")}
    assert len(set(budgets.values()) - longer) == 1  # one budget, and its named variants
    columns = {column for column, _ in seeds}
    main = {"seq2seq", "geca", "auxloss", "lcgn", "state", "attention+state", "constituency", "dependency",
            "semantic"}
    assert columns == main | {"seq2seq_160k", "auxloss_160k", "auxloss_dot", "geca_keep_held_out", "geca_command_kinds",
                              "semantic_minmax", "semantic_add", "dependency_cosine",
                              "semantic_faithful", "semantic_percommand", "semantic_percommand_screened",
                              "semantic_oversample", "semantic_screened", "attention+state_screened",
                              "semantic_len15_percommand", "semantic_len15_minmax", "semantic_len15_faithful",
                              "semantic_k10_160k"}
    # One selection rule: every main-table run trains its seed as it comes; three seeds per column.
    assert all(len(s) == 3 for (column, _), s in seeds.items() if column in main | {"semantic_faithful"})
    for run in plan.runs:
        screened = resolve_config(plan, run).screen_seeds > 1
        assert screened == (run.column.endswith("_screened") or "(screened)" in run.title), run.name
    assert {r.data.k_shot for r in plan.runs if r.data.split_kind == "compositional"} == {1, 5, 11, 51}
    first = ["semantic_s0", "semantic_s1", "semantic_s2", "auxloss_s0", "lcgn_s0"]
    assert [r.name for r in plan.runs[:len(first)]] == first  # `first:` (Semantic's seeds, then the comparison systems)
    order = {entry: sorted(s) for (_, entry), s in seeds.items()}
    rounds = [order[r.entry].index(r.seed) for r in plan.runs[len(first):]]
    assert rounds == sorted(rounds)  # then seed rounds: every column's first seed before any second seed
    minmax = next(r for r in plan.runs if r.column == "semantic_minmax")
    assert resolve_config(plan, minmax).model["size_map"] == "minmax"
    faithful = resolve_config(plan, next(r for r in plan.runs if r.column == "semantic_faithful"))
    assert (faithful.batch_size, faithful.lr, faithful.lr_decay, faithful.screen_seeds) == (200, 0.001, "none", 0)
    semantic = resolve_config(plan, next(r for r in plan.runs if r.name == "semantic_s0")).to_dict()
    screened = resolve_config(plan, next(r for r in plan.runs if r.name == "semantic_screened_s0")).to_dict()
    for run in (r for r in plan.runs if r.column.startswith("semantic_percommand")):  # the batching alone differs
        base = screened if run.column.endswith("_screened") else semantic
        changed = {k for k, v in resolve_config(plan, run).to_dict().items() if base[k] != v}
        assert changed == {"batching"} and resolve_config(plan, run).batching == "per_command"
    oversample = next(r for r in plan.runs if r.column == "semantic_oversample")  # its sampling alone differs
    changed = {k for k, v in resolve_config(plan, oversample).to_dict().items() if screened[k] != v}
    assert changed == {"oversample_word", "oversample_factor"} and oversample.data.k_shot == 11
    cosine = next(r for r in plan.runs if r.column == "dependency_cosine")
    assert resolve_config(plan, cosine).model["overlap"] == "cosine" and resolve_config(plan, cosine).parser == \
        "dependency"
    seq2seq = next(r for r in plan.runs if r.name == "seq2seq_s0")
    for geca in (r for r in plan.runs if r.column == "geca"):  # the seq2seq baseline; its train split alone differs
        assert resolve_config(plan, geca).to_dict() == resolve_config(plan, seq2seq).to_dict() | {"seed": geca.seed}
        assert (geca.data.augment, geca.data.augment_seed) == ("geca", 0)
        assert replace(geca.data, name="compositional", augment=None, augment_seed=None) == seq2seq.data


# ------------------------------------------------------------------------------ report
def fake_run(root: Path, name: str, column: str, seed: int, splits: dict, *, k_shot: int = 1, kind="compositional",
             cut: int = 0, curve=((500, 10.0), (1000, 30.0)), paper: str | None = None,
             seconds: tuple[float, float] | None = None) -> None:
    """A finished run's files; `seconds`: its (training, evaluation) wall times."""
    run = root / name
    run.mkdir(parents=True)
    doc = {"run": name, "column": column, "title": column.title(), "paper_column": paper or column, "seed": seed,
           "updates": curve[-1][0], "max_updates": 1000, "best_dev_exact_match": max(v for _, v in curve),
           "max_train_target_length": cut, "data": {"split_kind": kind, "k_shot": k_shot}, "splits": splits}
    if seconds is not None:
        doc["train_seconds"], doc["evaluation"] = seconds[0], {"seconds": seconds[1]}
    (run / "results.json").write_text(json.dumps(doc))
    (run / "config.yaml").write_text("batch_size: 50\n")
    (run / "metrics.jsonl").write_text("".join(json.dumps({"event": "validation", "step": s, "dev_exact_match": v})
                                               + "\n" for s, v in curve))


def split(letter: str, em: float, by_length: dict | None = None) -> dict:
    return {"letter": letter, "examples": 10, "exact_match": em, "token_accuracy": em,
            "by_target_length": by_length or {}}


@pytest.fixture
def results(tmp_path):
    root = tmp_path / "results"
    fake_run(root, "semantic_s0", "semantic", 0, {"test": split("A", 90.0), "adverb_1": split("G", 1.0)},
             seconds=(3600.0, 120.0))
    fake_run(root, "semantic_s1", "semantic", 1, {"test": split("A", 94.0), "adverb_1": split("G", 2.0)},
             curve=((500, 10.0), (1000, 10.5)), seconds=(5400.0, 120.0))
    fake_run(root, "seq2seq_s0", "seq2seq", 0, {"test": split("A", 97.0), "visual": split("C", 20.0)})
    fake_run(root, "state_s0", "state", 0, {"test": split("A", 50.0)})
    fake_run(root, "attention_state_s0", "attention+state", 0, {"test": split("A", 70.0)})
    fake_run(root, "semantic_k10_s0", "semantic", 0, {"test": split("A", 10.0), "adverb_1": split("G", 40.0)},
             k_shot=11)
    lengths = {"test": split("A", 99.0, {"14": {"examples": 5, "exact_match": 100.0},
                                         "15": {"examples": 4, "exact_match": 75.0}}),
               "target_lengths": split("I", 40.0, {"16": {"examples": 2, "exact_match": 50.0},
                                                   "18": {"examples": 3, "exact_match": 0.0},
                                                   "20": {"examples": 1, "exact_match": 100.0}})}
    fake_run(tmp_path / "worker1", "semantic_len15_s0", "semantic", 0, lengths, kind="length", cut=15)
    return [root, tmp_path / "worker1"]


def report(dirs, out: Path, *extra) -> int:
    return main(["report", *map(str, dirs), "--out", str(out), *extra])


def test_an_order_claim_averages_the_rows_the_paper_reports_for_both(tmp_path):
    """The paper has no G k=1 for Dependency: ours and the paper's means leave G out alike."""
    root = tmp_path / "results"
    fake_run(root, "semantic_s0", "semantic", 0, {"test": split("A", 90.0), "adverb_1": split("G", 0.0)})
    fake_run(root, "dependency_s0", "dependency", 0, {"test": split("A", 80.0), "adverb_1": split("G", 30.0)})
    assert report([root], tmp_path / "tables.md") == 0
    assert ("- semantic > dependency: holds — mean over A (the rows the paper reports for each): "
            "Semantic 90.00 vs Dependency 80.00; the order holds row by row on 1 of 1; paper: 96.73 > 96.91.") \
        in (tmp_path / "tables.md").read_text()  # over A and G, ours would not hold (45 < 55)


def test_report_puts_mean_and_std_beside_the_paper(results, tmp_path):
    out = tmp_path / "tables.md"
    assert report(results, out) == 0
    text = out.read_text()
    a_row = next(line for line in text.splitlines() if line.startswith("| A |"))
    # columns in the paper's order: Seq2seq, State, +Attention, Semantic
    assert a_row == ("| A | 97.00<br>paper 97.69 ± 0.22 | 50.00<br>paper 49.83 ± 5.05 | 70.00<br>paper 96.06 ± 1.40 "
                     "| 92.00 ± 2.83<br>paper 96.73 ± 0.58 |")
    assert "| G k=1 | –<br>paper 0.00 ± 0.00 | –<br>paper 3.38 ± 3.66 | –<br>paper 1.79 ± 0.69 " \
           "| 1.50 ± 0.71<br>paper 1.14 ± 0.30 |" in text
    assert "| G k=10 | –<br>paper 2.04 ± 0.95 | –<br>paper 8.48 ± 4.72 | –<br>paper 34.28 ± 6.59 " \
           "| 40.00<br>paper 36.91 ± 5.13 |" in text  # k_shot 11 is the paper's k=10; its A is not Table 1's
    assert "| 15 | 75.00<br>paper 92.06 ± 1.94 |" in text and "| ≥ 18 | 25.00<br>paper 53.67 ± 4.00 |" in text
    histogram = text.split("### Split I at every target length")[1].split("##")[0]
    assert [line for line in histogram.splitlines() if line.startswith("| 1")] == [
        "| 14 | 100.0 (5) |", "| 15 | 75.0 (4) |", "| 16 | 50.0 (2) |", "| 18 | 0.0 (3) |"]
    assert "| 20 | 100.0 (1) |" in histogram
    assert ("| Semantic | 0, 1 | 1000 | 1000 | 50k (30M: 1/600) | 20.25 ± 13.79 | rising +10.25 | 1.0–1.5 | 2.0 |"
            in text)
    assert "| Seq2Seq | 0 | 1000 | 1000 | 50k (40M: 1/800) |" in text  # the paper's seq2seq is Ruis et al.'s
    assert "| Seq2Seq | 0 | 1000 | 1000 | 50k (40M: 1/800) | 30.00 | rising +20.00 | – | – |" in text  # no times logged
    assert "- Semantic, A: ours 92.00 ± 2.83 vs paper 96.73 ± 0.58 (-4.73); dev curve still rising" in text
    assert "- attention-only > +Attention > State: holds — mean over A" in text
    assert "- semantic > constituency: not checked, no results for Constituency." in text
    # no Seq2seq run at k = 10: Semantic is checked against the paper's Seq2seq figure, and says so
    assert "  - G k=10 (Seq2seq: the paper's figure, no run here): 40.00 vs 2.04, +37.96 (paper +34.87)" in text
    assert "![dev exact match vs updates, one panel per column](tables_curves.png)" in text
    assert (tmp_path / "tables_curves.png").read_bytes().startswith(b"\x89PNG")


def test_a_cell_whose_seeds_differ_in_recipe_says_so(tmp_path):
    """A recipe changed between seeds (the older seed stale, not yet retrained) would be
    averaged silently; the report names the run and the keys. The seed, the seed screen and
    the budget are no recipe."""
    fake_run(tmp_path / "r", "semantic_s0", "semantic", 0, {"test": split("A", 90.0)})
    fake_run(tmp_path / "r", "semantic_s1", "semantic", 1, {"test": split("A", 92.0)})
    fake_run(tmp_path / "r", "semantic_s2", "semantic", 2, {"test": split("A", 94.0)})
    (tmp_path / "r/semantic_s0/config.yaml").write_text("batch_size: 50\nseed: 0\nmax_dev_target_length: 14\n")
    (tmp_path / "r/semantic_s1/config.yaml").write_text("batch_size: 50\nseed: 1\nscreen_seeds: 8\n"
                                                          "max_updates: 80000\n")
    (tmp_path / "r/semantic_s2/config.yaml").write_text("batch_size: 50\nseed: 2\n")
    out = tmp_path / "tables.md"
    assert report([tmp_path / "r"], out) == 0
    notes = out.read_text().split("### Cells whose seeds were trained with different recipes")[1].split("###")[0]
    assert notes.strip().splitlines() == [
        "- Semantic: `semantic_s1` differs from `semantic_s0` in max_dev_target_length; the cell averages both.",
        "- Semantic: `semantic_s2` differs from `semantic_s0` in max_dev_target_length; the cell averages both."]


def test_a_variant_column_is_measured_against_its_paper_columns_budget(tmp_path):
    fake_run(tmp_path / "r", "seq2seq_160k_s0", "seq2seq_160k", 0, {"test": split("A", 93.0)}, paper="seq2seq")
    out = tmp_path / "tables.md"
    assert report([tmp_path / "r"], out) == 0
    assert "| Seq2Seq_160K | 0 | 1000 | 1000 | 50k (40M: 1/800) |" in out.read_text()  # Ruis et al.'s 40M, not 30M
    fake_run(tmp_path / "a", "auxloss_s0", "auxloss", 0, {"test": split("A", 80.0)})
    assert report([tmp_path / "a"], out, "--overwrite") == 0
    assert "| 50k (not stated) |" in out.read_text()  # AuxLoss's own budget: the paper does not give it


def test_report_counts_each_columns_screened_starts_on_target(tmp_path):
    def screened(name, seed, candidates, kept):
        fake_run(tmp_path / "r", name, "semantic", seed, {"test": split("A", 90.0)})
        events = [{"event": "screen", "candidate": k, "seed": s, "passed": ok} for k, (s, ok) in enumerate(candidates)]
        events.append({"event": "screen_end", "seed": kept, "candidates": len(candidates)})
        with (tmp_path / "r" / name / "metrics.jsonl").open("a") as f:
            f.write("".join(json.dumps(e) + "\n" for e in events))

    screened("semantic_s0", 0, [(0, False), (1000, False), (2000, True)], 2000)
    screened("semantic_s1", 1, [(1, False), (1001, False)], 1001)  # none passed: the best trained
    fake_run(tmp_path / "r", "state_s0", "state", 0, {"test": split("A", 50.0)})  # not screened: no row
    out = tmp_path / "tables.md"
    assert report([tmp_path / "r"], out, "--no-curves") == 0
    screens = out.read_text().split("## Seed screens")[1].split("##")[0]
    assert [line for line in screens.splitlines() if line.startswith("| ") and "---" not in line][1:] == [
        "| Semantic | 1 of 5 | s0: 2000 after 3 · s1: none of 2, 1001 trained |"]


def test_report_pools_each_columns_failure_kinds(tmp_path):
    def failing(letter, episodes, kinds):
        return {**split(letter, 50.0), "examples": episodes, "failures": dict(zip(FAILURE_KINDS, kinds))}

    fake_run(tmp_path / "r", "semantic_s0", "semantic", 0, {"test": failing("A", 10, (1, 2, 0, 0)),
                                                           "adverb_2": failing("H", 10, (0, 0, 8, 0))})
    fake_run(tmp_path / "r", "semantic_s1", "semantic", 1, {"test": failing("A", 30, (0, 1, 0, 3))})
    fake_run(tmp_path / "r", "state_s0", "state", 0, {"test": split("A", 50.0)})  # evaluated before: no row
    out = tmp_path / "tables.md"
    assert report([tmp_path / "r"], out, "--no-curves") == 0
    section = out.read_text().split("## Where the failures go")[1].split("##")[0]
    assert [line for line in section.splitlines() if line.startswith("| ") and "---" not in line][1:] == [
        "| Semantic | A | s0, s1 of 2 | 40 | 2.5 | 7.5 | 0.0 | 7.5 |",
        "| Semantic | H | s0 of 2 | 10 | 0.0 | 0.0 | 80.0 | 0.0 |"]  # the seeds pooled are named
    fake_free = tmp_path / "none"
    fake_run(fake_free, "state_s0", "state", 0, {"test": split("A", 50.0)})
    assert report([fake_free], tmp_path / "none.md", "--no-curves") == 0
    assert "Where the failures go" not in (tmp_path / "none.md").read_text()


def test_report_is_byte_identical_and_refuses_to_overwrite(results, tmp_path, capsys):
    first, second = tmp_path / "one.md", tmp_path / "two.md"
    assert report(results, first, "--no-curves") == 0 and report(results[::-1], second, "--no-curves") == 0
    assert first.read_bytes() == second.read_bytes()
    assert "Reading (hand-written" not in first.read_text()
    (results[0] / "reading.md").write_text("Seq2seq trained on 1/800 of the examples.\n")
    assert report(results, tmp_path / "read.md", "--no-curves") == 0
    text = (tmp_path / "read.md").read_text()
    assert text.endswith(f"### Reading (hand-written, `{results[0].as_posix()}/reading.md`)\n\n"
                         "Seq2seq trained on 1/800 of the examples.\n")
    assert report(results, first, "--no-curves") == 1
    assert "--overwrite" in capsys.readouterr().err
    assert report([results[0], results[0]], tmp_path / "three.md", "--no-curves") == 1  # a run found twice
    assert "is in both" in capsys.readouterr().err


@pytest.mark.parametrize("field, value, named", [
    ("splits", {"test": 3}, "splits.test must be a mapping, got 3"),
    ("data", ["length"], "data must be a mapping, got ['length']"),
    ("splits", {"test": {"letter": "A", "exact_match": "high"}}, "splits.test.exact_match must be a finite number"),
    ("splits", {"test": split("A", 50.0) | {"failures": {"no_stop": "2"}}}, "splits.test.failures.no_stop"),
    ("best_dev_exact_match", "x", "best_dev_exact_match must be a finite number or null, got 'x'"),
    ("title", [1], "title must be a string, got [1]"),
    ("paper_column", ["a"], "paper_column must be a string or null, got ['a']"),
    ("seed", 1e400, "seed must be an integer >= 0, got inf"),
    ("updates", -5, "updates must be an integer >= 0, got -5"),
    ("data", {"split_kind": "length", "cut_off_target_length": [14]}, "data.cut_off_target_length"),
    ("evaluation", {"max_examples": 1e400}, "evaluation.max_examples must be an integer"),
    ("splits", {"test": split("A", 50.0) | {"by_target_length": {"9": {"exact_match": 50.0, "examples": "4"}}}},
     "splits.test.by_target_length.9.examples must be an integer >= 0, got '4'"),
])
def test_report_names_a_results_json_of_the_wrong_shape(results, tmp_path, capsys, field, value, named):
    path = results[0] / "state_s0" / "results.json"
    doc = json.loads(path.read_text())
    path.write_text(json.dumps(doc | {field: value}))
    assert report(results, tmp_path / "tables.md", "--no-curves") == 1
    err = capsys.readouterr().err
    assert f"{path}: {named}" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("record, named", [
    ({"event": "validation", "step": 1e400, "dev_exact_match": 5.0}, "step of a validation record must be an integer"),
    ({"event": "validation", "step": 3, "dev_exact_match": "x"}, "dev_exact_match of a validation record"),
    ({"event": "screen_end", "seed": [1]}, "seed of a screen_end record must be an integer, got [1]"),
    (None, "cannot read {metrics}: Is a directory"),
], ids=["step inf", "exact match a string", "seed a list", "a directory"])
def test_report_names_a_metrics_jsonl_of_the_wrong_shape(results, tmp_path, capsys, record, named):
    metrics = results[0] / "state_s0" / "metrics.jsonl"
    if record is None:
        metrics.unlink()
        metrics.mkdir()
    else:
        with metrics.open("a") as f:
            f.write(json.dumps(record) + "\n")
    assert report(results, tmp_path / "tables.md", "--no-curves") == 1
    err = capsys.readouterr().err
    assert named.format(metrics=metrics) in err and str(metrics) in err and "results.json" not in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_committed_tables_regenerate_exactly(tmp_path, monkeypatch):
    committed = REPO / "docs/paper_tables.md"
    if not (REPO / "results/paper").is_dir() or not committed.is_file():
        pytest.skip("no committed paper results yet")
    monkeypatch.chdir(REPO)
    out = tmp_path / "paper_tables.md"
    assert report([Path("results/paper")], out, "--curves", str(tmp_path / "paper_tables_curves.png"),
                  "--plan", "configs/experiments/paper.yaml") == 0
    assert out.read_text() == committed.read_text()


def _tex_figure(cell: str):
    cell = re.sub(r"\\phantom\{[^}]*\}|\\textbf\{|[}$]", "", cell).strip()
    if cell == "-":
        return None
    match = re.fullmatch(r"([\d.]+)\s*\\pm\s*([\d.]+)", cell)
    return (float(match[1]), float(match[2])) if match else cell


def test_paper_figures_match_the_tex():
    tex = REPO.parent / "shared" / "paper" / "kuo2021_compositional_gscan.tex"  # shared/ beside the checkout
    if not tex.is_file():
        pytest.skip("the paper's source is not on this machine")
    text = tex.read_text()
    columns = {0: "seq2seq", 4: "state", 5: "attention+state", 6: "constituency", 7: "dependency", 8: "semantic"}
    seen = 0
    for line in text.splitlines():
        cells = [c.strip() for c in line.rstrip("\\ ").split("&")]
        head = re.sub(r"\\phantom\{G \}", "G ", cells[0])
        if len(cells) != 10 or not re.fullmatch(r"[A-H]|G k=\d+", head):
            continue
        for i, column in columns.items():
            assert TABLE1[column].get(head) == _tex_figure(cells[i + 1]), (head, column)
            seen += 1
    assert seen == 11 * 6
    lengths = {"15": "15", "16": "16", "17": "17", "\\geq 18": ">=18"}
    keys = [("seq2seq", 15), ("semantic", 15), ("semantic", 14), ("semantic", 13)]
    found = 0
    for line in text.splitlines():
        cells = [c.strip() for c in line.rstrip("\\ ").split("&")]
        head = re.sub(r"\\phantom\{[^}]*\}|\$", "", cells[0]).strip()
        if len(cells) == 5 and head in lengths:
            for key, cell in zip(keys, cells[1:]):
                assert TABLE2[key][lengths[head]] == _tex_figure(cell), (head, key)
            found += 1
    assert found == 4


@pytest.mark.parametrize("screens, new_count, stale", [
    ([(0, False), (1, True)], 8, False),  # passed at candidate 1: 8 candidates keep the same seed
    ([(0, False), (1, True)], 1, True),  # without screening, seed 0 would have trained
    ([(0, False), (1, False)], 8, True),  # the screen kept the best of two; 8 might keep another
])
def test_more_screen_candidates_leave_a_run_whose_screen_passed_alone(tmp_path, screens, new_count, stale):
    from gscan_ros.training.config import TrainConfig

    old = TrainConfig(screen_seeds=len(screens), screen_updates=10, max_updates=100)
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(old.to_dict()))
    (tmp_path / "metrics.jsonl").write_text("".join(
        json.dumps({"event": "screen", "candidate": k, "passed": ok}) + "\n" for k, ok in screens))
    new = TrainConfig(screen_seeds=new_count, screen_updates=10, max_updates=100)
    assert (config_changes(tmp_path, new) == ["screen_seeds"]) is stale


@pytest.mark.parametrize("plan_value, changed", [(0, []), (14, ["max_dev_target_length"])])
def test_a_field_added_since_a_run_started_counts_as_its_default(tmp_path, plan_value, changed):
    """A config.yaml written before `max_dev_target_length` existed validated on all of dev:
    the plan asking for the default keeps the run, asking for a cut makes it stale."""
    from gscan_ros.training.config import TrainConfig

    saved = TrainConfig(max_train_target_length=14).to_dict()
    del saved["max_dev_target_length"]
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(saved))
    plan = TrainConfig(max_train_target_length=14, max_dev_target_length=plan_value)
    assert config_changes(tmp_path, plan) == changed


@pytest.mark.parametrize("schedule, changed", [
    ({"lr_decay": "cosine", "decay_updates": 0}, ["max_updates"]),  # the decay ends at the budget: it would bend
    ({"lr_decay": "cosine", "decay_updates": 100}, []),  # the decay ends where it did: the run trains on at its floor
    ({"lr_decay": "none", "decay_updates": 0}, []),
])
def test_a_new_budget_changes_the_config_only_where_it_moves_the_schedule(tmp_path, schedule, changed):
    from gscan_ros.training.config import TrainConfig

    (tmp_path / "config.yaml").write_text(yaml.safe_dump(TrainConfig(max_updates=100, **schedule).to_dict()))
    assert config_changes(tmp_path, TrainConfig(max_updates=200, **schedule)) == changed


@pytest.mark.parametrize("parser, changed", [("semantic", []), ("constituency", ["model.init_fan_in"]),
                                             ("dependency", ["model.init_fan_in"])])
def test_a_run_initialised_before_init_fan_in_is_stale_where_its_modules_differ_in_arity(tmp_path, parser, changed):
    """A config.yaml without `model.init_fan_in` was initialised as 'table' does: the same as
    the default for the semantic parse (modules of one argument at most), not for the others."""
    from gscan_ros.training.config import TrainConfig

    saved = TrainConfig(parser=parser).to_dict()
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(saved))
    assert config_changes(tmp_path, TrainConfig(parser=parser)) == changed
    (tmp_path / "config.yaml").write_text(yaml.safe_dump({**saved, "model": {"init_fan_in": "module"}}))
    assert config_changes(tmp_path, TrainConfig(parser=parser)) == []


def test_committed_weights_are_weights_only_and_belong_to_their_run():
    """A finished run's model.pt re-checks its numbers: the run's model kind, the update its
    training picked, and no optimizer state (git is no place for Adam's moments)."""
    from gscan_ros.model.checkpoint import read_checkpoint

    weights = sorted(REPO.glob("results/*/*/model.pt"))
    finished = [path for path in weights if (path.parent / "results.json").is_file()]
    if not finished:
        pytest.skip("no finished run with weights in results/")
    for path in finished:
        checkpoint = read_checkpoint(path)
        config = yaml.safe_load((path.parent / "config.yaml").read_text())
        results = json.loads((path.parent / "results.json").read_text())
        assert {"optimizer", "rng", "cursor"}.isdisjoint(checkpoint), path
        assert checkpoint["kind"] == config["model_kind"] == results["model_kind"], path
        assert 0 < checkpoint["step"] <= results["updates"], path
