"""The lock file that keeps two runners (or a runner and a dataset generation) from
working on the same run or dataset; stale once the processes it names are gone."""
from __future__ import annotations

import json
import os
import socket
import threading
from pathlib import Path


def _process_start(pid: int) -> str | None:
    """The process's start time in clock ticks since boot (Linux), to tell a live PID
    from a reused one; None where /proc is unavailable."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return None


def _alive(pid: int | None, started: str | None) -> bool:
    if not pid:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return started is None or _process_start(pid) in (None, started)


class FileLock:
    """An exclusive lock file holding {"host", "pid", "started", "child", "child_started"}.

    Created atomically (a complete file is hard-linked into place), so a reader never sees
    it half written. It is held while the runner or its current child process lives; a lock
    from another host counts as held (its processes cannot be checked from here)."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.held = False

    def holder(self) -> dict | None:
        """The live holder's record, or None when free or stale."""
        try:
            info = json.loads(self.path.read_text())
        except FileNotFoundError:
            return None
        except (OSError, ValueError):
            return {"host": "?", "pid": None, "unreadable": True}
        if info.get("host") != socket.gethostname():
            return info
        live = _alive(info.get("pid"), info.get("started")) or _alive(info.get("child"), info.get("child_started"))
        return info if live else None

    def acquire(self) -> bool:
        """Take the lock (breaking a stale one); False while someone else holds it."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        for _ in range(2):
            tmp = self._write_tmp(None)
            try:
                os.link(tmp, self.path)
                self.held = True
                return True
            except FileExistsError:
                if self.holder() is not None:
                    return False
                self.path.unlink(missing_ok=True)
            finally:
                tmp.unlink()
        return False

    def set_child(self, pid: int | None) -> None:
        """Record the subprocess now working for the holder."""
        os.replace(self._write_tmp(pid), self.path)

    def release(self) -> None:
        if self.held:
            self.path.unlink(missing_ok=True)
            self.held = False

    def _write_tmp(self, child: int | None) -> Path:
        tmp = self.path.with_name(f"{self.path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
        pid = os.getpid()
        tmp.write_text(json.dumps({"host": socket.gethostname(), "pid": pid, "started": _process_start(pid),
                                   "child": child, "child_started": child and _process_start(child)}))
        return tmp

