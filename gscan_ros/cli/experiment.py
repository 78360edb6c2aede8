"""`gscan-ros experiment`: train and evaluate every run of a plan, restartably.

The plan (YAML, e.g. configs/experiments/paper.yaml) lists datasets and runs; each run is
generated-data -> `train` -> `evaluate` -> RUN/results.json, every step a subprocess.
Kill it at any moment and start it again: finished runs are skipped, unfinished ones
resume from last.pt, and a run another runner is training is left to it. `--worker i/N`
takes every N-th run (run index % N == i), so N machines or a job array share a plan;
`gscan-ros report` merges their result folders. Details: docs/experiments.md.
"""
from __future__ import annotations

import argparse

from gscan_ros.cli.args import existing_file, output_dir, positive_int
from gscan_ros.runtime import available_cpus


def worker_share(text: str) -> tuple[int, int]:
    """'i/N': worker i (0-based) of N."""
    index, sep, count = text.partition("/")
    try:
        i, n = int(index), int(count)
    except ValueError:
        i, n = -1, 0
    if not sep or n < 1 or not 0 <= i < n:
        raise argparse.ArgumentTypeError(f"expects I/N with 0 <= I < N (e.g. 0/2), got {text!r}")
    return i, n


def register(subparsers) -> None:
    p = subparsers.add_parser("experiment", help="train and evaluate every run of a plan (restartable)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("plan", type=existing_file, metavar="PLAN", help="the plan (YAML)")
    p.add_argument("--results", type=output_dir, metavar="DIR",
                   help="folder of the run directories (default: the plan's `results:`)")
    p.add_argument("--data-root", type=output_dir, metavar="DIR",
                   help="folder of the generated datasets (default: the plan's `data_root:`)")
    p.add_argument("--parallel", type=positive_int, default=1, metavar="N", help="runs at once (default: 1)")
    p.add_argument("--threads", type=positive_int, default=1, metavar="T",
                   help="torch threads per run (default: 1); N x T must fit the available CPUs")
    p.add_argument("--worker", type=worker_share, metavar="I/N",
                   help="take only runs whose index %% N == I, one at a time")
    p.add_argument("--only", nargs="+", default=(), metavar="NAME",
                   help="only these runs: runs[] entry names (every seed) or run names such as semantic_s1; "
                        "in the order named within each group (runs to evaluate, then to resume, then new)")
    p.add_argument("--dry-run", action="store_true", help="print what is done, running and left; change nothing")
    p.add_argument("--restart-stale", action="store_true",
                   help="retrain from scratch runs whose config.yaml or dataset folder no longer matches the plan, "
                        "in <run>/.retrain/; their old files stay (and are reported) until the retrain is "
                        "evaluated, then move to <run>/.replaced/")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import signal

    from tqdm import tqdm

    from gscan_ros.errors import GscanError
    from gscan_ros.experiments.plan import load_plan
    from gscan_ros.experiments.runner import Runner
    from gscan_ros.experiments.state import ExperimentError

    cpus = available_cpus()
    if args.parallel * args.threads > cpus:
        raise GscanError(f"--parallel {args.parallel} x --threads {args.threads} needs "
                         f"{args.parallel * args.threads} CPUs but only {cpus} are available")
    if args.worker and args.parallel > 1:
        raise GscanError("--worker runs one run at a time; give each worker its own machine or CPUs "
                         "instead of --parallel")
    plan = load_plan(args.plan, args.results, args.data_root)
    runner = Runner(plan, parallel=args.parallel, threads=args.threads, worker=args.worker, only=tuple(args.only),
                    restart_stale=args.restart_stale, progress=not args.quiet, echo=tqdm.write)
    who = f"worker {args.worker[0]}/{args.worker[1]}: " if args.worker else ""
    print(f"{who}plan {plan.path} -> {plan.results}/")
    if not runner.share:  # a job array with more workers than the plan has runs
        print(f"{who}no run of the plan's {len(plan.runs)} falls to this worker")
        return 0
    if args.dry_run:
        print("\n".join(runner.status_lines(runner.states())))
        return 0

    def stop(signum, frame):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, stop)
    try:
        outcome = runner.run()
    finally:
        signal.signal(signal.SIGTERM, previous)
    print(f"{who}{len(outcome.done)} done, {len(outcome.failed)} failed, "
          f"{len(outcome.skipped)} left to others or stale")
    if outcome.failed:
        raise ExperimentError(f"{len(outcome.failed)} run(s) failed ({', '.join(outcome.failed)}); the FAILED "
                              "lines above name the log that says why; run again to retry")
    return 0
