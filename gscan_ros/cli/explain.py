"""`gscan-ros explain`: what the network thinks, as the paper's figures and as numbers.

- `explain "COMMAND" --out F.png` : Fig. 3 — the world, each word module's map from leaves
  to root under the parse tree, and the size-ordering map (-att_small + att_big)/2 when
  the command has a size word; `--step T` for step T, `--gif` (or F.gif) for every step.
- `explain --progression RUN_DIR "COMMAND" --out F.png` : Fig. 4 — rows are words,
  columns the run's step_<N>.pt snapshots (train with --set snapshot_every=N).
- `explain --metrics --data DS` : per split, step-0 localization (how often the map the
  noun phrase passes up peaks on the target's cell), the Spearman correlation between
  the size-ordering value at each object of the referred shape and its size, how often
  the size word's map ranks the target first, the noun's map by colour and how flat each
  size head is (docs/interpretability.md); with `--progression RUN_DIR`, the numbers
  along the snapshots.
The situation comes from `--data DS --split S --index I`, `--situation FILE.json` or
`--seed N` (a random world where the command has a unique referent; the default, seed 0).
"""
from __future__ import annotations

import argparse
from pathlib import Path

from gscan_ros.cli.args import (
    add_device_argument,
    dataset_path,
    existing_dir,
    existing_file,
    fill_defaults,
    int_in,
    nonnegative_int,
    output_file,
    positive_int,
    refuse_unused,
    thread_count,
)
from gscan_ros.errors import GscanError
from gscan_ros.user_files import read_json

MAX_FPS = 50


