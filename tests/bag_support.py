"""Episodes for the bag tests: random but valid (walk / turn / stay, never off the grid), and
damaged copies of bags (truncated, edited bytes, killed writer)."""
from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

from mcap.reader import make_reader

from gscan_ros.data.episode import Episode
from gscan_ros.world.types import COLORS, SHAPES, Action, Heading, Position, Situation, WorldObject

SPLITS = ("train", "test", "visual")
TESTS = Path(__file__).parent


def _route(rng: random.Random, start: Position, heading: Heading, length: int) -> tuple[Action, ...]:
    row, col, actions = start.row, start.col, []
    for _ in range(length):
        action = rng.choice((Action.WALK, Action.WALK, Action.TURN_LEFT, Action.TURN_RIGHT, Action.STAY))
        if action is Action.WALK:
            d_row, d_col = heading.delta
            if not (0 <= row + d_row < 6 and 0 <= col + d_col < 6):
                action = Action.TURN_LEFT
            else:
                row, col = row + d_row, col + d_col
        if action is Action.TURN_LEFT:
            heading = Heading((heading - 1) % 4)
        elif action is Action.TURN_RIGHT:
            heading = Heading((heading + 1) % 4)
        actions.append(action)
    return tuple(actions)


def make_episode(rng: random.Random, index: int, max_len: int = 20) -> Episode:
    cells = rng.sample([Position(r, c) for r in range(6) for c in range(6)], 4)
    objects = tuple(
        WorldObject(shape, rng.choice(COLORS), rng.randint(1, 4), cell)
        for shape, cell in zip(SHAPES, cells[1:])
    )
    target = objects[0]
    situation = Situation(
        agent_position=cells[0],
        agent_direction=Heading.EAST,
        placed_objects=objects,
        target_object=target,
        direction_to_target=None,
        distance_to_target=abs(target.position.row - cells[0].row) + abs(target.position.col - cells[0].col),
    )
    actions = _route(rng, cells[0], Heading.EAST, rng.randint(0, max_len))
    command = f"walk to a {target.color} {target.shape}"
    return Episode(command, situation, actions, split=SPLITS[index % len(SPLITS)], example_id=index, meta={"n": index})


def make_episodes(count: int, seed: int = 0, max_len: int = 20) -> list[Episode]:
    rng = random.Random(seed)
    return [make_episode(rng, i, max_len) for i in range(count)]


# ------------------------------------------------------------------------ damaged bags
def mcap_file(bag: Path) -> Path:
    return bag / f"{bag.name}_0.mcap"


def copy_bag(src: Path, dst: Path, content: bytes) -> Path:
    """Bag `dst` with `src`'s metadata.yaml and `content` as its MCAP file."""
    dst.mkdir(parents=True)
    (dst / "metadata.yaml").write_text(
        (src / "metadata.yaml").read_text().replace(mcap_file(src).name, mcap_file(dst).name)
    )
    mcap_file(dst).write_bytes(content)
    return dst


def truncated_copy(src: Path, dst: Path, keep: int) -> Path:
    return copy_bag(src, dst, mcap_file(src).read_bytes()[:keep])


def damaged_copy(src: Path, dst: Path, edit) -> Path:
    """A copy whose MCAP bytes went through `edit(bytearray)`."""
    data = bytearray(mcap_file(src).read_bytes())
    edit(data)
    return copy_bag(src, dst, bytes(data))


def data_end(bag: Path) -> int:
    """File offset after the last chunk (its message indexes and the summary follow)."""
    with open(mcap_file(bag), "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    return max(c.chunk_start_offset + c.chunk_length for c in chunks)


WRITER = textwrap.dedent(
    """
    import sys
    sys.path.insert(0, {tests!r})
    import itertools, random, time
    from bag_support import make_episode
    from gscan_ros.data.bag import BagWriter

    writer = BagWriter({bag!r}, chunk_size=2048).open()
    rng = random.Random({seed})
    for i in itertools.count():  # until killed
        writer.write_episode(make_episode(rng, i))
        if i + 1 == {flush_at}:
            writer.flush()
        if i + 1 == {flush_at} + {extra}:  # some more chunks are out, one is being filled
            print("flushed", {flush_at}, flush=True)
            time.sleep(600)
    """
)


def kill_writer(bag: Path, seed: int = 11, flush_at: int = 41, extra: int = 9) -> int:
    """Write make_episodes(…, seed) into `bag` in a child process, flush after `flush_at`
    episodes, write `extra` more and SIGKILL it (a chunk in progress, no summary,
    metadata.yaml still `recording`); returns the number of episodes flushed."""
    child = subprocess.Popen(
        [sys.executable, "-c",
         WRITER.format(tests=str(TESTS), bag=str(bag), seed=seed, flush_at=flush_at, extra=extra)],
        stdout=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        line = child.stdout.readline()
        assert line.startswith("flushed"), line
        os.killpg(child.pid, signal.SIGKILL)
    finally:
        child.kill()
        child.wait(timeout=30)
    return int(line.split()[1])
