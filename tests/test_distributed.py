"""`torchrun` on 2 CPU ranks (gloo, loopback only): data-parallel training reaches the
parameters one process reaches, a run resumes across rank counts, and sharded evaluation
writes what one process writes."""
import json
import os
import socket
import subprocess
import sys

import numpy as np
import pytest
import torch

from gscan_ros.cli import main
from gscan_ros.errors import GscanError
from gscan_ros.model.checkpoint import read_checkpoint
from gscan_ros.runtime import resolve_device
from gscan_ros.training.distributed import Ranks, shard_batch

pytestmark = pytest.mark.slow

UPDATES = 20
TIMING_KEYS = ("seconds", "episodes_per_s")


@pytest.fixture(scope="module")
def dataset(tiny_dataset):
    return tiny_dataset


def train_args(dataset, out, updates: int, *extra) -> list[str]:
    """Dropout off, so that 1 and 2 ranks compute the same function of the same batches.

    Batches of 17 of the 154 training episodes: every update splits 9/8, so the shards'
    loss weights differ, and update 10 (the epoch's last batch, 1 episode) leaves rank 1
    a weight-0 row. lr 1e-4, not 1e-3: Adam divides each gradient by its own magnitude,
    so where one nearly cancels (attention biases shift every cell's logit, and the
    softmax removes that) float rounding moves the weights by up to ~lr/100 per update.
    At lr 1e-3 (batch 16) one process on 1 vs 2 threads already ends 3.7e-5 apart (2
    ranks: 1.1-3.2e-5); at 1e-4, 9e-7 (2 ranks: 2e-7 to 1.3e-6), 10x under the bound,
    while leaving out the shard weights ends 6e-4 apart (docs/scaling.md)."""
    return ["train", "--data", str(dataset), "--out", str(out), "--quiet", "--set", "batch_size=17",
            "--set", "lr=1e-4", "--set", f"max_updates={updates}", "--set", "lexicon=none",
            "--set", "model.cnn_dropout=0",
            "--set", "threads=1", "--set", "max_dev_examples=4", "--set", "validate_every=1000",
            "--set", "checkpoint_every=1000", "--set", "log_every=5", *extra]


