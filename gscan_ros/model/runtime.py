"""Process-wide torch settings for running the network on CPU."""
from __future__ import annotations

import torch


def configure_torch(threads: int = 0) -> None:
    """Set intra-op threads (0 = keep torch's default) and flush denormal floats to zero.

    A trained network's weights, activations and Adam moments drift into the denormal
    range (< 1.2e-38), where x86 float arithmetic is tens of times slower: a training run
    at 2 threads fell from ~890 to ~480 examples/s within 700 updates, and an update from
    a trained checkpoint ran 839 vs 1,182 examples/s without vs with flushing
    (docs/results.md). Values that small change nothing a float32 model computes.
    """
    if threads:
        torch.set_num_threads(threads)
    torch.set_flush_denormal(True)
