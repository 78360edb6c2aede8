"""bench/research/retrain_agreement.py on two hand-written attempts of one run."""
import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "bench/research/retrain_agreement.py"


def write_attempt(folder: Path, losses: list[float], dev: dict[int, float], test: float) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    events = [{"event": "train", "step": 50 * (i + 1), "loss": loss} for i, loss in enumerate(losses)]
    events += [{"event": "validation", "step": step, "dev_exact_match": em} for step, em in dev.items()]
    (folder / "metrics.jsonl").write_text("".join(json.dumps(e) + "\n" for e in events))
    (folder / "results.json").write_text(json.dumps({"seed": 0, "splits": {"test": {"exact_match": test}}}))


def test_a_retrain_is_compared_with_the_newest_attempt_it_replaced(tmp_path):
    run = tmp_path / "semantic_s0"
    write_attempt(run / ".replaced/20261201T000000Z_40000upd", [1.0, 0.5], {1000: 10.0}, 50.0)
    write_attempt(run / ".replaced/20261202T000000Z_40000upd", [1.0, 0.5], {1000: 20.0, 2000: 40.0}, 60.0)
    write_attempt(run, [1.0, 0.25], {1000: 25.0, 2000: 31.0, 3000: 50.0}, 64.5)
    out = subprocess.run([sys.executable, str(SCRIPT), str(run)], capture_output=True, text=True, check=True).stdout
    assert "20261202T000000Z_40000upd" in out
    assert "0.500000  0.250000  -2.50e-01" in out
    assert "largest dev difference over 2 validations: 9.0 points" in out
    assert "60.00      64.50       +4.50" in out


def test_a_run_with_no_replaced_attempt_is_one_line_and_exit_1(tmp_path):
    run = tmp_path / "semantic_s0"
    write_attempt(run, [1.0], {}, 10.0)
    done = subprocess.run([sys.executable, str(SCRIPT), str(run)], capture_output=True, text=True)
    assert done.returncode == 1 and done.stderr.strip().count("\n") == 0
    assert "holds no attempt with a results.json" in done.stderr
