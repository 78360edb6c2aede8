"""`gscan-ros render`: draw one dataset example as a PNG (initial state) or an animated GIF."""
from __future__ import annotations

import argparse

from gscan_ros.cli.args import existing_path, float_in, int_in, nonnegative_int, output_file

MAX_FPS = 50  # save_gif's shortest frame is 20 ms
MIN_FPS = 0.01  # 100 s a frame; a GIF frame lasts at most 655.35 s
DEFAULT_FPS = 4.0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "render",
        help="render a dataset example to .png or .gif",
        description="Render an example of a dataset: .png shows the initial state, .gif plays its "
                    "target actions.",
    )
    p.add_argument("dataset", type=existing_path, metavar="DATASET",
                   help="dataset.txt, a directory holding it, or a bag directory")
    p.add_argument("--split", default="test", help="split name (default: test, as for demo, bringup and explain)")
    p.add_argument("--index", type=nonnegative_int, default=0, help="example index within the split (default: 0)")
    p.add_argument("--out", required=True, type=output_file(".png", ".gif"), metavar="FILE",
                   help="output .png or .gif, in an existing folder")
    p.add_argument("--overwrite", action="store_true", help="replace FILE if it exists")
    p.add_argument("--fps", type=float_in(MIN_FPS, MAX_FPS), default=None,
                   help=f"GIF frames per second, {MIN_FPS}-{MAX_FPS} (default: {DEFAULT_FPS:g}); a .png has none")
    p.add_argument("--cell-px", type=int_in(8, 400), default=40, help="pixels per grid cell, 8-400 (default: 40)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from gscan_ros.data.io import iter_episodes
    from gscan_ros.errors import GscanError
    from gscan_ros.outputs import writing_file
    from gscan_ros.world.render import render_frames, save_gif, save_png

    gif = args.out.suffix.lower() == ".gif"
    if args.fps is not None and not gif:
        raise GscanError(f"--fps sets a GIF's frame rate; {args.out} is a .png (one frame)")
    with writing_file(args.out, overwrite=args.overwrite) as tmp:
        episode = next((e for i, e in enumerate(iter_episodes(args.dataset, [args.split])) if i == args.index), None)
        if episode is None:
            raise GscanError(f"split {args.split!r} has no example {args.index}")
        frames = render_frames(episode.situation, episode.actions, cell_px=args.cell_px)
        if gif:
            save_gif(frames, tmp, fps=args.fps or DEFAULT_FPS)
        else:
            save_png(frames[0], tmp)
    print(f"wrote {args.out}: {episode.command!r}, {len(episode.actions)} actions")
    return 0
