"""Split G's learning curves of k-shot runs on one axis: exposures of the held-out word.

    .venv/bin/python bench/research/kshot_exposures.py CURVE.json [CURVE.json ...] [--word cautiously]
        [--split adverb_1] [--png FILE] [--paper-passes 81.5]

Each CURVE.json is what `bench/research/snapshot_curve.py RUN --train-containing WORD --json` wrote.
A snapshot after U updates has shown each train example U / (batches per epoch) times,
so the word has been seen n_word x U / (batches per epoch) times, where n_word is the
number of train examples whose command has it (the "train:WORD" row's episodes), times the
run's `oversample_factor` when it oversamples the word, and the batches per epoch come from
the run's own `batch_size`, `batching` and oversampling through
`training.batches.batch_order` (one command per batch and oversampling need the train
commands, read from the run's data). If runs with different k line up on this axis, what separates them is
how often the word was seen, not how many distinct examples of it there were.
`--paper-passes` prints where the paper's budget (150,000 updates of 200 over the
367,933-episode train split: 81.5 passes) puts each k.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


class _Commands:
    """What `batch_order` reads of a store: its length and, for one-command batches, its commands."""

    def __init__(self, commands: list[str]):
        self.commands = commands

    def __len__(self) -> int:
        return len(self.commands)


def batches_per_epoch(run: Path, data: str) -> tuple[int, int, str, int]:
    """(batches per epoch, train examples, the word it oversamples ('' none) and how often
    its episodes appear per epoch) of the run in `run`, from its config and metrics."""
    import yaml

    from gscan_ros.training.batches import batch_order, word_repeats

    cfg = yaml.safe_load((run / "config.yaml").read_text())
    start = next(json.loads(line) for line in (run / "metrics.jsonl").open() if '"event": "start"' in line)
    n = int(start["train_examples"])
    batching = cfg.get("batching", "mixed")
    word, factor = cfg.get("oversample_word", ""), cfg.get("oversample_factor", 1)
    if batching == "per_command" or word:
        from gscan_ros.training.trainer import iter_split

        cap = cfg.get("max_train_target_length") or 0
        commands = [ep.command for ep in iter_split(data, cfg.get("train_split", "train"))
                    if not cap or len(ep.actions) <= cap]
        if len(commands) != n:
            raise ValueError(f"{data} has {len(commands)} train episodes, the run logged {n}")
    else:
        commands = [""] * n
    order = batch_order(_Commands(commands), int(cfg["batch_size"]), batching, np.random.default_rng(0),
                        word_repeats(commands, word, factor))
    return len(order), n, word, factor


def curve_rows(curve: dict, word: str, split: str) -> list[dict]:
    """Per snapshot: updates, exposures of the word, and the split's and the word's own rows."""
    run = Path(curve["run"])
    per_epoch, n, oversampled, factor = batches_per_epoch(run, curve["data"])
    if oversampled != word:
        factor = 1
    by_update: dict[int, dict] = {}
    for row in curve["rows"]:
        by_update.setdefault(row["updates"], {})[row["split"]] = row
    rows = []
    for updates, rows_at in sorted(by_update.items()):
        own, target = rows_at.get(f"train:{word}"), rows_at.get(split)
        if own is None or target is None:
            raise ValueError(f"{run}: no 'train:{word}' or '{split}' row at {updates} updates "
                             f"(run snapshot_curve.py with --train-containing {word})")
        rows.append({"run": run.name, "k": own["episodes"], "updates": updates, "passes": updates / per_epoch,
                     "exposures": own["episodes"] * factor * updates / per_epoch, "batches_per_epoch": per_epoch,
                     "train_examples": n, "target": target, "own": own})
    return rows


def plot(runs: dict[str, list[dict]], split: str, word: str, png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(14, 4))
    panels = [(lambda r: r["target"]["token_accuracy"], f"{split}: teacher-forced token acc. %"),
              (lambda r: r["own"]["token_accuracy"], f"its own '{word}' train examples: teacher-forced acc. %"),
              (lambda r: r["target"].get("exact_match", float("nan")), f"{split}: closed-loop exact match %")]
    for ax, (value, title) in zip(axes, panels):
        for name, rows in runs.items():
            ax.plot([r["exposures"] for r in rows], [value(r) for r in rows], marker="o",
                    label=f"{name} (k={rows[0]['k']})")
        ax.set_xscale("log")
        ax.set_xlabel(f"exposures of '{word}' (train examples x passes)")
        ax.set_title(title, fontsize=9)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(png, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("curves", nargs="+", type=Path, help="snapshot_curve.py --json files")
    ap.add_argument("--word", default="cautiously", help="the held-out word (its 'train:WORD' rows)")
    ap.add_argument("--split", default="adverb_1", help="the split the word is tested on")
    ap.add_argument("--png", type=Path, help="also plot here (refuses an existing file)")
    ap.add_argument("--paper-passes", type=float, default=150_000 * 200 / 367_933,
                    help="passes over train of the paper's budget, for the closing lines")
    args = ap.parse_args()
    if args.png is not None and args.png.exists():
        sys.exit(f"bench/research/kshot_exposures.py: {args.png} exists; give another path")
    runs: dict[str, list[dict]] = {}
    try:
        for path in args.curves:
            rows = curve_rows(json.loads(path.read_text()), args.word, args.split)
            runs[rows[0]["run"]] = rows
    except (OSError, ValueError, KeyError, StopIteration) as err:
        sys.exit(f"bench/research/kshot_exposures.py: {err!r}" if isinstance(err, (KeyError, StopIteration)) else
                 f"bench/research/kshot_exposures.py: {err}")
    print(f"| run | k | updates | passes | exposures of '{args.word}' | {args.split}: TF acc. % / NLL | "
          f"own examples: TF acc. % / exact % | {args.split}: exact % |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for rows in sorted(runs.values(), key=lambda rows: rows[0]["k"]):
        for r in rows:
            t, o = r["target"], r["own"]
            print(f"| {r['run']} | {r['k']} | {r['updates']} | {r['passes']:.2f} | {r['exposures']:.0f} | "
                  f"{t['token_accuracy']:.1f} / {t['nll']:.2f} | {o['token_accuracy']:.1f} / "
                  f"{o['sequence_accuracy']:.1f} | {t.get('exact_match', float('nan')):.2f} |")
    for rows in sorted(runs.values(), key=lambda rows: rows[0]["k"]):
        last = rows[-1]
        print(f"{last['run']}: k={last['k']}, {last['batches_per_epoch']} batches per epoch, "
              f"{last['exposures']:.0f} exposures at {last['updates']} updates; the paper's budget: "
              f"{last['k'] * args.paper_passes:.0f}")
    if args.png is not None:
        plot(runs, args.split, args.word, args.png)
        print(f"wrote {args.png}")


if __name__ == "__main__":
    main()
