"""Training update time with the encoder's Toeplitz matrix vs its per-cell canvas bags.

    .venv/bin/python bench/encoder_paths.py [--data DIR] [--config FILE] [--batch-size 50] [--updates 8]
    .venv/bin/python bench/encoder_paths.py --data data_gen/len_20k --config configs/length.yaml   # 12x12

Both paths compute the same features (tests/test_model_fastpaths.py); this times whole
training updates (batch, forward, backward, Adam) on the same batches, switching the
path every update so that both see the same machine load. Prints the median of each.
Without --data, a 6,000-candidate 6x6 set is generated into a temp dir.
"""
from __future__ import annotations

import argparse
import time

from _data import dataset_or_generated, training_update


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", help="dataset (default: generate 6000 candidates into a temp dir)")
    ap.add_argument("--config", help="training config whose model is measured (default: built-in defaults)")
    ap.add_argument("--batch-size", type=int, default=50)
    ap.add_argument("--updates", type=int, default=8, help="timed updates per path")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()

    import numpy as np
    import torch

    from gscan_ros.runtime import configure_torch

    configure_torch(args.threads)
    torch.manual_seed(0)
    with dataset_or_generated(args.data, examples=6000) as data:
        model, step, order = training_update(data, args.config, args.batch_size)
        if len(order) < 2 * args.updates + 2:
            raise SystemExit(f"{len(order)} batches in the data; {2 * args.updates + 2} needed")
        times: dict[bool, list[float]] = {True: [], False: []}
        for i, ids in enumerate(order[: 2 * args.updates + 2]):
            per_cell = bool(i % 2)
            model.encoder.sparse.per_cell = per_cell
            start = time.perf_counter()
            step(ids)
            if i >= 2:  # the first update of each path warms its caches
                times[per_cell].append(time.perf_counter() - start)
    g = model.cfg.grid_size
    toeplitz, canvas = (float(np.median(times[k])) for k in (False, True))
    print(f"{g}x{g}, batch {args.batch_size}, {args.threads} thread(s): Toeplitz {toeplitz * 1e3:.0f} ms/update, "
          f"per-cell canvas {canvas * 1e3:.0f} ms/update ({toeplitz / canvas:.2f}x); "
          f"training uses {'per-cell' if g >= PER_CELL_MIN_GRID else 'Toeplitz'} on {g}x{g}")


if __name__ == "__main__":
    from gscan_ros.model.sparse_encoder import PER_CELL_MIN_GRID

    main()
