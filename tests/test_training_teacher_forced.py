"""Teacher-forced metrics: an episode is right under teacher forcing exactly when the greedy
closed loop reproduces it, so their sequence accuracy and exact match agree."""
from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from gscan_ros.data.io import select_test_episodes
from gscan_ros.errors import InvalidActionError
from gscan_ros.model.config import Seq2SeqConfig
from gscan_ros.model.decoder import command_vocabulary
from gscan_ros.model.policy import MAX_STEPS, Policy
from gscan_ros.model.seq2seq import Seq2Seq
from gscan_ros.training.batches import EpisodeStore
from gscan_ros.training.evaluate import evaluate_episodes, teacher_forced

pytestmark = pytest.mark.slow
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def shipped():
    torch.set_num_threads(1)
    return Policy.from_checkpoint(None)


def replayable(ep) -> bool:
    try:
        ep.states()
    except InvalidActionError:
        return False
    return True


def test_sequence_accuracy_is_closed_loop_exact_match_on_every_split(shipped, tiny_dataset):
    episodes = select_test_episodes(tiny_dataset, None, max_examples=40, seed=0)
    by_split: dict[str, list] = {}
    for ep in episodes:
        by_split.setdefault(ep.split, []).append(ep)
    exact_matches = []
    for split, eps in by_split.items():
        closed = evaluate_episodes(shipped, eps).exact_match
        forced = teacher_forced(shipped.model, EpisodeStore(eps, shipped.parser), batch_size=16)
        assert forced.sequence_accuracy == pytest.approx(closed), split
        assert forced.episodes == len(eps) and forced.steps == sum(len(ep.actions) + 1 for ep in eps)
        assert forced.token_accuracy >= forced.sequence_accuracy
        exact_matches.append(closed)
    assert min(exact_matches) < 100.0 < 2 * max(exact_matches), "the check needs hits and misses"


@pytest.mark.parametrize("kind", ["compositional", "seq2seq"])
def test_a_models_own_decoding_is_all_right_under_teacher_forcing(kind, shipped, tiny_dataset):
    torch.manual_seed(0)
    policy = shipped if kind == "compositional" else Policy(Seq2Seq(Seq2SeqConfig(), command_vocabulary()), "semantic")
    episodes = select_test_episodes(tiny_dataset, ["test", "visual"], max_examples=30, seed=1)
    decoded = evaluate_episodes(policy, episodes).predictions
    own = [dataclasses.replace(p.episode, actions=tuple(p.actions)) for p in decoded if len(p.actions) <= MAX_STEPS]
    own = [ep for ep in own if replayable(ep)]
    assert len(own) >= 10, f"only {len(own)} decodings ended within the cap"
    forced = teacher_forced(policy.model, EpisodeStore(own, policy.parser), np.arange(len(own)), batch_size=8)
    assert forced.sequence_accuracy == 100.0 and forced.token_accuracy == 100.0
    gold = teacher_forced(policy.model, EpisodeStore(episodes, policy.parser))
    assert gold.nll > forced.nll  # the gold actions are less likely than the model's own, where they differ


def test_snapshot_curve_bench_reads_every_snapshot_in_order(tmp_path, tiny_dataset):
    from model_support import tiny_checkpoint

    run = tmp_path / "run"
    run.mkdir()
    for step in (10, 2):
        tiny_checkpoint(run / f"step_{step}.pt", seed=step, weight_scale=3.0)
    out = tmp_path / "curve.json"
    cmd = [sys.executable, str(REPO / "bench/research/snapshot_curve.py"), str(run), "--data", str(tiny_dataset),
           "--splits", "test", "--max-examples", "6", "--train-containing", "walk", "--json", str(out)]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    rows = json.loads(out.read_text())["rows"]
    assert [(Path(r["checkpoint"]).name, r["split"]) for r in rows] == [
        ("step_2.pt", "test"), ("step_2.pt", "train:walk"), ("step_10.pt", "test"), ("step_10.pt", "train:walk")]
    assert all(r["exact_match"] == pytest.approx(r["sequence_accuracy"]) for r in rows)
    assert rows[0]["episodes"] == 6 and rows[1]["episodes"] > 0
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert again.returncode != 0 and "exists" in again.stderr and "Traceback" not in again.stderr


