"""How closely a retrained run repeats the attempt it replaced (same config and seed).

    .venv/bin/python bench/research/retrain_agreement.py RUN_DIR [--against ARCHIVE]

A run retrained for its missing weights (`gscan-ros experiment --restart-stale`) keeps the
attempt it replaced in `RUN_DIR/.replaced/<time>_<updates>upd/` (the newest with a
results.json unless `--against` names one). Printed: the train loss at the first logged
updates (bit-equal kernels give equal losses; another CPU's rounding drifts from the
first updates on), dev exact match at every validation both logged, and closed-loop exact
match per test split, each with the difference (retrained - replaced). Exits 1 when
either folder lacks what it compares.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from gscan_ros.training.metrics_log import read_events

LOSS_STEPS = 5  # logged train updates compared one by one


def by_step(events: list[dict], kind: str, key: str) -> dict[int, float]:
    """`key` of every `kind` record by update (a resumed run's later record wins)."""
    return {int(e["step"]): float(e[key]) for e in events if e.get("event") == kind and key in e}


def newest_archive(run: Path) -> Path | None:
    archives = sorted(p for p in (run / ".replaced").glob("*") if (p / "results.json").is_file())
    return archives[-1] if archives else None


def fail(message: str) -> None:
    print(f"retrain_agreement: {message}", file=sys.stderr)
    sys.exit(1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="the retrained run's folder")
    ap.add_argument("--against", type=Path, help="the replaced attempt's folder (default: newest in .replaced/)")
    args = ap.parse_args()
    old_dir = args.against or newest_archive(args.run)
    if old_dir is None:
        fail(f"{args.run}/.replaced/ holds no attempt with a results.json")
    runs = {}
    for label, folder in (("replaced", old_dir), ("retrained", args.run)):
        results, metrics = folder / "results.json", folder / "metrics.jsonl"
        if not results.is_file() or not metrics.is_file():
            fail(f"{folder} has no results.json and metrics.jsonl to compare")
        try:
            runs[label] = (json.loads(results.read_text()), read_events(metrics))
        except (OSError, ValueError) as exc:
            fail(f"{results} does not read: {exc}")
    (old_res, old_ev), (new_res, new_ev) = runs["replaced"], runs["retrained"]
    print(f"{args.run.name}: retrained (seed {new_res.get('seed')}) against {old_dir}")

    old_loss, new_loss = by_step(old_ev, "train", "loss"), by_step(new_ev, "train", "loss")
    print("\ntrain loss   update  replaced   retrained  difference")
    for step in sorted(set(old_loss) & set(new_loss))[:LOSS_STEPS]:
        print(f"{step:>19}  {old_loss[step]:.6f}  {new_loss[step]:.6f}  {new_loss[step] - old_loss[step]:+.2e}")

    old_dev, new_dev = (by_step(ev, "validation", "dev_exact_match") for ev in (old_ev, new_ev))
    shared = sorted(set(old_dev) & set(new_dev))
    print("\ndev exact match  update  replaced  retrained  difference")
    for step in shared:
        print(f"{step:>23}  {old_dev[step]:8.1f}  {new_dev[step]:9.1f}  {new_dev[step] - old_dev[step]:+10.1f}")
    if shared:
        worst = max(abs(new_dev[s] - old_dev[s]) for s in shared)
        print(f"largest dev difference over {len(shared)} validations: {worst:.1f} points")

    print("\nsplit            replaced  retrained  difference")
    for split in sorted(set(old_res.get("splits", {})) & set(new_res.get("splits", {}))):
        old, new = old_res["splits"][split]["exact_match"], new_res["splits"][split]["exact_match"]
        print(f"{split:<15} {old:9.2f}  {new:9.2f}  {new - old:+10.2f}")


if __name__ == "__main__":
    main()
