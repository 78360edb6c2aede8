"""The lock file that keeps two runners (or a runner and a dataset generation) from
working on the same run or dataset: an flock, which the kernel releases when its holder
dies, on a file that names the holder's processes."""
from __future__ import annotations

import fcntl
import json
import os
import socket
import threading
from pathlib import Path

# The record is written in place over the same bytes, padded to this width: a reader never
# sees the tail of a longer earlier record.
RECORD_BYTES = 512


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
    """An exclusive lock on a file holding {"host", "pid", "started", "child", "child_started"}.

    The holder keeps an flock on the file while it holds the lock, so two runners never both
    take it, and the lock needs no breaking after a crash: the kernel drops it with the
    process. The record says who holds it (`--dry-run`), and keeps the lock held while a
    process it names lives: the runner's training subprocess outlives a runner killed with
    SIGKILL, and runners of versions before the flock (2026-12-06) lock by the record
    alone. A lock from another host counts as held (its processes cannot be checked from
    here). The file appears whole (a complete file is hard-linked into place) and is
    removed at release."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.held = False
        self._fd: int | None = None

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
        """Take the lock; False while someone else holds it (its flock, or a live process
        its record names)."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        while True:
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CLOEXEC)
            except FileNotFoundError:
                fd = self._create()
                if fd is None:  # another process created it first
                    continue
                self._fd, self.held = fd, True
                return True
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                return False
            if not _names(self.path, fd):  # released (removed) while we opened it: try again
                os.close(fd)
                continue
            if self.holder() is not None:
                os.close(fd)
                return False
            self._fd, self.held = fd, True
            self._write(None)
            return True

    def set_child(self, pid: int | None) -> None:
        """Record the subprocess now working for the holder."""
        self._write(pid)

    def release(self) -> None:
        if self.held:
            self.path.unlink(missing_ok=True)  # while still locked: whoever opened it notices (`_names`)
            os.close(self._fd)
            self._fd, self.held = None, False

    def _create(self) -> int | None:
        """A new lock file, locked and holding our record, linked into place; None when the
        path exists by then."""
        tmp = self.path.with_name(f"{self.path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
        fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)  # a name of our own: no one else waits on it
            os.pwrite(fd, _record(None), 0)
            os.link(tmp, self.path)
        except FileExistsError:
            os.close(fd)
            return None
        except BaseException:
            os.close(fd)
            raise
        finally:
            tmp.unlink()
        return fd

    def _write(self, child: int | None) -> None:
        record = _record(child)
        os.pwrite(self._fd, record, 0)
        os.ftruncate(self._fd, len(record))  # the same length but over a longer stale record


def _record(child: int | None) -> bytes:
    pid = os.getpid()
    record = {"host": socket.gethostname(), "pid": pid, "started": _process_start(pid), "child": child,
              "child_started": child and _process_start(child)}
    return json.dumps(record).encode().ljust(RECORD_BYTES)


def _names(path: Path, fd: int) -> bool:
    """`path` still names the file open as `fd`."""
    try:
        return os.stat(path).st_ino == os.fstat(fd).st_ino
    except FileNotFoundError:
        return False