@pytest.mark.parametrize("mixing", [[], ["--alone", "2"]])
def test_oversample_probe_trains_and_reports_every_watched_set(mixing, tmp_path, tiny_dataset):
    from model_support import tiny_checkpoint

    ckpt = tiny_checkpoint(tmp_path / "tiny.pt")
    cmd = [sys.executable, str(REPO / "bench/research/oversample_probe.py"), "--checkpoint", str(ckpt), "--data",
           str(tiny_dataset), "--word", "cautiously", "--updates", "4", "--eval-every", "2", "--subset", "40",
           "--batch-size", "8", "--split", "test", "--max-examples", "4", *mixing]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    rows = [line for line in done.stdout.splitlines() if line.startswith("| ") and line[2].isdigit()]
    assert [row.split(" | ")[0] for row in rows] == ["| 0", "| 0", "| 2", "| 2", "| 4", "| 4"]
    assert all("train:cautiously" in row for row in rows[::2]) and all("test (4)" in row for row in rows[1::2])
    bad = subprocess.run(cmd[:-len(mixing) or None] + ["--per-batch", "8"], capture_output=True, text=True)
    assert bad.returncode != 0 and "--per-batch must be" in bad.stderr and "Traceback" not in bad.stderr


def _fake_run(run: Path, data: Path, batching: str, batch_size: int, train_examples: int, k: int,
              oversample: str = "", word: str = "cautiously") -> Path:
    """A run directory and its snapshot curve as snapshot_curve.py writes them (two snapshots)."""
    run.mkdir()
    (run / "config.yaml").write_text(f"batching: {batching}\nbatch_size: {batch_size}\n{oversample}")
    start = {"event": "start", "step": 0, "train_examples": train_examples}
    (run / "metrics.jsonl").write_text(json.dumps(start) + "\n")
    rows = []
    for updates, acc in ((10, 40.0), (20, 60.0)):
        for split, episodes in (("adverb_1", 30), (f"train:{word}", k)):
            rows.append({"updates": updates, "split": split, "episodes": episodes, "token_accuracy": acc,
                         "nll": 1.0, "sequence_accuracy": 0.0, "exact_match": 0.0})
    curve = run / "curve.json"
    curve.write_text(json.dumps({"run": str(run), "data": str(data), "rows": rows}))
    return curve


