"""bench/research/length_failures.py on hand-written predictions of two models."""
import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "bench/research/length_failures.py"
GOLD = ["turn left", "walk", "walk", "walk", "walk", "turn right", "walk"]  # a first leg of 4 cells


def episode(ident: int, words: list[str], prediction: list[str], distance: int) -> dict:
    return {"split": "target_lengths", "example_id": ident, "input": words, "target": GOLD,
            "prediction": prediction, "exact_match": prediction == GOLD,
            "situation": {"distance_to_target": str(distance)}}


def write(path: Path, episodes: list[dict]) -> str:
    path.write_text(json.dumps(episodes))
    return str(path)


def test_early_turns_and_groups_are_counted_on_the_shared_episodes(tmp_path):
    early = ["turn left", "walk", "walk", "turn right", "walk", "walk"]  # left the leg after 2 of 4
    late = GOLD[:5] + ["walk", "turn right"]  # walked past the turn: not early
    counting = write(tmp_path / "a.json", [episode(0, ["walk", "to", "a", "small", "circle"], early, 5),
                                           episode(1, ["walk", "to", "a", "circle"], GOLD, 5),
                                           episode(2, ["walk", "to", "a", "circle"], late, 17)])
    exact = write(tmp_path / "b.json", [episode(0, ["walk", "to", "a", "small", "circle"], GOLD, 5),
                                        episode(1, ["walk", "to", "a", "circle"], GOLD, 5),
                                        episode(3, ["walk", "to", "a", "circle"], GOLD, 9)])  # not in a.json
    out = subprocess.run([sys.executable, str(SCRIPT), f"counting={counting}", f"exact={exact}"],
                         capture_output=True, text=True, check=True).stdout
    assert "2 episodes shared by counting, exact" in out
    assert "with     (n=    1)  counting   0.0  exact 100.0" in out
    assert "4-7      (n=    2)  counting  50.0  exact 100.0" in out
    assert "counting: 4: 50.0; 1 of its 1 failures (100.0 %)" in out
    assert "exact: 4: 0.0; 0 of its 0 failures (- %)" in out


def test_files_without_a_shared_episode_are_refused(tmp_path):
    a = write(tmp_path / "a.json", [episode(0, ["walk"], GOLD, 5)])
    b = write(tmp_path / "b.json", [episode(1, ["walk"], GOLD, 5)])
    done = subprocess.run([sys.executable, str(SCRIPT), f"a={a}", f"b={b}"], capture_output=True, text=True)
    assert done.returncode == 1 and "share no episode" in done.stderr
