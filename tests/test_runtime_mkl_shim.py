"""The MKL vendor shim: which subprocess environments get it, and that a process started
with it computes the same matmuls (gscan_ros/runtime.py: mkl_shim_env)."""
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from experiment_support import write_plan

from gscan_ros import runtime
from gscan_ros.experiments import locks, plan, runner
from gscan_ros.runtime import MKL_SHIM, cpu_vendor, mkl_shim_env

SOURCE = Path(runtime.__file__).with_name("mkl_intel_cpu.c")


@pytest.fixture
def shim(tmp_path):
    path = tmp_path / MKL_SHIM
    path.write_bytes(b"")  # mkl_shim_env only checks that the file is there
    return path


def test_an_amd_cpu_gets_the_shim_after_the_existing_preloads(shim):
    env = mkl_shim_env({"LD_PRELOAD": "/a/liba.so:/b/libb.so", "HOME": "/root"}, vendor="AuthenticAMD", shim=shim)
    assert env["LD_PRELOAD"] == f"/a/liba.so:/b/libb.so {shim}" and env["HOME"] == "/root"
    assert mkl_shim_env(env, vendor="AuthenticAMD", shim=shim) == env  # never twice
    assert mkl_shim_env({}, vendor="AuthenticAMD", shim=shim)["LD_PRELOAD"] == str(shim)


@pytest.mark.parametrize("env, vendor, built", [
    ({}, "GenuineIntel", True),                      # MKL's own vendor: nothing to fix
    ({}, "", True),                                  # unknown CPU
    ({"GSCAN_MKL_SHIM": "0"}, "AuthenticAMD", True),  # switched off
    ({}, "AuthenticAMD", False),                     # `make setup` could not build it
])
def test_the_environment_is_unchanged_where_the_shim_does_not_apply(shim, env, vendor, built):
    if not built:
        shim.unlink()
    assert mkl_shim_env(env, vendor=vendor, shim=shim) == env


def test_cpu_vendor_reads_cpuinfo(tmp_path):
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nvendor_id\t: AuthenticAMD\ncpu family\t: 25\n")
    assert cpu_vendor(str(info)) == "AuthenticAMD"
    assert cpu_vendor(str(tmp_path / "missing")) == ""


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler to build the shim")
def test_a_process_started_with_the_shim_computes_the_same_products(tmp_path):
    lib = tmp_path / MKL_SHIM
    subprocess.run(["cc", "-shared", "-fPIC", "-O2", "-o", str(lib), str(SOURCE)], check=True)
    probe = ("import torch\nfrom gscan_ros.runtime import mkl_shim_loaded\n"
             "torch.manual_seed(0)\n"
             "a, b = torch.randn(300, 150, dtype=torch.float64), torch.randn(150, 450, dtype=torch.float64)\n"
             "err = ((a.float() @ b.float()).double() - a @ b).abs().max().item()\n"
             "print(mkl_shim_loaded(), err < 1e-3)\n")
    out = subprocess.run([sys.executable, "-c", probe], env={**os.environ, "LD_PRELOAD": str(lib)},
                         capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["True", "True"], out.stderr


def test_the_runner_starts_its_steps_in_the_shim_environment(tmp_path, monkeypatch):
    monkeypatch.setattr(runner, "mkl_shim_env", lambda: {**os.environ, "GSCAN_SHIM_PROBE": "from mkl_shim_env"})
    steps = runner.Runner(plan.load_plan(write_plan(tmp_path / "plan.yaml", tmp_path)), progress=False)
    lock, log = locks.FileLock(tmp_path / ".lock"), tmp_path / "step.log"
    assert lock.acquire()
    steps._call([sys.executable, "-c", "import os; print(os.environ['GSCAN_SHIM_PROBE'])"], log, lock, "probe")
    assert log.read_text().splitlines()[-1] == "from mkl_shim_env"