def test_kshot_exposures_counts_passes_with_the_runs_own_batching(tmp_path, tiny_dataset):
    from gscan_ros.training.trainer import iter_split

    commands = [ep.command for ep in iter_split(str(tiny_dataset), "train")]
    per_command = sum(-(-commands.count(c) // 4) for c in set(commands))  # ceil per command
    assert per_command > -(-len(commands) // 4), "the check needs commands that leave batches part-full"
    mixed = _fake_run(tmp_path / "mixed", tiny_dataset, "mixed", 4, len(commands), k=5)
    grouped = _fake_run(tmp_path / "grouped", tiny_dataset, "per_command", 4, len(commands), k=11)
    walks = sum("walk" in c.split() for c in commands)
    oversampled = _fake_run(tmp_path / "oversampled", tiny_dataset, "mixed", 4, len(commands), k=walks,
                            oversample="oversample_word: walk\noversample_factor: 3\n", word="walk")
    png = tmp_path / "exposures.png"
    cmd = [sys.executable, str(REPO / "bench/research/kshot_exposures.py"), str(mixed), str(grouped), "--png", str(png)]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    rows = {(r.split(" | ")[0][2:], int(r.split(" | ")[2])): float(r.split(" | ")[4])
            for r in done.stdout.splitlines() if r.startswith("| ") and r[2] != "-" and r.split(" | ")[1].isdigit()}
    assert rows[("mixed", 20)] == pytest.approx(5 * 20 / -(-len(commands) // 4), abs=0.5)
    assert rows[("grouped", 20)] == pytest.approx(11 * 20 / per_command, abs=0.5)
    assert png.stat().st_size > 0
    walked = subprocess.run([*cmd[:2], str(oversampled), "--word", "walk"], capture_output=True, text=True)
    assert walked.returncode == 0, walked.stderr
    row = next(r for r in walked.stdout.splitlines() if r.startswith("| oversampled | ") and " | 20 | " in r)
    epoch = -(-(len(commands) + 2 * walks) // 4)  # the walk episodes three times each
    assert float(row.split(" | ")[4]) == pytest.approx(3 * walks * 20 / epoch, abs=0.5)
    again = subprocess.run(cmd, capture_output=True, text=True)
    assert again.returncode != 0 and "exists" in again.stderr and "Traceback" not in again.stderr
    curve = json.loads(mixed.read_text())
    curve["rows"] = [r for r in curve["rows"] if r["split"] != "train:cautiously"]
    mixed.write_text(json.dumps(curve))
    bad = subprocess.run(cmd[:3], capture_output=True, text=True)
    assert bad.returncode != 0 and "--train-containing cautiously" in bad.stderr and "Traceback" not in bad.stderr


def test_think_accuracy_bench_scores_the_auxloss_classifiers_guess(tmp_path, tiny_dataset):
    """With its scoring vector zeroed, the classifier's logits tie and its guess is cell 0
    in every episode: the bench's figures then follow from the situations alone."""
    from gscan_ros.language.lexicon import Lexicon
    from gscan_ros.model.checkpoint import build_model, checkpoint_dict, save_checkpoint

    torch.manual_seed(0)
    model = build_model("auxloss", {}, {"tokens": command_vocabulary()})
    with torch.no_grad():
        model.think_world.v.weight.zero_()
    ckpt = tmp_path / "auxloss.pt"
    save_checkpoint(ckpt, checkpoint_dict(model, parser="semantic", lexicon=Lexicon.none(), step=0, metrics={}))
    out = tmp_path / "think.json"
    cmd = [sys.executable, str(REPO / "bench/research/think_accuracy.py"), "--checkpoint", str(ckpt), "--data",
           str(tiny_dataset), "--splits", "test", "visual", "--max-examples", "40", "--json", str(out)]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    rows = {r["split"]: r for r in json.loads(out.read_text())["rows"]}
    episodes = select_test_episodes(tiny_dataset, ["test", "visual"], max_examples=40, seed=0)
    for split in ("test", "visual"):
        eps = [ep for ep in episodes if ep.split == split]
        at_origin = [next((o for o in ep.situation.placed_objects if o.position == (0, 0)), None) for ep in eps]
        target_there = [o == ep.situation.target_object for o, ep in zip(at_origin, eps)]
        row = rows[split]
        assert row["episodes"] == len(eps) and row["think"] == pytest.approx(100 * np.mean(target_there), abs=0.01)
        wrong = [o for o, hit in zip(at_origin, target_there) if not hit]
        assert row["wrong_guesses"]["empty"] == sum(o is None for o in wrong)
        assert sum(row["wrong_guesses"].values()) == len(wrong) > 0
    bad = subprocess.run(cmd[:3] + [str(REPO / "gscan_ros/assets/default_model.pt")] + cmd[4:-2],
                         capture_output=True, text=True, timeout=300)
    assert bad.returncode != 0 and "not auxloss" in bad.stderr and "Traceback" not in bad.stderr
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert again.returncode != 0 and "exists" in again.stderr and "Traceback" not in again.stderr
