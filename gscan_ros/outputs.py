"""The rules every `gscan-ros` writer follows for what it leaves on disk (docs/reliability.md, section 1).

- One writer per output: `claimed(path)` holds an exclusive `flock` on `<parent>/.<name>.lock`,
  beside the output so that the output holds only what the writer made; a second writer is
  refused with one line naming the holder. The kernel drops the lock of a killed process.
- Nothing half written in place: `replacing(path)` writes a temporary sibling
  (`.<stem>.partial-<pid><suffix>`) and renames it onto `path`; `scratch(folder, name)` is
  a staging folder named the same way. What a killed writer left of either is removed by
  the next writer of that output, which says so. The rename is `replace_durably`: the
  file's bytes reach the disk before it, the folder's entry after it, so not even a power
  cut leaves `path` half written.
- Never through a symbolic link: a link where an output goes is refused, since writing
  through it would change a file outside the folder the user named (`refuse_links`).
- Nothing replaced without the user's flag: `check_targets(..., overwrite=False)`.
- A full disk, a read-only folder or a missing permission is one line (`OutputError`).

`writing_file` is all of them for a command that writes one file.
"""
from __future__ import annotations

import errno
import fcntl
import json
import logging
import os
import re
import shutil
import socket
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterable, Iterator

from gscan_ros.errors import GscanError

log = logging.getLogger(__name__)

PARTIAL = ".partial-"
_PARTIAL_NAME = re.compile(rf"\..+{re.escape(PARTIAL)}(\d+)(\.\w+)?")
# OSErrors of writing that are the machine's state, not a bug: reported as one line
# (ENOENT: a folder where no file can be made, such as /proc; ENAMETOOLONG: a name the
# file system refuses).
WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EACCES, errno.EPERM,
                          errno.ENOENT, errno.ENAMETOOLONG})


class OutputError(GscanError):
    """An output that must not be written now: held by another writer, a symbolic link,
    already there without --overwrite, or refused by the disk."""


def lock_path(path: str | os.PathLike) -> Path:
    """The lock file of output `path` (the same for every spelling of the path)."""
    real = Path(path).resolve()
    return real.parent / f".{real.name}.lock"


def partial_path(path: str | os.PathLike) -> Path:
    """This process's temporary sibling of `path`, with its suffix (format inference keeps working)."""
    path = Path(path)
    return path.with_name(f".{path.stem}{PARTIAL}{os.getpid()}{path.suffix}")


@contextmanager
def claimed(path: str | os.PathLike) -> Iterator[Path]:
    """Hold the exclusive lock of output `path` (a file or a folder) for the block.

    Partial files a dead writer of `path` left are removed first (a live one would hold
    the lock); an OSError of the disk (full, read-only, no permission) on `path`, in it or
    on its lock and partial files leaves the block as one `OutputError` line (one on an
    input read in the block is left as it is)."""
    path = Path(path)
    try:
        with _Lock(path):
            _remove_partials(path)
            yield path
    except OSError as exc:
        if exc.errno not in WRITE_ERRNOS or not _of_output(exc.filename, path):
            raise
        where = f" ({exc.filename})" if exc.filename and Path(exc.filename) != path else ""
        raise OutputError(f"while writing {path}: {exc.strerror}{where}") from None


def _of_output(filename: str | os.PathLike | None, path: Path) -> bool:
    """Whether an error on `filename` is one of writing `path`: the path itself, what lies
    in it, the folders made for it, or its lock and partial files (named after it, beside it)."""
    if filename is None:
        return True
    failed, out = Path(os.path.abspath(filename)), Path(os.path.abspath(path))
    if failed == out or out in failed.parents or failed in out.parents:
        return True
    return any(p.parent == out.parent and out.name in p.name for p in (failed, *failed.parents))


def check_targets(paths: Iterable[str | os.PathLike], *, overwrite: bool, flag: str = "--out") -> None:
    """Refuse, before any work, a symbolic link among the paths a writer will replace
    (always) and a path that exists already (unless `overwrite`)."""
    paths = [Path(p) for p in paths]
    refuse_links(paths)
    existing = [str(p) for p in paths if p.exists()]
    if existing and not overwrite:
        one = len(existing) == 1
        raise OutputError(f"{flag}: {', '.join(existing)} {'exists' if one else 'exist'} already; pass --overwrite "
                          f"to replace {'it' if one else 'them'}")


def file_in_the_way(folder: str | os.PathLike) -> Path | None:
    """The file at `folder` or at the nearest of its parents that exists, which keeps a
    writer from making `folder` or writing into it; None when nothing is in the way."""
    path = Path(folder)
    for p in (path, *path.parents):
        if p.exists():
            return None if p.is_dir() else p
    return None


def refuse_links(paths: Iterable[str | os.PathLike]) -> None:
    """Refuse a symbolic link among the paths a writer will replace or write into."""
    for path in paths:
        _refuse_link(Path(path))


