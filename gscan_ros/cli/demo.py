"""`gscan-ros demo`: bring the stack up, give it commands, show and save the episodes.

Runs `gscan-ros bringup`'s nodes in this process with a recorder and drives them with
a GscanCommander (`gscan_ros.nodes.commander`). For each of
`--episodes` situations (the next one after a `reset_world` call) it sends the command
that the situation was generated with (so it is satisfiable) or `--command`, prints the
parse, the actions and whether they match the planner's demonstration, and writes one
bag with every episode and an animated GIF per episode with the word modules'
attention maps.
"""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from gscan_ros.cli.args import float_in, nonblank, output_dir, positive_int
from gscan_ros.cli.bringup import add_stack_arguments, resolve_stack_arguments, stack_options
from gscan_ros.errors import GscanError

DEFAULT_OUT_ROOT = Path("out/demo")
MAX_TIMEOUT_S = 86_400.0  # threading waits overflow on huge timeouts


def register(subparsers) -> None:
    p = subparsers.add_parser("demo", help="run the ROS stack on one command and show the episode",
                              description=__doc__.splitlines()[0])
    add_stack_arguments(p)
    p.add_argument("--command", dest="command_text", type=nonblank, default=None,
                   help="command to send (default: the situation's generated one)")
    p.add_argument("--out", type=output_dir, default=None,
                   help=f"output directory, new or empty (default: a new {DEFAULT_OUT_ROOT}/<date>_<time>)")
    p.add_argument("--overwrite", action="store_true", help="replace the bag and GIFs of an earlier demo in --out")
    p.add_argument("--episodes", type=positive_int, default=3,
                   help="episodes to run, each after a reset_world (default: 3)")
    p.add_argument("--timeout", type=float_in(0, MAX_TIMEOUT_S, low_open=True), default=120.0,
                   help="seconds to wait for each episode (default: 120)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    from gscan_ros.outputs import claimed, refuse_links

    ckpt = resolve_stack_arguments(args)
    episodes, graphs = _plan(args, ckpt)  # a bad dataset or --command fails here, before any output
    out = args.out or DEFAULT_OUT_ROOT / time.strftime("%Y%m%d_%H%M%S")
    with claimed(out):
        if out.exists() and any(out.iterdir()) and not args.overwrite:
            raise GscanError(f"--out {out} is not empty; pass --overwrite to replace an earlier demo there")
        refuse_links([out / "bag", *(out / f"episode_{i}.gif" for i in range(1, args.episodes + 1))])
        out.mkdir(parents=True, exist_ok=True)
        for gif in _earlier_gifs(out, args.episodes):  # an earlier demo's, beyond this one's episodes
            gif.unlink()
        return _run(args, out, episodes, graphs)


def _plan(args: argparse.Namespace, ckpt: dict) -> tuple[list, list]:
    """The situations the world node will serve (its own source, same arguments) and the
    command graph of each, parsed as the parser node will with the checkpoint's parser."""
    from gscan_ros.data.sources import episode_source
    from gscan_ros.language.registry import get_parser
    from gscan_ros.model.checkpoint import checkpoint_lexicon
    from gscan_ros.model.policy import require_grid

    source = episode_source(str(args.dataset) if args.dataset else "", args.split, args.index, args.seed,
                            args.grid_size)
    episodes = [source.next() for _ in range(args.episodes)]
    for episode in episodes:
        require_grid(episode.situation.grid_size, args.grid_size,
                     f"{args.dataset}: example {episode.example_id} of split {episode.split!r}")
    parser = get_parser(str(ckpt["parser"]), checkpoint_lexicon(ckpt))
    return episodes, [parser.parse(args.command_text or e.command) for e in episodes]  # CommandError for --command


def _earlier_gifs(out: Path, episodes: int) -> list[Path]:
    """The `episode_<n>.gif` files an earlier demo wrote in `out` that one of `episodes` does not replace."""
    return [p for p in out.glob("episode_*.gif")
            if p.is_file() and not p.is_symlink() and p.stem[8:].isdigit() and int(p.stem[8:]) > episodes]


def _run(args: argparse.Namespace, out: Path, episodes: list, graphs: list) -> int:
    """The demo proper, writing into `out` (claimed)."""
    from gscan_ros.nodes.commander import GscanCommander
    from gscan_ros.nodes.stack import Stack

    options = stack_options(args, record=out / "bag", record_images=True)
    matched = 0
    with Stack(options) as stack:
        words = list(dict.fromkeys(node.word for g in graphs for node in g.nodes))
        with GscanCommander("demo_operator", attention_words=words) as commander:
            stack.start()
            stack.wait_until_recording()
            commander.wait_until_ready()
            for i, (episode, graph) in enumerate(zip(episodes, graphs), start=1):
                if i > 1:
                    commander.reset_world(args.timeout)
                # Sent as typed: parser_node maps a paraphrase to its gSCAN command.
                result = commander.run_episode(graph.typed or graph.command, args.timeout)
                if not result.finished:
                    raise GscanError(f"episode {i} {result.outcome} without <eos> after {args.timeout:.0f} s; "
                                     f"status: {result.status[-3:]}")
                commander.wait_for_status(f"episode_recorder_node: recorded episode {i - 1} ", args.timeout)
                print(f"--- episode {i} of {len(episodes)}")
                matched += _report(graph, episode, result, out / f"episode_{i}.gif")
    print(f"matched the planner in {matched} of {len(episodes)} episodes")
    print(f"bag:      {out / 'bag'}")
    print(f"output:   {out.resolve()}")
    return 0


def _failure(episode, graph, result, planned) -> str:
    """What kind of failure the episode's actions are against the planner's (`gscan_ros.training.failures`)."""
    from dataclasses import replace

    from gscan_ros.nodes.commander import Outcome
    from gscan_ros.training.failures import FAILURE_KINDS, classify_failure, failure_label

    gold = replace(episode, command=graph.command, actions=tuple(planned))
    kind = classify_failure(gold, result.moves, stopped=result.outcome is not Outcome.MAX_STEPS)
    return f"{failure_label(kind)} ({FAILURE_KINDS[kind]})"


def _report(graph, episode, result, gif_path: Path) -> bool:
    """Print one episode (a GscanCommander EpisodeResult), write its GIF; True when the actions equal the planner's."""
    from gscan_ros.outputs import replacing
    from gscan_ros.world import demonstrate
    from gscan_ros.world.render import render_frames, save_gif
    from msg_adapters import cdr_to_attention

    actions = result.actions
    moves = [a.token for a in result.moves]
    try:
        planned = demonstrate(episode.situation, graph.command)
        gold = [a.token for a in planned]
    except GscanError as exc:
        gold, why = None, str(exc)
    if graph.typed is not None:
        from gscan_ros.language import canonicalize

        print(f"typed:    {graph.typed}")
        for mapping in canonicalize(graph.typed).mappings:
            print(f"          {mapping}")
    print(f"command:  {graph.command}")
    print(f"parse ({graph.parser}):")
    print("  " + graph.pretty().replace("\n", "\n  "))
    print(f"actions:  {', '.join(moves) or '(none)'}  [{len(moves)} actions, then <eos>]")
    if gold is None:
        print(f"planner:  no demonstration ({why})")
    else:
        print(f"planner:  {', '.join(gold)}  [{len(gold)} actions]")
        verdict = "yes, exact match" if moves == gold else "no, " + _failure(episode, graph, result, planned)
        print(f"match:    {verdict}")
    attention = [
        {word: cdr_to_attention(maps[t], grid_size=episode.situation.grid_size)
         for word, maps in result.attention.items() if t < len(maps)}
        for t in range(len(actions))
    ]
    with replacing(gif_path) as tmp:
        save_gif(render_frames(episode.situation, actions, attention=attention), tmp)
    print(f"gif:      {gif_path}")
    return moves == gold
