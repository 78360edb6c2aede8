"""bench/research/time_to_accuracy.py --from-runs: the summary of runs already trained, worked by hand."""
import importlib.util
import json
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def tta():
    spec = importlib.util.spec_from_file_location("time_to_accuracy", REPO / "bench/research/time_to_accuracy.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def fake_run(root: Path, name: str, curve: list[tuple[int, float, float]]) -> Path:
    run = root / name
    run.mkdir()
    lines = [{"event": "train", "step": 1, "examples_per_s": 100.0}]
    lines += [{"event": "validation", "step": u, "dev_exact_match": em, "elapsed_s": s} for u, em, s in curve]
    (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in lines))
    return run


def test_from_runs_reads_each_runs_first_crossing_and_the_median(tta, tmp_path, capsys):
    fast = fake_run(tmp_path, "a_s0", [(1000, 80.0, 60), (2000, 91.0, 120), (3000, 96.0, 180)])
    slow = fake_run(tmp_path, "a_s1", [(1000, 90.0, 90), (2000, 95.0, 300)])
    never = fake_run(tmp_path, "a_s2", [(1000, 50.0, 60), (2000, 89.9, 120)])
    assert tta.main(["--from-runs", str(fast), str(slow), str(never)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == ("90 %: a_s0: 2000 upd. / 2.0 min, a_s1: 1000 upd. / 1.5 min, a_s2: not reached; "
                        "range 1000-2000 updates, 1.5-2.0 minutes")
    # 95 %: 3.0 and 5.0 minutes and one never: the median seed is the 5-minute one
    assert lines[-1] == ("time-to-accuracy: median over 3 seeds reached 95.0% after 2000 updates, 5.0 minutes "
                         "(2 of 3 reached)")


def test_from_runs_names_a_folder_without_metrics(tta, tmp_path, capsys):
    assert tta.main(["--from-runs", str(tmp_path)]) == 1
    err = capsys.readouterr().err.strip()
    assert err == f"time_to_accuracy: error: {tmp_path}: no metrics.jsonl (not a training run)"
