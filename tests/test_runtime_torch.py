"""Process-wide torch settings."""
import torch

from gscan_ros import runtime
from gscan_ros.runtime import configure_torch


def test_configure_torch_flushes_denormals_and_sets_threads(monkeypatch):
    threads = torch.get_num_threads()
    monkeypatch.setattr(runtime, "_default_threads", None)  # as in a process that never called it
    try:
        torch.set_flush_denormal(False)  # torch's default (another test may have changed it)
        assert (torch.tensor([1e-40]) * 1.0).item() != 0.0
        configure_torch(0)  # 0 keeps the count torch has
        assert torch.get_num_threads() == threads
        configure_torch(1)
        assert torch.get_num_threads() == 1
        assert (torch.tensor([1e-40]) * 1.0).item() == 0.0
    finally:
        torch.set_flush_denormal(False)
        torch.set_num_threads(threads)


def test_configure_torch_0_goes_back_to_torchs_default(monkeypatch):
    """A running node's `torch_threads` set back to 0 restores the count torch chose itself."""
    threads = torch.get_num_threads()
    monkeypatch.setattr(runtime, "_default_threads", None)
    torch.set_num_threads(3)  # torch's default, as the first call finds it
    try:
        configure_torch(2)
        assert torch.get_num_threads() == 2
        configure_torch(0)
        assert torch.get_num_threads() == 3
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