@contextmanager
def replacing(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary sibling to write `path` to; it is renamed onto `path` when the
    block ends and removed if the block fails, so `path` is never half written. A symbolic
    link at `path` is refused (the rename would not write through it, but silently drop it)."""
    path = Path(path)
    _refuse_link(path)
    tmp = partial_path(path)
    try:
        yield tmp
        replace_durably(tmp, path)
    finally:
        _remove(tmp)


def replace_durably(tmp: str | os.PathLike, path: str | os.PathLike, keep_old_as: str | os.PathLike | None = None
                    ) -> None:
    """Rename the complete file `tmp` onto `path`, durably: `tmp` is synced to the disk
    before the rename and the folder after it, so a crash, power cut included, leaves the
    old `path` or the new one, whole. `keep_old_as`: the file `path` held is renamed there
    first (a crash between the two renames leaves `path` missing and the old file there)."""
    path = Path(path)
    fd = os.open(tmp, os.O_RDONLY | os.O_CLOEXEC)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
    if keep_old_as is not None and path.exists():
        os.replace(path, keep_old_as)
    os.replace(tmp, path)
    fd = os.open(path.parent, os.O_RDONLY | os.O_CLOEXEC)
    try:
        os.fsync(fd)
    except OSError as exc:  # a file system that cannot sync a folder (EINVAL) has nothing to sync
        if exc.errno != errno.EINVAL:
            raise
    finally:
        os.close(fd)


@contextmanager
def writing_file(path: str | os.PathLike, *, overwrite: bool, flag: str = "--out") -> Iterator[Path]:
    """Every rule for a command that writes one file: `claimed`, `check_targets`, then
    `replacing` (yields the temporary sibling to write)."""
    with claimed(path):
        check_targets([path], overwrite=overwrite, flag=flag)
        with replacing(path) as tmp:
            yield tmp


@contextmanager
def scratch(folder: str | os.PathLike, name: str) -> Iterator[Path]:
    """A new staging folder `<folder>/.<name>.partial-<pid>/`, removed with its content at
    the end of the block (what it holds is moved out before, when it is to be kept)."""
    path = partial_path(Path(folder) / name)
    path.mkdir()
    try:
        yield path
    finally:
        _remove(path)


def write_text(path: str | os.PathLike, text: str) -> Path:
    """`path` replaced by `text` (UTF-8) in one step (`replacing`)."""
    with replacing(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


# ------------------------------------------------------------------------------ internals
class _Lock:
    """An exclusive, non-blocking flock on a lock file holding its holder's description.

    The file is removed at release; a process that opened it just before and locks the
    removed file notices (the path no longer names its file) and locks the new one."""

    def __init__(self, output: Path):
        self.output = output
        self.path = lock_path(output)
        self._fd: int | None = None
        self._made: list[Path] = []  # parent folders created for the lock, deepest first

    def __enter__(self) -> "_Lock":
        parent = self.path.parent
        blocking = file_in_the_way(parent)
        if blocking is not None:
            raise OutputError(f"cannot write {self.output}: {blocking} is a file, not a folder")
        self._made = [p for p in (parent, *parent.parents) if not p.exists()]
        parent.mkdir(parents=True, exist_ok=True)
        try:
            self._fd = self._lock()
        except BaseException:
            self._remove_made()
            raise
        record = {"pid": os.getpid(), "host": socket.gethostname(), "since": time.strftime("%Y-%m-%d %H:%M:%S"),
                  "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]])[:300]}
        os.ftruncate(self._fd, 0)
        os.write(self._fd, json.dumps(record).encode())
        return self

    def _lock(self) -> int:
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = _holder(fd)
                os.close(fd)
                raise OutputError(f"{self.output} is being written by {holder}; wait for it to finish or "
                                  "write elsewhere") from None
            try:
                if os.fstat(fd).st_ino == os.stat(self.path).st_ino:
                    return fd
            except FileNotFoundError:
                pass
            os.close(fd)  # the previous holder removed the file we locked: lock the new one

    def __exit__(self, *exc_info) -> None:
        self.path.unlink(missing_ok=True)  # while still locked: no one can take the old file
        os.close(self._fd)
        self._remove_made()

    def _remove_made(self) -> None:
        for folder in self._made:
            try:
                folder.rmdir()
            except OSError:  # no longer empty: the writer's output is in it
                break


def _holder(fd: int) -> str:
    try:
        record = json.loads(os.pread(fd, 4096, 0))
        return f"pid {record['pid']} on {record['host']} since {record['since']} ({record['command']})"
    except (ValueError, KeyError, TypeError):
        return "another process"  # it has the lock but has not written its name yet


def _refuse_link(path: Path) -> None:
    if path.is_symlink():
        raise OutputError(f"{path} is a symbolic link (to {os.readlink(path)}); refusing to write through it")


def _remove_partials(path: Path) -> None:
    """Remove the partial files and staging folders of `path` (beside it, and inside it
    when it is a folder) that a writer which died left behind."""
    own = re.compile(rf"\.{re.escape(path.stem)}{re.escape(PARTIAL)}(\d+){re.escape(path.suffix)}")
    leftovers = [(p, own.fullmatch(p.name)) for p in path.parent.glob(f".*{PARTIAL}*")]
    if path.is_dir() and not path.is_symlink():
        leftovers += [(p, _PARTIAL_NAME.fullmatch(p.name)) for p in path.glob(f".*{PARTIAL}*")]
    for leftover, match in leftovers:
        if match is None or _alive(int(match.group(1))):
            continue
        size = _size(leftover)
        _remove(leftover)
        log.warning("removed %s (%.1f MB), left by an interrupted writer", leftover, size / 1e6)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        pass
    return True


def _size(path: Path) -> int:
    if path.is_dir() and not path.is_symlink():
        return sum(p.lstat().st_size for p in path.rglob("*"))
    return path.lstat().st_size


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        path.unlink(missing_ok=True)
