"""Split G, the adverb k-shot protocol (Ruis et al. 2020; docs/data.md, "Splits"):
one model per k, exact match on adverb_1.

    .venv/bin/python bench/research/kshot.py [--ks 1 5 10 50] [--updates 5000] [--parallel 2]
                                    [--eval-examples 10000] [--examples N | full]

For each k, with the same seed, so the datasets differ only in which k "cautiously"
examples sit in train (quirk Q10: k is the total count in train):
  1. generate data_gen/full_k{k} (`gscan-ros generate --full --k-shot k`) unless present;
  2. train configs/semantic.yaml into runs/full_k{k} for --updates updates, resuming a
     partial run (`last.pt`). Runs go --parallel at a time, with one torch thread each;
  3. evaluate the best-on-dev checkpoint (`model.pt`) closed loop on a seeded subset of
     adverb_1 (G) and of test (A, for reference), then print one table.
Every step that already has its output is skipped, so an interrupted run can be restarted.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

CLI = [sys.executable, "-m", "gscan_ros.cli"]


def trained_updates(run: Path) -> int:
    """The last logged update of a run (0 if none)."""
    metrics = run / "metrics.jsonl"
    if not metrics.exists():
        return 0
    steps = [json.loads(line).get("step", 0) for line in metrics.read_text().splitlines() if line.strip()]
    return max(steps, default=0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ks", type=int, nargs="+", default=[1, 5, 10, 50])
    ap.add_argument("--examples", default="full", help="candidates per dataset, or 'full' (default)")
    ap.add_argument("--updates", type=int, default=5000, help="training updates per model (batch 200)")
    ap.add_argument("--parallel", type=int, default=2, help="training runs at once (1 torch thread each)")
    ap.add_argument("--eval-examples", type=int, default=10000, help="seeded subset per split (0 = all)")
    ap.add_argument("--data-pattern", default="data_gen/full_k{k}")
    ap.add_argument("--run-pattern", default="runs/full_k{k}")
    args = ap.parse_args()

    size = ["--full"] if args.examples == "full" else ["--examples", args.examples]
    for k in args.ks:
        data = Path(args.data_pattern.format(k=k))
        if not (data / "dataset.txt").exists():
            subprocess.run([*CLI, "generate", "--out", str(data), *size, "--seed", "0", "--k-shot", str(k),
                            "--quiet"], check=True)

    pending = [k for k in args.ks if trained_updates(Path(args.run_pattern.format(k=k))) < args.updates]
    running: list[tuple[int, subprocess.Popen]] = []
    while pending or running:
        while pending and len(running) < args.parallel:
            k = pending.pop(0)
            run = Path(args.run_pattern.format(k=k))
            cmd = [*CLI, "train", "--config", "configs/semantic.yaml", "--data", args.data_pattern.format(k=k),
                   "--out", str(run), "--set", "threads=1", "--set", f"max_updates={args.updates}", "--quiet"]
            if (run / "last.pt").exists():
                cmd.append("--resume")
            print(f"k={k}: training ({' '.join(cmd[2:])})", flush=True)
            running.append((k, subprocess.Popen(cmd)))
        time.sleep(5)
        for k, proc in list(running):
            if proc.poll() is not None:
                running.remove((k, proc))
                if proc.returncode:
                    raise SystemExit(f"k={k}: training failed with exit code {proc.returncode}")

    rows = []
    for k in args.ks:
        run = Path(args.run_pattern.format(k=k))
        out = run / "eval_kshot"
        if not (out / "results.json").exists():
            subprocess.run([*CLI, "evaluate", "--checkpoint", str(run / "model.pt"), "--data",
                            args.data_pattern.format(k=k), "--splits", "adverb_1", "test", "--max-examples",
                            str(args.eval_examples), "--out", str(out), "--no-predictions", "--quiet"], check=True)
        res = json.loads((out / "results.json").read_text())["splits"]
        rows.append((k, res["adverb_1"], res["test"]))
    print("\n| k | G examples | G exact match | G token acc. | A exact match | updates |")
    print("|---:|---:|---:|---:|---:|---:|")
    for k, g, a in rows:
        print(f"| {k} | {g['examples']:,} | {g['exact_match']:.2f} | {g['token_accuracy']:.2f} | "
              f"{a['exact_match']:.2f} | {trained_updates(Path(args.run_pattern.format(k=k)))} |")


if __name__ == "__main__":
    main()