def torchrun(nproc: int, argv: list[str]) -> None:
    """`torchrun --nproc_per_node N -m gscan_ros.cli ARGV`, rendezvous and gloo on 127.0.0.1."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    # faulthandler: a rank that aborts in C++ prints where its Python threads were.
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MASTER_ADDR": "127.0.0.1", "PYTHONFAULTHANDLER": "1"}
    if os.path.isdir("/sys/class/net/lo"):
        env["GLOO_SOCKET_IFNAME"] = "lo"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", str(nproc),
           "--master_addr", "127.0.0.1", "--master_port", str(port), "-m", "gscan_ros.cli", *argv]
    res = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-4000:]


def weights(run) -> dict:
    return read_checkpoint(run / "last.pt")["state_dict"]


def max_difference(a: dict, b: dict) -> float:
    assert a.keys() == b.keys()
    return max(float((a[k].float() - b[k].float()).abs().max()) for k in a)


def records(run, event: str) -> list[dict]:
    lines = (run / "metrics.jsonl").read_text().splitlines()
    return [r for r in map(json.loads, lines) if r["event"] == event]


@pytest.fixture(scope="module")
def one_process(dataset, tmp_path_factory):
    torch.set_num_threads(1)
    run = tmp_path_factory.mktemp("one") / "run"
    assert main(train_args(dataset, run, UPDATES)) == 0
    return run


@pytest.fixture(scope="module")
def two_ranks(dataset, tmp_path_factory):
    run = tmp_path_factory.mktemp("two") / "run"
    torchrun(2, train_args(dataset, run, UPDATES))
    return run


def test_two_ranks_train_the_parameters_of_one_process(one_process, two_ranks):
    assert max_difference(weights(one_process), weights(two_ranks)) < 1e-5
    assert records(two_ranks, "start")[0]["world_size"] == 2 and records(one_process, "start")[0]["world_size"] == 1
    # The logged loss is the whole batch's, not rank 0's shard's.
    np.testing.assert_allclose([r["loss"] for r in records(two_ranks, "train")],
                               [r["loss"] for r in records(one_process, "train")], rtol=1e-5)


def test_resume_across_rank_counts(dataset, one_process, tmp_path):
    run = tmp_path / "run"
    torchrun(2, train_args(dataset, run, UPDATES // 2))
    assert read_checkpoint(run / "last.pt")["step"] == UPDATES // 2
    torch.set_num_threads(1)
    assert main(train_args(dataset, run, UPDATES, "--resume")) == 0
    assert max_difference(weights(one_process), weights(run)) < 1e-5
    assert [r["world_size"] for r in records(run, "start")] == [2, 1]


def test_sharded_evaluation_writes_the_single_process_results(dataset, two_ranks, tmp_path):
    # 12 episodes in batches of 5: rank 0 decodes batches 0 and 2, rank 1 batch 1.
    argv = ["evaluate", "--checkpoint", str(two_ranks / "model.pt"), "--data", str(dataset), "--splits", "test",
            "visual", "--max-examples", "6", "--batch-size", "5", "--threads", "1", "--quiet", "--attention"]
    torch.set_num_threads(1)
    assert main([*argv, "--out", str(tmp_path / "one")]) == 0
    torchrun(2, [*argv, "--out", str(tmp_path / "two")])
    one, two = (json.loads((tmp_path / d / "results.json").read_text()) for d in ("one", "two"))
    assert one["episodes"] == 12
    def untimed(r):
        return {k: v for k, v in r.items() if k not in TIMING_KEYS}
    assert untimed(one) == untimed(two)
    assert (tmp_path / "one" / "predictions.json").read_bytes() == (tmp_path / "two" / "predictions.json").read_bytes()


@pytest.mark.parametrize("size", [16, 7, 2])
def test_shards_cover_the_batch_and_weigh_to_its_mean(size):
    ids = np.arange(100, 100 + size)
    lengths = np.zeros(200, dtype=np.int64)
    lengths[ids] = np.random.default_rng(size).integers(2, 30, size)
    shards = [shard_batch(ids, lengths, Ranks(rank, 3)) for rank in range(3)]
    counted = [s for s, w in shards if w > 0]
    assert sorted(np.concatenate(counted).tolist()) == ids.tolist()
    # sum_r w_r * mean_r(loss) / W == mean(loss) for any per-episode loss
    loss = {int(i): float(i % 7) for i in ids}
    total = sum(w * np.mean([loss[int(i)] for i in s]) for s, w in shards) / 3
    assert total == pytest.approx(np.mean(list(loss.values())))


def test_device_names():
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(GscanError, match="tpu"):
        resolve_device("tpu")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA GPU (CI runs on the CPU)")
def test_cuda_runs_what_the_cpu_runs(dataset, one_process, tmp_path):
    """Needs a GPU (skipped without one); passed on an NVIDIA H200 on 2026-11-30 (docs/scaling.md)."""
    from gscan_ros.language.registry import get_parser
    from gscan_ros.model.policy import Policy
    from gscan_ros.training.batches import EpisodeStore
    from gscan_ros.training.evaluate import evaluate_episodes
    from gscan_ros.training.trainer import load_split

    cpu, gpu = (Policy.from_checkpoint(one_process / "model.pt", device=d) for d in ("cpu", "cuda"))
    episodes = load_split(str(dataset), "test", 8)
    assert ([p.actions for p in evaluate_episodes(gpu, episodes, record_attention=True).predictions]
            == [p.actions for p in evaluate_episodes(cpu, episodes).predictions])
    store = EpisodeStore(episodes, get_parser("semantic", cpu.lexicon))
    batch = store.batch(range(len(episodes)), cpu.model.table)
    with torch.no_grad():
        expected = float(cpu.model.teacher_forcing(batch).loss)
        assert float(gpu.model.teacher_forcing(batch).loss) == pytest.approx(expected, rel=1e-4)
    gpu.model.train().teacher_forcing(batch).loss.backward()  # dropout masks drawn on the GPU
    run = tmp_path / "run"
    assert main(train_args(dataset, run, 2, "--device", "cuda", "--set", "model.cnn_dropout=0.1")) == 0
    assert all(t.device.type == "cpu" for t in torch.load(run / "last.pt", weights_only=True)["state_dict"].values())
