"""`gscan-ros`: the one command-line entry point; each subcommand lives in its own module.

A subcommand module defines `register(subparsers)` (adds its parser and sets
`func=run`) and `run(args) -> int`. Modules import heavy libraries (torch, rclpy)
inside `run`, so `gscan-ros --help` stays fast. Any `GscanError` becomes one line on
stderr and exit status 1; so does a bad argument (`cli.args`: the parser class and the
validators every subcommand uses for its numbers and paths).
"""
from __future__ import annotations

import argparse
import errno
import importlib
import os
import sys

from gscan_ros import __version__
from gscan_ros.cli.args import ArgumentParser
from gscan_ros.errors import GscanError

# Subcommand modules, in help order. A module missing here is simply not offered.
SUBCOMMANDS = (
    "generate",
    "augment",
    "verify",
    "render",
    "parse",
    "train",
    "evaluate",
    "experiment",
    "report",
    "explain",
    "replay",
    "bag",
    "demo",
    "bringup",
)

# What standard output meets when the file or device it was sent to takes no more (> /dev/full).
_FULL_DISK = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG})


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(
        prog="gscan-ros",
        description="gSCAN grounded command following with compositional networks (Kuo et al. 2021).",
    )
    parser.add_argument("--version", action="version", version=f"gscan-ros {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in SUBCOMMANDS:
        try:
            module = importlib.import_module(f"gscan_ros.cli.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"gscan_ros.cli.{name}":
                continue
            raise
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    name = " ".join(filter(None, (args.command, getattr(args, "bag_command", None))))  # "bag repair"
    try:
        code = int(args.func(args) or 0)
        sys.stdout.flush()  # what is left fails here, not in the interpreter's flush at exit
        return code
    except GscanError as exc:
        print(f"gscan-ros {name}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"gscan-ros {name}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 0
    except OSError as exc:
        if exc.filename is not None and exc.strerror:  # an input that cannot be read (no permission, ...)
            print(f"gscan-ros {name}: error: {exc.filename}: {exc.strerror}", file=sys.stderr)
            return 1
        if exc.errno not in _FULL_DISK:  # no file named: a bug, with its traceback
            raise
        print(f"gscan-ros {name}: error: cannot write to standard output: {exc.strerror}", file=sys.stderr)
        _discard_stdout()
        return 1


def _discard_stdout() -> None:
    """Point standard output at /dev/null: what is left in its buffer would fail again, with a
    traceback, in the interpreter's flush at exit."""
    os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


if __name__ == "__main__":
    sys.exit(main())
