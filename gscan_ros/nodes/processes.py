"""Node processes on a machine shared with other DDS users, for the tests and the ROS benches.

The rules (docs/ros.md "Testing and DDS hygiene"): discovery stays on loopback, every run
uses its own domain and the fast-discovery Fast DDS profile, and node processes run in
their own session so they are stopped as a process group (SIGINT, then SIGKILL and
`fastdds shm clean`). Importing this module changes nothing; `join_local_graph()` sets
the calling process up to join such a graph.
"""
from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import tempfile
from pathlib import Path


def _fast_discovery_profile() -> Path:
    """config/fastdds_fast_discovery.xml of the source tree, else of the installed share/."""
    name = Path("config") / "fastdds_fast_discovery.xml"
    source = Path(__file__).resolve().parents[2] / name
    if source.is_file():
        return source
    try:
        from ament_index_python.packages import get_package_share_directory

        return Path(get_package_share_directory("gscan_ros")) / name
    except (ImportError, LookupError):
        return source


FAST_DISCOVERY_XML = _fast_discovery_profile()
VENV_BIN = Path(sys.executable).parent

_domains = itertools.count()


def join_local_graph() -> None:
    """Make this process join the node processes' graph: same profile, loopback only, logs
    under a temp dir (each only where unset). Call it before the first rclpy.init: Fast DDS
    reads the profile at first use."""
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    os.environ.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", str(FAST_DISCOVERY_XML))
    os.environ.setdefault("ROS_LOG_DIR", tempfile.mkdtemp(prefix="gscan_ros_test_log_"))


def fresh_domain_id() -> int:
    """The ROS domain for one run: ROS_DOMAIN_ID when the environment sets it (a machine
    or CI job that assigns each user a domain: the runs then take turns in it), else one within
    1..100 (valid Fast DDS ports), varied by pid."""
    assigned = os.environ.get("ROS_DOMAIN_ID", "")
    if assigned.isdigit():
        return int(assigned)
    return 1 + (os.getpid() * 7 + next(_domains)) % 100


def ros_env(domain_id: int, log_dir: Path) -> dict[str, str]:
    """Environment for node processes: loopback discovery, own domain, unbuffered output."""
    env = dict(os.environ)
    env.update(
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        ROS_DOMAIN_ID=str(domain_id),
        ROS_LOG_DIR=str(log_dir),
        FASTRTPS_DEFAULT_PROFILES_FILE=str(FAST_DISCOVERY_XML),
        PYTHONUNBUFFERED="1",
        OMP_NUM_THREADS="1",
    )
    return env


def ros_args(params: dict[str, object], remaps: dict[str, str] | None = None) -> list[str]:
    """`--ros-args -p name:=value ... -r from:=to ...` for a node command line."""
    args = ["--ros-args"]
    for name, value in params.items():
        text = str(value).lower() if isinstance(value, bool) else str(value)
        args += ["-p", f"{name}:={text}"]
    for source, target in (remaps or {}).items():
        args += ["-r", f"{source}:={target}"]
    return args


class NodeProcess:
    """One node executable (the installed console script) in its own session.

    `executable` is a node name (console script, else `python -m gscan_ros.nodes.<name>`)
    or a full argv list (e.g. `gscan-ros bringup ...`).
    """

    def __init__(self, executable: str | list[str], env: dict[str, str], log_dir: Path, params=None, remaps=None,
                 name=None):
        if isinstance(executable, str):
            script = VENV_BIN / executable
            command = [str(script)] if script.exists() else [sys.executable, "-m", f"gscan_ros.nodes.{executable}"]
            command += ros_args(params or {}, remaps)
        else:
            command = list(executable)
        self.name = name or Path(command[0]).name
        self.log_path = log_dir / f"{self.name}.out"
        self._log = open(self.log_path, "wb")
        self.process = subprocess.Popen(
            command, env=env, stdout=self._log, stderr=subprocess.STDOUT, start_new_session=True
        )

    def alive(self) -> bool:
        return self.process.poll() is None

    def output(self) -> str:
        return self.log_path.read_text(errors="replace")

    def stop(self, sig: int = signal.SIGINT, timeout: float = 15.0) -> int:
        """Signal the process group; SIGKILL (and clean Fast DDS shared memory) after `timeout`."""
        if self.alive():
            os.killpg(self.process.pid, sig)
            try:
                self.process.wait(timeout)
            except subprocess.TimeoutExpired:
                self.kill()
        self._log.close()
        return self.process.returncode

    def kill(self) -> None:
        if self.alive():
            os.killpg(self.process.pid, signal.SIGKILL)
            self.process.wait()
        clean_shared_memory()


def clean_shared_memory() -> None:
    """Remove Fast DDS shared-memory segments left by SIGKILLed participants."""
    fastdds = VENV_BIN / "fastdds"
    if fastdds.exists():
        subprocess.run([str(fastdds), "shm", "clean"], capture_output=True, timeout=30, check=False)
