"""Shared by the benches: a dataset to measure on when `--data` is not given."""
from __future__ import annotations

import contextlib
import tempfile
from typing import Iterator


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
