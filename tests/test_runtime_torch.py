"""Process-wide torch settings."""
import torch

from gscan_ros import runtime
from gscan_ros.runtime import configure_torch


def test_configure_torch_flushes_denormals_and_sets_threads():
    threads = torch.get_num_threads()
    try:
        torch.set_flush_denormal(False)  # torch's default (another test may have changed it)
        assert (torch.tensor([1e-40]) * 1.0).item() != 0.0
        configure_torch(1)
        assert torch.get_num_threads() == 1
        assert (torch.tensor([1e-40]) * 1.0).item() == 0.0
        configure_torch(0)  # 0 keeps the thread count
        assert torch.get_num_threads() == 1
    finally:
        torch.set_flush_denormal(False)
        torch.set_num_threads(threads)


def test_configure_torch_keeps_freed_memory(monkeypatch):
    calls = []
    monkeypatch.setattr(runtime, "keep_freed_memory", lambda: calls.append(True) or True)
    threads = torch.get_num_threads()
    try:
        configure_torch(0)
    finally:
        torch.set_flush_denormal(False)
        torch.set_num_threads(threads)
    assert calls == [True]
