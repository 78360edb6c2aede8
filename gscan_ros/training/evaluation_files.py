"""Evaluation outputs: results JSON, a Markdown table, and a gSCAN-format predictions file."""
from __future__ import annotations

import contextlib
import json
from pathlib import Path

from gscan_ros.outputs import check_targets, claimed, replacing, write_text
from gscan_ros.training.evaluate import EvalResult
from gscan_ros.training.failures import FAILURE_KINDS, failure_label

REPORT_FILES = ("results.json", "results.md", "predictions.json")


def markdown_table(summary: dict, title: str = "") -> str:
    """One row per split (letter, key, examples, exact match %, token accuracy %, and the
    failed episodes of each `FAILURE_KINDS` entry)."""
    lines = [f"## {title}", ""] if title else []
    kinds = [failure_label(k) for k in FAILURE_KINDS]
    lines += [f"| split | key | examples | exact match % | token accuracy % | {' | '.join(kinds)} |",
              "|---|---|---:|---:|---:|" + "---:|" * len(kinds)]
    for split, s in summary.items():
        failures = s.get("failures", {})
        counts = " | ".join(str(failures.get(k, "-")) for k in FAILURE_KINDS)
        lines.append(f"| {s['letter'] or '-'} | {split} | {s['examples']} | {s['exact_match']:.2f} "
                     f"| {s['token_accuracy']:.2f} | {counts} |")
    return "\n".join(lines) + "\n"


def group_table(summary: dict) -> str:
    """Exact match per command group (`command_groups`), one row per split and axis:
    each value's exact match % and episodes, e.g. `no 50.5 % of 8604 · yes 0.0 % of 29978`."""
    lines = ["| split | axis | exact match % of episodes, per value |", "|---|---|---|"]
    for split, s in summary.items():
        for axis, values in s.get("by_group", {}).items():
            cells = " · ".join(f"{value} {v['exact_match']:.1f} % of {v['examples']}" for value, v in values.items())
            lines.append(f"| {s['letter'] or split} | {axis} | {cells} |")
    return "\n".join(lines) + "\n"


def prediction_records(result: EvalResult):
    """gSCAN prediction-file entries (the format of LauraRuis/groundedSCAN's
    `example_prediction.json`), CG variant: `attention_weights` is a
    dict word -> one 36-value map per decoding step."""
    for p in result.predictions:
        ep = p.episode
        yield {
            "input": _tokens(ep.command),
            "prediction": [a.token for a in p.actions],
            "target": [a.token for a in ep.actions],
            "derivation": ep.meta.get("derivation", ""),
            "situation": ep.situation.to_json(),
            "attention_weights": {w: [[round(float(v), 5) for v in m] for m in maps]
                                  for w, maps in (p.attention or {}).items()},
            "accuracy": p.token_accuracy,
            "exact_match": p.exact_match,
            "failure": p.failure,
            "split": ep.split,
            "example_id": ep.example_id,
        }


def _tokens(command: str) -> list[str]:
    from gscan_ros.language.tokens import tokenize

    return list(tokenize(command))


def claim_report_dir(held: contextlib.ExitStack, out_dir: str | Path, overwrite: bool) -> None:
    """Before an evaluation: hold `out_dir`'s lock while `held` lasts, and refuse the
    results of an earlier one there unless `overwrite` (a symbolic link among them always)."""
    held.enter_context(claimed(out_dir))
    check_targets([Path(out_dir) / name for name in REPORT_FILES], overwrite=overwrite)


def write_reports(out_dir: str | Path, result: EvalResult, meta: dict, predictions: bool = True) -> dict:
    """results.json, results.md and (with `predictions`) predictions.json in `out_dir`, each
    replaced whole; an older predictions.json is removed when none is written (no stale set)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    summary = result.summary()
    doc = {**meta, "splits": summary}
    write_text(out / "results.json", json.dumps(doc, indent=2))
    write_text(out / "results.md", markdown_table(summary, meta.get("title", "")) + "\n### By command group\n\n"
               + group_table(summary))
    if predictions:
        with replacing(out / "predictions.json") as tmp, open(tmp, "w") as f:
            f.write("[\n")
            for i, rec in enumerate(prediction_records(result)):
                f.write((",\n" if i else "") + json.dumps(rec))
            f.write("\n]\n")
    else:
        (out / "predictions.json").unlink(missing_ok=True)
    return doc
