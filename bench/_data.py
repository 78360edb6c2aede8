"""Shared by the benches: a dataset to measure on when `--data` is not given, a fresh
model with its training update on a dataset's batches, a torchrun launch that stays
on the loopback interface, and `LABEL=PATH` arguments."""
from __future__ import annotations

import argparse
import contextlib
import os
import socket
import sys
import tempfile
from typing import Iterator


def labelled(what: str):
    """An argparse type for `LABEL=PATH`, naming `what` the path is in its error."""
    def parse(text: str) -> tuple[str, str]:
        label, sep, path = text.partition("=")
        if not sep or not label or not path:
            raise argparse.ArgumentTypeError(f"expected LABEL={what}, got {text!r}")
        return label, path
    return parse


@contextlib.contextmanager
def dataset_or_generated(data: str | None, examples: int, seed: int = 0, fmt: str = "txt") -> Iterator[str]:
    """`data` itself, or a fresh dataset of `examples` candidates (seeded) in a temp dir
    that is removed afterwards."""
    if data is not None:
        yield data
        return
    from gscan_ros.data.generate import GenerationConfig, generate_dataset

    with tempfile.TemporaryDirectory(prefix="gscan_bench_") as tmp:
        generate_dataset(tmp, GenerationConfig(seed=seed, max_examples=examples), workers=1, fmt=fmt)
        yield tmp


def training_update(data: str, config: str | None, batch_size: int, lr: float = 1e-3):
    """(model, update step, mixed batches in a seeded order) for the config's model, parser
    and lexicon on `data`'s train split; torch's threads and seed are the caller's."""
    import numpy as np
    import torch

    from gscan_ros.language.lexicon import Lexicon
    from gscan_ros.language.registry import get_parser
    from gscan_ros.training.batches import EpisodeStore, batch_order
    from gscan_ros.training.config import TrainConfig
    from gscan_ros.training.step import TrainStep
    from gscan_ros.training.trainer import iter_split, new_model

    cfg = TrainConfig.load(config)
    lexicon = Lexicon.named(cfg.lexicon)
    parser = get_parser(cfg.parser, lexicon)
    store = EpisodeStore(iter_split(data, "train"), parser)
    model = new_model(cfg, parser, lexicon, store)
    step = TrainStep(model, torch.optim.Adam(model.parameters(), lr=lr), store)
    return model, step, batch_order(store, batch_size, "mixed", np.random.default_rng(0))


def loopback_torchrun(processes: int, threads: int) -> tuple[list[str], dict[str, str]]:
    """(argv prefix, environment) that start `processes` ranks of `threads` torch threads
    each with torchrun, rendezvous and gloo on 127.0.0.1 (a free port), nothing else."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
    if os.path.isdir("/sys/class/net/lo"):
        env["GLOO_SOCKET_IFNAME"] = "lo"
    return ([sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", str(processes),
             "--master_addr", "127.0.0.1", "--master_port", str(port)], env)
