"""Process-wide torch settings, and which device the network runs on: what whoever starts
a process that runs a model (the CLI, the trainer, torchrun ranks, the policy node, the
benchmarks) sets up first. The model package never configures the machine; it runs
where it is put.

torch is imported inside the functions, so the CLI can offer `DEVICES` without loading it.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import os
import re
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Mapping

from gscan_ros.errors import GscanError

if TYPE_CHECKING:
    import torch

DEVICES = ("auto", "cpu", "cuda")


_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc mallopt parameters
MKL_SHIM = "libgscan_mkl_intel_cpu.so"  # built by `make setup` into the environment's lib/
MKL_SHIM_SWITCH = "GSCAN_MKL_SHIM"  # "0": start subprocesses without the shim


_default_threads: int | None = None  # torch's intra-op threads before the first `configure_torch`


def available_cpus() -> int:
    """CPUs this process may run on (its affinity mask, else the machine's count)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def check_cpu_count(count: int, what: str, error: type[GscanError] = GscanError) -> int:
    """`count` (worker processes, torch threads), unless it is more than the CPUs available:
    more buys nothing, and torch's thread pool kills the process (SIGSEGV) when asked for
    100,000 threads. The one rule for `--workers`, `--threads` and the `threads` setting."""
    cpus = available_cpus()
    if count > cpus:
        raise error(f"{count} {what} but only {cpus} CPU(s) available; use at most {cpus}")
    return count


def configure_torch(threads: int = 0) -> None:
    """Set intra-op threads (0 = torch's default: the count torch had before the first call,
    so a process that set another one can go back), flush denormal floats to zero and keep
    freed tensors in the heap (`keep_freed_memory`).

    A trained network's weights, activations and Adam moments drift into the denormal
    range (< 1.2e-38), where x86 float arithmetic is tens of times slower, and training
    slows down sharply after a few hundred updates without flushing (figures:
    docs/results.md, "Denormals"). Values that small change nothing a float32 model computes.
    """
    import torch

    global _default_threads
    if _default_threads is None:
        _default_threads = torch.get_num_threads()
    torch.set_num_threads(threads or _default_threads)
    torch.set_flush_denormal(True)
    keep_freed_memory()


def keep_freed_memory(threshold: int = 1 << 30) -> bool:
    """Let glibc keep freed tensors in the heap instead of returning them to the OS.

    By default glibc serves large blocks with mmap (the threshold grows to at most 32 MB)
    and unmaps or trims them on free, so the feature tensors of every training update and
    closed-loop step are page-faulted in again (~30,000 minor faults per 2,048 evaluated
    episodes; figures: docs/results.md, "Engine settings" and "Closed-loop evaluation
    throughput"). Raising the mmap and trim thresholds makes those blocks reusable.
    Returns False (and changes nothing) where the C library has no `mallopt` (non-glibc
    platforms).
    """
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    return bool(mallopt(_M_MMAP_THRESHOLD, threshold)) and bool(mallopt(_M_TRIM_THRESHOLD, threshold))


def cpu_vendor(cpuinfo: str = "/proc/cpuinfo") -> str:
    """The CPU's vendor id ('GenuineIntel', 'AuthenticAMD', ...); '' where it cannot be read."""
    try:
        with open(cpuinfo) as f:
            for line in f:
                if line.startswith("vendor_id"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return ""


def mkl_shim_env(env: Mapping[str, str] | None = None, *, vendor: str | None = None,
                 shim: Path | None = None) -> dict[str, str]:
    """`env` (default: this process's environment) with the MKL vendor shim added to
    LD_PRELOAD, for subprocesses that train or evaluate.

    torch's x86 CPU wheels do their float matmuls with MKL, and MKL runs a generic, slower
    code path on CPUs that are not Intel's. The shim (`mkl_intel_cpu.c`, beside this file)
    makes MKL treat the CPU as Intel's and pick its kernels by the CPU's features. On an AMD EPYC (AVX2)
    VM, float32 products of [3,000 x 150] by [150 x 150] or [150 x 450] ran 1.8-2.1x
    faster at 1 thread (bench/matmul.py), and training updates 8-10 % faster
    (docs/results.md, "Engine settings"). A library has to be preloaded when a process
    starts, hence an environment for the next one. Returned unchanged for other vendors,
    where the shim was not built, or with GSCAN_MKL_SHIM=0.
    """
    out = dict(os.environ if env is None else env)
    shim = shim or Path(sys.prefix) / "lib" / MKL_SHIM
    vendor = cpu_vendor() if vendor is None else vendor
    if (out.get(MKL_SHIM_SWITCH, "1") == "0" or vendor != "AuthenticAMD" or not shim.is_file()
            or str(shim) in _preloads(out)):
        return out
    out["LD_PRELOAD"] = f"{out.get('LD_PRELOAD', '')} {shim}".strip()
    return out


def mkl_shim_loaded() -> bool:
    """Whether this process started with the MKL vendor shim preloaded (for benchmark records)."""
    return any(Path(p).name == MKL_SHIM for p in _preloads(os.environ))


def _preloads(env: Mapping[str, str]) -> list[str]:
    """LD_PRELOAD's entries (ld.so separates them by spaces or colons)."""
    return [p for p in re.split(r"[:\s]+", env.get("LD_PRELOAD", "")) if p]


def resolve_device(name: str | torch.device = "cpu", index: int = 0) -> torch.device:
    """'cpu', 'cuda' (GPU `index`: a process's local rank under torchrun) or 'auto' (cuda
    when torch sees a GPU, else cpu) -> a torch.device; GscanError for another name or a
    GPU that is not there."""
    import torch

    if isinstance(name, torch.device):
        return name
    if name not in DEVICES:
        raise GscanError(f"device must be one of {list(DEVICES)}, got {name!r}")
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cpu":
        return torch.device("cpu")
    if not torch.cuda.is_available():
        raise GscanError(f"device 'cuda' asked for, but torch {torch.__version__} sees no CUDA GPU")
    if index >= torch.cuda.device_count():
        raise GscanError(f"process {index} on this machine needs GPU {index}, but only "
                         f"{torch.cuda.device_count()} are visible")
    return torch.device("cuda", index)
