"""A tiny experiment plan for the tests of the runner (test_experiment) and of the
environment its subprocesses get (test_runtime_mkl_shim)."""
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
TINY = {"max_updates": 2, "batch_size": 16, "validate_every": 2, "checkpoint_every": 2, "log_every": 1,
        "max_dev_examples": 8, "lexicon": "none",
        "model": {"rnn_dim": 8, "rnn_layers": 1, "cnn_channels": 4, "att_dim": 4}}
SPLITS = ["test", "visual"]
TINY_DATA = {"examples": 300, "seed": 0}


def write_plan(path: Path, root: Path, defaults: dict = TINY, runs: list | None = None,
               data: dict = TINY_DATA) -> Path:
    plan = {
        "results": str(root / "results"),
        "data_root": str(root / "data"),
        "defaults": defaults,
        "evaluation": {"max_examples": 5},
        "datasets": {"tiny": data},
        "runs": runs or [
            {"name": "semantic", "config": str(REPO / "configs/semantic.yaml"), "data": "tiny", "seeds": [0],
             "splits": SPLITS},
            {"name": "state", "config": str(REPO / "configs/semantic.yaml"), "data": "tiny", "seeds": [0],
             "splits": SPLITS, "set": {"model.message": "state"}, "max_eval_examples": 3},
        ],
    }
    path.write_text(yaml.safe_dump(plan, sort_keys=False))
    return path
