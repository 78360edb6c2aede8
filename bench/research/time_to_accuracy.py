"""Time to accuracy: train a config from scratch until a dev exact match target or a time limit.

    .venv/bin/python bench/research/time_to_accuracy.py --config configs/semantic_fast.yaml \
        [--target 95] [--max-minutes 30] [--seed 0] [--threads 2] [--data DIR] \
        [--set key=value ...] [--out RUN_DIR] [--resume | --overwrite]

Without --data, the full compositional set is generated once (seed 0) into
`data_gen/comp` and reused afterwards. Validation is closed loop on a fixed, seeded
1,000-episode subset of dev (seed = the run's seed) every `--validate-every` updates.
The clock is the trainer's: training and validation time, not data loading; a run
resumed with `--resume` keeps counting from where it stopped. With seed screening
(`screen_seeds` in the config) the clock and the ex/s include every candidate's updates;
the updates reported are the kept candidate's.

One row per validation, then as the last line exactly one of
    time-to-accuracy: reached 95.0% dev exact match after U updates, M.M minutes (X ex/s)
    time-to-accuracy: not reached (best B.B% after U updates, M.M minutes)

`--seeds S1 S2 ...` runs one seed after the other into RUN_DIR/s<seed> and ends with the
median and range over the seeds of the updates and minutes to 90 % and to the target (a
seed that did not get there counts as slower than every seed that did), as the last line
    time-to-accuracy: median over N seeds reached 95.0% after U updates, M.M minutes (K of N reached)
or  time-to-accuracy: median over N seeds not reached (K of N reached)

`--from-runs RUN_DIR ...` trains nothing: it reads runs already trained (e.g. the paper
plan's `results/paper/semantic_faithful_s*`, which validate on 500 dev episodes every
1,000 updates) and prints the same summary from their `metrics.jsonl`.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

DEFAULT_DATA = Path("data_gen/comp")
DEV_EPISODES = 1000


def ensure_data(data: str | None) -> str:
    if data is not None:
        return data
    if not (DEFAULT_DATA / "dataset.txt").exists():
        from gscan_ros.data.generate import GenerationConfig, generate_dataset

        print(f"generating the full compositional set into {DEFAULT_DATA} (once) ...", flush=True)
        generate_dataset(DEFAULT_DATA, GenerationConfig(seed=0), workers=1, progress=False)
    return str(DEFAULT_DATA)


def throughput(metrics_path: Path) -> float:
    """Mean training examples/s over the run's log lines."""
    rates = [r["examples_per_s"] for r in map(json.loads, metrics_path.read_text().splitlines())
             if r.get("event") == "train"]
    return sum(rates) / len(rates) if rates else 0.0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", metavar="FILE", help="training config (YAML); required unless --from-runs")
    ap.add_argument("--target", type=float, default=95.0, metavar="PERCENT", help="dev exact match to reach (95)")
    ap.add_argument("--max-minutes", type=float, default=30.0, metavar="M", help="time limit (30)")
    seeds = ap.add_mutually_exclusive_group()
    seeds.add_argument("--seed", type=int, default=0, help="run seed (0)")
    seeds.add_argument("--seeds", type=int, nargs="+", metavar="S",
                       help="several runs, one per seed, into RUN_DIR/s<seed>; ends with the median over them")
    ap.add_argument("--threads", type=int, default=2, help="torch threads (2)")
    ap.add_argument("--data", default=None, metavar="DIR", help=f"dataset (default: {DEFAULT_DATA}, made once)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="override a training config key (as `gscan-ros train --set`)")
    ap.add_argument("--validate-every", type=int, default=250, metavar="N", help="updates between validations (250)")
    ap.add_argument("--out", default=None, metavar="RUN_DIR",
                    help="run directory (default: runs/tta/<config>_s<seed>; with --seeds, the folder of the "
                         "seeds' run directories, default runs/tta/<config>)")
    ap.add_argument("--from-runs", nargs="+", metavar="RUN_DIR",
                    help="summarize these runs' metrics.jsonl (one per seed) instead of training")
    mode = ap.add_mutually_exclusive_group()
    mode.add_argument("--resume", action="store_true", help="continue RUN_DIR from its last.pt")
    mode.add_argument("--overwrite", action="store_true", help="replace a run already in RUN_DIR")
    args = ap.parse_args(argv)

    from gscan_ros.errors import GscanError

    try:
        if not 0 < args.target <= 100:
            raise GscanError(f"--target must be in (0, 100], got {args.target}")
        if args.from_runs:
            marks = [marks_of(validations_of(Path(d)), args.target) for d in args.from_runs]
            summarize(marks, [Path(d).name for d in args.from_runs], args.target)
            return 0
        if args.config is None:
            raise GscanError("--config FILE is needed to train (or --from-runs RUN_DIR ... to read runs)")
        stem = Path(args.config).stem
        if args.max_minutes <= 0 or args.validate_every <= 0 or args.threads < 1:
            raise GscanError("--max-minutes, --validate-every and --threads must be positive")
        data = ensure_data(args.data)
        if args.seeds is None:
            run_seed(args, args.seed, Path(args.out or f"runs/tta/{stem}_s{args.seed}"), data, args.resume)
            return 0
        root = Path(args.out or f"runs/tta/{stem}")
        marks = []
        for seed in args.seeds:
            print(f"== seed {seed} -> {root / f's{seed}'}", flush=True)
            out = root / f"s{seed}"
            # --resume continues the seeds that have started and starts the others
            marks.append(run_seed(args, seed, out, data, resume=args.resume and (out / "last.pt").is_file()))
    except GscanError as exc:
        print(f"time_to_accuracy: error: {exc}", file=sys.stderr)
        return 1
    summarize(marks, [f"seed {s}" for s in args.seeds], args.target)
    return 0


def validations_of(run: Path) -> list[dict]:
    """The validation records of a run's metrics.jsonl."""
    from gscan_ros.errors import GscanError

    path = run / "metrics.jsonl"
    if not path.is_file():
        raise GscanError(f"{run}: no metrics.jsonl (not a training run)")
    return [r for r in map(json.loads, path.read_text().splitlines()) if r.get("event") == "validation"]


def marks_of(validations: list[dict], target: float) -> dict[float, tuple[int, float] | None]:
    """(updates, minutes) at which the run first reached 90 % and the target (None: not reached)."""
    return {percent: first_at(validations, percent) for percent in sorted({90.0, target})}


def first_at(validations: list[dict], percent: float) -> tuple[int, float] | None:
    """(updates, minutes) of the first validation at or above `percent`."""
    hit = next((r for r in validations if r["dev_exact_match"] >= percent), None)
    return None if hit is None else (hit["step"], hit["elapsed_s"] / 60)


def run_seed(args: argparse.Namespace, seed: int, out: Path, data: str,
             resume: bool) -> dict[float, tuple[int, float] | None]:
    """Train one seed to the target, print its rows and its last line; returns the
    (updates, minutes) at which it first reached 90 % and the target (None: not reached)."""
    from gscan_ros.training.config import TrainConfig
    from gscan_ros.training.trainer import train

    cfg = TrainConfig.load(args.config, [
        *args.overrides, f"seed={seed}", f"threads={args.threads}", f"max_minutes={args.max_minutes}",
        f"target_dev_exact_match={args.target}", f"max_dev_examples={DEV_EPISODES}",
        f"validate_every={args.validate_every}", f"checkpoint_every={args.validate_every}",
        f"log_every={min(50, args.validate_every)}",
    ])
    header = [f"{'updates':>8} {'minutes':>8} {'ex/s':>7} {'dev EM %':>9}  slowest groups"]

    def row(m: dict) -> None:
        if header:
            print(header.pop(), flush=True)
        groups = sorted(((em, f"{axis}={value}") for axis, values in m["dev_by_group"].items()
                         for value, em in values.items()), key=lambda x: x[0])[:3]
        worst = ", ".join(f"{name} {em:.0f}" for em, name in groups)
        rate = throughput(out / "metrics.jsonl")
        print(f"{m['step']:>8} {m['elapsed_s'] / 60:>8.1f} {rate:>7.0f} {m['dev_exact_match']:>9.1f}  {worst}",
              flush=True)

    result = train(cfg, data, out, resume=resume, overwrite=args.overwrite, progress=False,
                   on_validation=row)
    records = [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]
    validations = [r for r in records if r.get("event") == "validation"]
    for r in records:
        if r.get("event") == "screen":
            print(f"screen: candidate {r['candidate']} (seed {r['seed']}) after {r['step']} updates: "
                  f"localization {r['localization']:.1f}% (chance {r['chance']:.1f}%) "
                  f"{'kept' if r['passed'] else 'rejected'} at {r['elapsed_s'] / 60:.1f} minutes")
        elif r.get("event") == "screen_end":
            print(f"screen: training seed {r['seed']}; {r['screen_updates']} updates spent on "
                  f"{r['candidates']} candidate(s) are in the minutes below")
    marks = marks_of(validations, args.target)
    hit = marks[args.target]
    if hit is not None:
        print(f"time-to-accuracy: reached {args.target:.1f}% dev exact match after {hit[0]} updates, "
              f"{hit[1]:.1f} minutes ({throughput(out / 'metrics.jsonl'):.0f} ex/s)")
    else:
        last = validations[-1] if validations else {"step": result["step"], "elapsed_s": 0.0}
        print(f"time-to-accuracy: not reached (best {max(result['best_dev_exact_match'], 0):.1f}% after "
              f"{last['step']} updates, {last['elapsed_s'] / 60:.1f} minutes)")
    return marks


def median_of(values: list[tuple[int, float] | None]) -> tuple[int, float] | None:
    """The median seed's (updates, minutes), a seed that never got there being the slowest
    (None when that is the median seed); ordered by minutes. An even count takes the
    slower of the two middle seeds."""
    ordered = sorted(values, key=lambda v: math.inf if v is None else v[1])
    return ordered[len(ordered) // 2]


def summarize(marks: list[dict], labels: list[str], target: float) -> None:
    """Per threshold, each run's updates and minutes and the range; then the last line."""
    for percent in sorted({90.0, target}):
        values = [m[percent] for m in marks]
        got = [v for v in values if v is not None]
        spread = (f"; range {min(u for u, _ in got)}-{max(u for u, _ in got)} updates, "
                  f"{min(t for _, t in got):.1f}-{max(t for _, t in got):.1f} minutes" if got else "")
        per_seed = ", ".join(f"{s}: " + ("not reached" if v is None else f"{v[0]} upd. / {v[1]:.1f} min")
                             for s, v in zip(labels, values))
        print(f"{percent:.0f} %: {per_seed}{spread}")
    reached = sum(m[target] is not None for m in marks)
    median = median_of([m[target] for m in marks])
    over = f"{len(labels)} seed" + ("s" if len(labels) != 1 else "")
    if median is None:
        print(f"time-to-accuracy: median over {over} not reached ({reached} of {len(labels)} reached)")
    else:
        print(f"time-to-accuracy: median over {over} reached {target:.1f}% after {median[0]} updates, "
              f"{median[1]:.1f} minutes ({reached} of {len(labels)} reached)")


if __name__ == "__main__":
    sys.exit(main())
