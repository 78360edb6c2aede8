"""Training update time with the per-cell encoder's weight gradient from torch's
embedding-bag backward vs `fast_ops.BagSum` (one sparse product).

    .venv/bin/python bench/research/bag_backward.py --data data_gen/len_20k --config configs/length.yaml [--updates 12]

Both give the same gradient (tests/test_model_fastpaths.py). Every batch is trained twice,
once per backward, in alternating order, so that both see the same batches and machine
load; prints the median time of each and the median of the per-batch ratios. The
per-cell bags are what training on grids of `PER_CELL_MIN_GRID` and wider uses (12x12).
"""
from __future__ import annotations

import argparse
import sys
import time
import types
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/, for the benches' _data
from _data import training_update  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="a dataset on a grid of PER_CELL_MIN_GRID or wider")
    ap.add_argument("--config", default="configs/length.yaml", help="training config whose model is measured")
    ap.add_argument("--batch-size", type=int, default=50)
    ap.add_argument("--updates", type=int, default=12, help="batches, each trained once per backward")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()

    import numpy as np
    import torch
    import torch.nn.functional as F

    from gscan_ros.model import sparse_encoder
    from gscan_ros.runtime import configure_torch

    configure_torch(args.threads)
    torch.manual_seed(0)
    model, step, order = training_update(args.data, args.config, args.batch_size, lr=1e-4)
    if not model.encoder.sparse.per_cell:
        raise SystemExit(f"{args.data}: a {model.cfg.grid_size}x{model.cfg.grid_size} grid trains on the Toeplitz "
                         f"matrix, not the per-cell bags")
    order = order[: args.updates + 1]
    torch_backward = types.SimpleNamespace(apply=lambda rows, weight, starts: F.embedding_bag(
        rows, weight, starts, mode="sum"))
    fast_backward = sparse_encoder.BagSum
    times: dict[str, list[float]] = {"torch": [], "BagSum": []}
    for i, ids in enumerate(order):
        for name in (("torch", "BagSum") if i % 2 else ("BagSum", "torch")):
            sparse_encoder.BagSum = fast_backward if name == "BagSum" else torch_backward
            start = time.perf_counter()
            step(ids)
            if i:  # the first batch warms the caches
                times[name].append(time.perf_counter() - start)
    sparse_encoder.BagSum = fast_backward
    plain, fast = (float(np.median(times[k])) for k in ("torch", "BagSum"))
    ratio = float(np.median(np.array(times["torch"]) / np.array(times["BagSum"])))
    g = model.cfg.grid_size
    print(f"{g}x{g}, batch {args.batch_size}, {args.threads} thread(s): torch embedding-bag backward "
          f"{plain * 1e3:.0f} ms/update, BagSum {fast * 1e3:.0f} ms/update (per-batch ratio {ratio:.2f}x)")


if __name__ == "__main__":
    main()
