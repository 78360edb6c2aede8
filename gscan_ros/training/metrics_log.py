"""A run's `metrics.jsonl`: one JSON record per line, appended as the run goes.

A run killed while writing can leave its last line torn (half written). Readers skip
a line that is not a whole record, with one warning per file; the writer cuts such a
tail off before it appends, and writes each record as one whole line, so a resumed
run's records never glue onto the torn one. A run resumed from its last checkpoint first
drops the records logged after it (`rewind`): those updates are trained again, so the
curve has each update once, however long after a checkpoint the run was stopped.
"""
from __future__ import annotations

import json
import logging
import os
from pathlib import Path

from gscan_ros.errors import GscanError

log = logging.getLogger(__name__)
_warned: set[Path] = set()


def read_events(path: str | os.PathLike) -> list[dict]:
    """The records of a metrics.jsonl (none when it does not exist), torn lines skipped;
    GscanError when it cannot be read."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except FileNotFoundError:
        return []
    except OSError as exc:  # a folder in its place, no permission
        raise GscanError(f"cannot read {path}: {exc.strerror}") from None
    events, torn = [], 0
    for line in text.splitlines():
        try:
            record = json.loads(line)
        except ValueError:
            record = None
        if isinstance(record, dict):
            events.append(record)
        else:
            torn += 1
    if torn:
        _warn_once(path, f"{path}: skipped {torn} line(s) that are not whole records (torn by a killed run)")
    return events


def append_event(path: str | os.PathLike, record: dict) -> None:
    """Append `record` as one line, in one write, after cutting off a torn last line."""
    data = (json.dumps(record) + "\n").encode()
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_APPEND | os.O_CLOEXEC, 0o644)
    try:
        _cut_torn_tail(Path(path), fd)
        os.write(fd, data)
    finally:
        os.close(fd)


def rewind(path: str | os.PathLike, step: int) -> int:
    """Drop the records of updates after `step` (a resume from the checkpoint at `step`);
    returns how many were dropped. The file is replaced in one step."""
    from gscan_ros.outputs import write_text

    events = read_events(path)
    kept = [e for e in events if not isinstance(e.get("step"), (int, float)) or e["step"] <= step]
    if len(kept) < len(events):
        write_text(path, "".join(json.dumps(e) + "\n" for e in kept))
    return len(events) - len(kept)


def _cut_torn_tail(path: Path, fd: int) -> None:
    size = os.fstat(fd).st_size
    if not size or os.pread(fd, 1, size - 1) == b"\n":
        return
    tail = os.pread(fd, min(size, 1 << 20), max(size - (1 << 20), 0))  # records are a few kB
    keep = size - len(tail) + tail.rfind(b"\n") + 1
    os.ftruncate(fd, keep)
    _warn_once(path, f"{path}: removed a torn last line ({size - keep} bytes) left by a killed run")


def _warn_once(path: Path, message: str) -> None:
    if path not in _warned:
        _warned.add(path)
        log.warning(message)


def finished_end(events: list[dict], cfg) -> dict | None:
    """The last "end" event when it closed the training (budget reached, target reached, or
    out of its time budget) and no later start reopened it; else None."""
    for event in reversed(events):
        kind = event.get("event")
        if kind == "start":
            return None
        if kind == "end":
            out_of_time = cfg.max_minutes and event.get("elapsed_s", 0) >= cfg.max_minutes * 60
            return event if event["step"] >= cfg.max_updates or event.get("reached_target") or out_of_time else None
    return None
