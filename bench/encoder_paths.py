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

from _data import dataset_or_generated


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

    from gscan_ros.language.lexicon import Lexicon
    from gscan_ros.language.registry import get_parser
    from gscan_ros.model.runtime import configure_torch
    from gscan_ros.training.batches import EpisodeStore, batch_order
    from gscan_ros.training.config import TrainConfig
    from gscan_ros.training.step import TrainStep
    from gscan_ros.training.trainer import iter_split, new_model

    configure_torch(args.threads)
    torch.manual_seed(0)
    with dataset_or_generated(args.data, examples=6000) as data:
        lexicon = Lexicon.named("wordnet")
        parser = get_parser("semantic", lexicon)
        store = EpisodeStore(iter_split(data, "train"), parser)
        model = new_model(TrainConfig.load(args.config), parser, lexicon, store)
        step = TrainStep(model, torch.optim.Adam(model.parameters(), lr=1e-3), store)
        order = batch_order(store, args.batch_size, "mixed", np.random.default_rng(0))
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
