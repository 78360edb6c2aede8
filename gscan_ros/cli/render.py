"""`gscan-ros render`: draw one dataset example as a PNG (initial state) or an animated GIF."""
from __future__ import annotations

import argparse


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "render",
        help="render a dataset example to .png or .gif",
        description="Render an example of a dataset: .png shows the initial state, .gif plays its "
                    "target actions.",
    )
    p.add_argument("dataset", metavar="DATASET", help="dataset.txt, a directory holding it, or a bag directory")
    p.add_argument("--split", default="train", help="split name (default: train)")
    p.add_argument("--index", type=int, default=0, help="example index within the split (default: 0)")
    p.add_argument("--out", required=True, metavar="FILE", help="output .png or .gif")
    p.add_argument("--fps", type=float, default=4.0, help="GIF frames per second (default: 4)")
    p.add_argument("--cell-px", type=int, default=40, help="pixels per grid cell (default: 40)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from gscan_ros.data.io import iter_episodes
    from gscan_ros.errors import GscanError
    from gscan_ros.world.render import render_frames, save_gif, save_png

    suffix = Path(args.out).suffix.lower()
    if suffix not in (".png", ".gif"):
        raise GscanError(f"--out must end in .png or .gif, got {args.out!r}")
    if args.index < 0:
        raise GscanError(f"--index must be >= 0, got {args.index}")
    episode = next((e for i, e in enumerate(iter_episodes(args.dataset, [args.split])) if i == args.index), None)
    if episode is None:
        raise GscanError(f"split {args.split!r} has no example {args.index}")
    frames = render_frames(episode.situation, episode.actions, cell_px=args.cell_px)
    path = save_gif(frames, args.out, fps=args.fps) if suffix == ".gif" else save_png(frames[0], args.out)
    print(f"wrote {path}: {episode.command!r}, {len(episode.actions)} actions")
    return 0
