"""Float32 matmul throughput of torch (MKL) with and without the MKL vendor shim, beside numpy.

    .venv/bin/python bench/matmul.py [--threads 1] [--repeats 200]

MKL runs a generic code path on CPUs that are not Intel's; `make setup` builds a shim
that the experiment runner preloads on AMD CPUs (`gscan_ros.runtime.mkl_shim_env`,
docs/model.md "Performance (CPU)"). Each setting is measured in a child process started
with or without the shim on LD_PRELOAD, on the shapes of the training update's
projections (~3,000 states by 150 features) and one large square product. numpy's
column is its own BLAS (OpenBLAS in the PyPI wheels), for scale. Where the shim does
not apply (not an AMD CPU, or not built) only the "without" column is measured.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

SHAPES = ((3000, 150, 150), (3000, 150, 450), (2000, 2000, 2000))


def measure(threads: int, repeats: int) -> dict:
    """GFLOP/s of torch and numpy per shape, in this process."""
    import time

    import numpy as np
    import torch

    torch.set_num_threads(threads)  # numpy's OpenBLAS reads OPENBLAS_NUM_THREADS, set by the parent

    def rate(matmul, a, b, n: int) -> float:
        for _ in range(max(2, n // 20)):
            matmul(a, b)
        start = time.perf_counter()
        for _ in range(n):
            matmul(a, b)
        return 2 * a.shape[0] * a.shape[1] * b.shape[1] * n / (time.perf_counter() - start) / 1e9

    out = {"torch": {}, "numpy": {}}
    for m, k, n in SHAPES:
        a, b = torch.randn(m, k), torch.randn(k, n)
        count = repeats if m * k * n < 1e8 else max(3, repeats // 40)
        out["torch"][f"{m}x{k}x{n}"] = rate(torch.matmul, a, b, count)
        out["numpy"][f"{m}x{k}x{n}"] = rate(np.matmul, a.numpy(), b.numpy(), count)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=1, help="torch (and OpenBLAS) threads")
    ap.add_argument("--repeats", type=int, default=200, help="timed products per small shape (large: 1/40)")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(measure(args.threads, args.repeats)))
        return
    from gscan_ros.runtime import MKL_SHIM_SWITCH, mkl_shim_env

    plain = {**os.environ, MKL_SHIM_SWITCH: "0", "OPENBLAS_NUM_THREADS": str(args.threads)}
    plain.pop("LD_PRELOAD", None)
    shimmed = mkl_shim_env({**plain, MKL_SHIM_SWITCH: "1"})
    cmd = [sys.executable, __file__, "--child", "--threads", str(args.threads), "--repeats", str(args.repeats)]
    runs = {"without": plain, **({"with": shimmed} if "LD_PRELOAD" in shimmed else {})}
    results = {name: json.loads(subprocess.run(cmd, env=env, check=True, capture_output=True, text=True).stdout)
               for name, env in runs.items()}
    if "with" not in results:
        print("the MKL shim does not apply here (not an AMD CPU, or `make setup` did not build it)")
    print(f"float32 GFLOP/s, {args.threads} thread(s)")
    print(f"{'m x k x n':>16s}  {'torch':>8s}  {'torch+shim':>10s}  {'numpy':>8s}")
    for shape in results["without"]["torch"]:
        with_shim = f"{results['with']['torch'][shape]:10.1f}" if "with" in results else f"{'-':>10s}"
        print(f"{shape:>16s}  {results['without']['torch'][shape]:8.1f}  {with_shim}  "
              f"{results['without']['numpy'][shape]:8.1f}")


if __name__ == "__main__":
    main()