def register(subparsers) -> None:
    p = subparsers.add_parser("explain", help="attention figures (paper Fig. 3/4) and interpretability numbers",
                              description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("command_text", nargs="?", metavar="COMMAND",
                   help="the command (default: the example's with --data, a random one with --seed)")
    source = p.add_mutually_exclusive_group()
    source.add_argument("--data", type=dataset_path, metavar="DS",
                        help="dataset.txt, its directory or a bag: the situation (or the --metrics episodes)")
    source.add_argument("--situation", type=existing_file, metavar="FILE.json",
                        help="a gSCAN situation JSON (or an object with a 'situation' key)")
    source.add_argument("--seed", type=nonnegative_int, metavar="N",
                        help="a random situation for the command (default: seed 0)")
    p.add_argument("--split", default=None, help="split of --data (default: test)")
    p.add_argument("--index", type=nonnegative_int, default=None, help="example index in --split (default: 0)")
    p.add_argument("--checkpoint", type=existing_file, metavar="CKPT", help="checkpoint (default: the shipped model)")
    when = p.add_mutually_exclusive_group()
    when.add_argument("--step", type=nonnegative_int, default=None, metavar="T",
                      help="the decoding step to show (default: 0, the initial state)")
    when.add_argument("--gif", action="store_true",
                      help="an animated GIF with every step (also implied by --out F.gif)")
    p.add_argument("--out", type=output_file(".png", ".gif"), metavar="FILE", help="the figure, .png or .gif")
    p.add_argument("--overwrite", action="store_true", help="replace FILE if it exists")
    p.add_argument("--fps", type=int_in(1, MAX_FPS), default=None, help="GIF frames per second (default: 2)")
    p.add_argument("--progression", type=existing_dir, metavar="RUN_DIR",
                   help="a training run with step_<N>.pt snapshots: Fig. 4, or the metrics along training")
    p.add_argument("--max-columns", type=int_in(2, 40), default=None,
                   help="--progression: at most this many snapshots, evenly spaced (default: 8)")
    p.add_argument("--metrics", action="store_true", help="print localization and size-ordering numbers for --data")
    p.add_argument("--splits", nargs="+", metavar="SPLIT", help="--metrics: splits (default: every test split present)")
    p.add_argument("--max-examples", type=nonnegative_int, default=None, metavar="N",
                   help="--metrics: seeded subset of N episodes per split, as `evaluate --max-examples` (0 = all; "
                        "default: 1000)")
    p.add_argument("--batch-size", type=positive_int, default=None,
                   help="--metrics: episodes per batch (default: 512)")
    p.add_argument("--threads", type=thread_count, default=0,
                   help="torch threads (0 = torch default; at most the CPUs available)")
    add_device_argument(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from gscan_ros.runtime import configure_torch, resolve_device

    _check_combination(args)
    configure_torch(args.threads)
    args.device = resolve_device(args.device)  # 'auto' named once, before any work
    if args.metrics:
        return _metrics(args)
    from gscan_ros.outputs import writing_file

    with writing_file(args.out, overwrite=args.overwrite) as tmp:
        return (_progression if args.progression else _figure)(args, tmp)


DEFAULTS = {"split": "test", "index": 0, "fps": 2, "max_columns": 8, "max_examples": 1000, "batch_size": 512}


def _check_combination(args: argparse.Namespace) -> None:
    """Arguments that only make sense together (one line, exit 1, before any work); then
    the defaults of the options the mode uses."""
    _check_modes(args)
    fill_defaults(args, DEFAULTS)


def _check_modes(args: argparse.Namespace) -> None:
    if args.progression and args.checkpoint:
        raise GscanError("--progression reads the run's own snapshots; it takes no --checkpoint")
    if not args.progression:
        refuse_unused(args, ("max_columns",), "without --progression")
    if args.metrics:
        if args.data is None:
            raise GscanError("--metrics needs --data DS (the episodes to measure on)")
        if args.command_text or args.out or args.gif or args.overwrite:
            raise GscanError("--metrics prints numbers: it takes no COMMAND, --out, --gif or --overwrite")
        refuse_unused(args, ("step", "fps", "split", "index"), "by --metrics (it reads --splits of --data)")
        return
    refuse_unused(args, ("splits", "max_examples", "batch_size"), "without --metrics")
    if args.data is None:
        refuse_unused(args, ("split", "index"), "without --data")
    if args.out is None:
        raise GscanError("--out FILE (.png or .gif) is required for a figure")
    is_gif = args.out.suffix.lower() == ".gif"
    if args.gif and not is_gif:
        raise GscanError(f"--gif writes a .gif, but --out is {args.out}")
    if args.progression and (args.gif or is_gif):
        raise GscanError("--progression draws one .png (snapshots as columns); no GIF")
    if is_gif and args.step is not None:
        raise GscanError(f"--step draws one step as a .png; the GIF {args.out} shows every step")
    if not is_gif:
        refuse_unused(args, ("fps",), f"for the .png {args.out}")
    args.step = args.step or 0
    if args.situation and not args.command_text:
        raise GscanError("--situation needs a COMMAND")


def _episode(args: argparse.Namespace, grid_size: int):
    """(command, situation, gold actions or None) from --data / --situation / --seed."""
    from gscan_ros.world.types import Situation

    if args.data is not None:
        from gscan_ros.data.io import iter_episodes

        episode = next((e for i, e in enumerate(iter_episodes(args.data, [args.split])) if i == args.index), None)
        if episode is None:
            raise GscanError(f"{args.data}: split {args.split!r} has no example {args.index}")
        same = args.command_text in (None, episode.command)
        return args.command_text or episode.command, episode.situation, list(episode.actions) if same else None
    if args.situation is not None:
        data = read_json(args.situation, f"--situation {args.situation}", GscanError)
        try:
            situation = Situation.from_json(data["situation"] if isinstance(data, dict) and "situation" in data
                                            else data)
        except GscanError as exc:
            raise GscanError(f"--situation {args.situation}: {exc}") from None
        return args.command_text, situation, None
    from gscan_ros.data.sources import sample_episode

    episode = sample_episode(args.seed or 0, grid_size, args.command_text)
    return episode.command, episode.situation, list(episode.actions)


def _setup(args: argparse.Namespace, policy):
    """(command, situation with the command's referent as target, gold actions or None)."""
    from gscan_ros.analysis.explain import require_attention, with_referent

    require_attention(policy)
    command, situation, actions = _episode(args, policy.grid_size)
    policy.require_grid(situation.grid_size, "the situation")
    return command, with_referent(situation, command), actions


def _model_name(args: argparse.Namespace, policy) -> str:
    name = args.checkpoint.name if args.checkpoint else "shipped model"
    return f"{name}, update {policy.metadata.get('step', '?')}"


def _figure(args: argparse.Namespace, path: Path) -> int:
    """Fig. 3 (one step) or its GIF, written to `path`."""
    from gscan_ros.analysis.explain import trace
    from gscan_ros.analysis.figures import figure_rgb, panel_titles, save_figure, step_figure
    from gscan_ros.model.policy import Policy
    from gscan_ros.world.render import save_gif

    policy = Policy.from_checkpoint(args.checkpoint, device=args.device)
    command, situation, _ = _setup(args, policy)
    gif = args.gif or args.out.suffix.lower() == ".gif"
    tr = trace(policy, situation, command, until=None if gif else args.step)
    title = f"{command}   ({_model_name(args, policy)})"
    if gif:
        import matplotlib.pyplot as plt

        frames = []
        for t in range(len(tr.steps)):
            fig = step_figure(tr, t, title)
            frames.append(figure_rgb(fig))
            plt.close(fig)
        save_gif(frames, path, fps=args.fps)
        print(f"wrote {args.out}: {len(frames)} steps, panels: {', '.join(panel_titles(tr, 0))}")
        return 0
    if args.step >= len(tr.steps):
        raise GscanError(f"the model ended the episode (<eos>) at step {len(tr.steps) - 1}; "
                         f"--step must be at most {len(tr.steps) - 1}")
    save_figure(step_figure(tr, args.step, title), path)
    print(f"wrote {args.out}: step {args.step} (next: {tr.steps[args.step].action.token}), "
          f"panels: {', '.join(panel_titles(tr, args.step))}")
    return 0


def _progression(args: argparse.Namespace, path: Path) -> int:
    """Fig. 4 (the maps along a training run), written to `path`."""
    from gscan_ros.analysis.explain import evenly, snapshots, trace
    from gscan_ros.analysis.figures import progression_figure, save_figure
    from gscan_ros.model.policy import Policy
    from gscan_ros.world import demonstrate

    paths = evenly(snapshots(args.progression), args.max_columns)
    columns, graph = [], None
    for i, (update, checkpoint) in enumerate(paths):
        policy = Policy.from_checkpoint(checkpoint, device=args.device)
        if i == 0:
            command, situation, actions = _setup(args, policy)
            if args.step and actions is None:
                actions = demonstrate(situation, command)  # every snapshot sees the same states
        tr = trace(policy, situation, command, actions=actions if args.step else None, until=args.step)
        if args.step >= len(tr.steps):
            raise GscanError(f"the demonstration has {len(tr.steps) - 1} actions; --step must be at most that")
        em = (policy.metadata.get("metrics") or {}).get("dev_exact_match")
        columns.append((f"update {update}" + ("" if em is None else f"\ndev EM {em:.0f}%"), tr.steps[args.step]))
        graph = tr.graph
    subtitle = (f"maps at step {args.step} along the training run {args.progression}: rows are words, columns "
                "snapshots;\neach map scaled from its minimum to its maximum (noted: ~1/cells = uniform)")
    save_figure(progression_figure(columns, graph, command, subtitle), path)
    print(f"wrote {args.out}: {len(columns)} snapshots (updates {', '.join(str(u) for u, _ in paths)})")
    return 0


def _metrics(args: argparse.Namespace) -> int:
    from gscan_ros.analysis.explain import (
        evenly,
        metrics_table,
        noun_colours,
        noun_colours_table,
        progression_metrics,
        progression_table,
        size_heads,
        size_heads_table,
        snapshots,
        step0_readings,
        summarize,
    )
    from gscan_ros.data.io import select_test_episodes
    from gscan_ros.model.policy import Policy

    episodes = select_test_episodes(args.data, args.splits, args.max_examples)  # as evaluate's seed 0
    if args.progression:
        paths = evenly(snapshots(args.progression), args.max_columns)
        rows = progression_metrics(paths, episodes, args.batch_size, device=args.device)
        print(f"{len(episodes)} episodes of {args.data}, snapshots of {args.progression}:")
        print(progression_table(rows), end="")
        return 0
    policy = Policy.from_checkpoint(args.checkpoint, device=args.device)
    readings = step0_readings(policy, episodes, args.batch_size)
    print(f"{_model_name(args, policy)} on {args.data} (step 0):")
    print(metrics_table(summarize(readings)), end="")
    print("\nThe noun's map at each object of its shape, by colour, relative to the scene's highest such value "
          "(mean over objects, in scenes with two or more; all splits above):")
    print(noun_colours_table(noun_colours(readings)), end="")
    heads = size_heads(readings)
    if heads:
        print("\nThe size words' heads (big|small share one module): how far each map is from flat, over the "
              "episodes with a size word; ~0 is a head that passes nothing (docs/interpretability.md):")
        print(size_heads_table(heads), end="")
    return 0
