"""The `gscan-ros` parser class and argparse `type=` validators shared by every subcommand.

A bad value is caught while parsing, before a subcommand reads or writes anything, and
reported like every other gscan-ros error: one line naming the argument, exit status 1.
"""
from __future__ import annotations

import argparse
import functools
import math
from pathlib import Path
from typing import Callable

from gscan_ros.errors import GscanError
from gscan_ros.outputs import file_in_the_way
from gscan_ros.runtime import DEVICES, check_cpu_count


class ArgumentParser(argparse.ArgumentParser):
    """argparse with a one-line error and exit status 1 instead of a usage block and 2
    (subparsers inherit the class); `--help` is unchanged."""

    def error(self, message: str):
        self.exit(1, f"{self.prog}: error: {' '.join(message.split())} (see {self.prog} --help)\n")


# ------------------------------------------------------------------------------ numbers
def _parse(kind: type, text: str):
    try:
        value = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expects {'an integer' if kind is int else 'a number'}, got {text!r}") from None
    if kind is float and not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expects a finite number, got {text!r}")
    return value


def int_in(low: int, high: int | None = None) -> Callable[[str], int]:
    """An integer in [low, high] (no upper bound when high is None)."""
    def check(text: str) -> int:
        value = _parse(int, text)
        if value < low or (high is not None and value > high):
            bound = f">= {low}" if high is None else f"in [{low}, {high}]"
            raise argparse.ArgumentTypeError(f"must be an integer {bound}, got {text!r}")
        return value

    return check


def float_in(low: float, high: float, *, low_open: bool = False, high_open: bool = False) -> Callable[[str], float]:
    """A finite number between low and high (each end open or closed)."""
    def check(text: str) -> float:
        value = _parse(float, text)
        if value < low or value > high or (low_open and value == low) or (high_open and value == high):
            bound = f"{'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"
            raise argparse.ArgumentTypeError(f"must be a number in {bound}, got {text!r}")
        return value

    return check


positive_int = int_in(1)
nonnegative_int = int_in(0)


def add_device_argument(parser: argparse.ArgumentParser) -> None:
    """`--device auto|cpu|cuda` (default cpu; under torchrun, cuda means each process's own GPU)."""
    parser.add_argument("--device", choices=DEVICES, default="cpu",
                        help="where the network runs: cpu (default), cuda, or auto (cuda if torch sees a GPU)")


def worker_count(text: str) -> int:
    """A number of worker processes: at least 1, at most the CPUs available."""
    return _within_cpus(positive_int(text), "workers")


def thread_count(text: str) -> int:
    """A number of torch threads: 0 (torch's default) up to the CPUs available."""
    return _within_cpus(nonnegative_int(text), "threads")


def _within_cpus(count: int, what: str) -> int:
    try:
        return check_cpu_count(count, what)
    except GscanError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def nonblank(text: str) -> str:
    """Text with something in it (a command to send): blank text would silently mean "the default"."""
    if not text.strip():
        raise argparse.ArgumentTypeError("is empty")
    return text


def name_list(text: str) -> list[str]:
    """Comma-separated names (`--splits train,dev`): none of them empty."""
    names = [name.strip() for name in text.split(",")]
    if not all(names):
        raise argparse.ArgumentTypeError(f"{text!r} holds an empty name; expected names separated by commas")
    return names


# -------------------------------------------------------------------------------- paths
def _probing(check: Callable[[str], Path]) -> Callable[[str], Path]:
    """An empty path, or one that cannot even be looked at (a name too long, a folder not
    readable), is a usage error too: pathlib reads "" as the current folder and passes such
    an OSError on, which argparse would not catch."""
    @functools.wraps(check)
    def probe(text: str) -> Path:
        if not text.strip():  # an unset shell variable: not the current folder
            raise argparse.ArgumentTypeError(f"{text!r} is an empty path")
        try:
            return check(text)
        except OSError as exc:
            raise argparse.ArgumentTypeError(f"{text!r}: {exc.strerror or exc}") from None

    return probe


@_probing
def existing_file(text: str) -> Path:
    return _existing(text, "file")


@_probing
def existing_path(text: str) -> Path:
    """A file or directory that exists (a dataset.txt, its directory, a bag)."""
    path = Path(text)
    if not path.exists():
        raise argparse.ArgumentTypeError(f"{text!r} does not exist")
    return path


def dataset_path(text: str) -> Path:
    """An existing dataset: a dataset.txt, its folder, or a bag's folder (not one of its files)."""
    from gscan_ros.data.io import refuse_bag_file
    from gscan_ros.errors import GscanError

    path = existing_path(text)
    try:
        refuse_bag_file(path)
    except GscanError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return path


@_probing
def existing_dir(text: str) -> Path:
    """A directory that exists (a training run)."""
    return _existing(text, "directory")


def _existing(text: str, kind: str) -> Path:
    """`text` as a path to an existing `kind` ("file" or "directory"), else what it is instead."""
    path = Path(text)
    if not (path.is_dir() if kind == "directory" else path.is_file()):
        found = "is a directory" if path.is_dir() else "is a file" if path.exists() else "does not exist"
        raise argparse.ArgumentTypeError(f"{text!r} {found}, expected a {kind}")
    return path


@_probing
def output_dir(text: str) -> Path:
    """A directory to write into: existing, or creatable (no file in the way)."""
    path = Path(text)
    blocking = file_in_the_way(path)
    if blocking is not None:
        raise argparse.ArgumentTypeError(f"{str(blocking)!r} is a file, not a directory")
    return path


def output_file(*suffixes: str) -> Callable[[str], Path]:
    """A file to write, ending in one of `suffixes`, in a folder that exists; whether an
    existing file may be replaced is `gscan_ros.outputs.check_targets`'s call (it depends
    on --overwrite)."""
    @_probing
    def check(text: str) -> Path:
        path = Path(text)
        if path.suffix.lower() not in suffixes:
            raise argparse.ArgumentTypeError(f"must end in {' or '.join(suffixes)}, got {text!r}")
        if path.is_dir():
            raise argparse.ArgumentTypeError(f"{text!r} is a directory, expected a file name")
        if not path.parent.is_dir():
            raise argparse.ArgumentTypeError(f"folder {str(path.parent)!r} does not exist")
        return path

    return check


# ------------------------------------------------------------------------------ combinations
def refuse_unused(args: argparse.Namespace, names: tuple[str, ...], why: str) -> None:
    """Refuse the options among `names` that were given (their default is None) but that
    the chosen mode would not use; `why` completes "not used ..."."""
    given = [f"--{name.replace('_', '-')}" for name in names if getattr(args, name) is not None]
    if given:
        raise GscanError(f"{' and '.join(given)}: not used {why}")


def fill_defaults(args: argparse.Namespace, defaults: dict[str, object]) -> None:
    """Give the options left at None (not given) their defaults, once the combination is checked."""
    for name, value in defaults.items():
        if getattr(args, name) is None:
            setattr(args, name, value)
