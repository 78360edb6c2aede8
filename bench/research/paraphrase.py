"""Closed-loop exact match on paraphrased test commands next to the canonical ones.

    .venv/bin/python bench/research/paraphrase.py [--checkpoint CKPT] [--data DIR] [--split test]
                                         [--episodes 1000] [--seed 0] [--threads 2]

Each command of the first `--episodes` episodes of `--split` is rewritten with
`gscan_ros.language.paraphrase` (seeded: WordNet synonyms, "the"/"an", size-before-color
order, case, punctuation) and both sets are decoded closed loop on the same situations
with `evaluate_episodes`. Canonicalization maps every paraphrase back to its command, so
the two exact matches must be equal; the bench also counts graphs and action sequences
that differ (both must be 0). Default data: 20000 freshly generated candidates (seed 0),
about 1000 test episodes.
"""
from __future__ import annotations

import argparse
import random
import sys
import time
from collections import Counter
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/, for the benches' _data
from _data import dataset_or_generated  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", help="checkpoint (default: the shipped model)")
    ap.add_argument("--data", help="dataset (default: generate 20000 candidates into a temp dir)")
    ap.add_argument("--split", default="test")
    ap.add_argument("--episodes", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0, help="seed of the paraphrases")
    ap.add_argument("--threads", type=int, default=2, help="torch intra-op threads")
    args = ap.parse_args()

    from gscan_ros.data.io import iter_episodes
    from gscan_ros.language import canonicalize
    from gscan_ros.language.paraphrase import paraphrase
    from gscan_ros.model.policy import Policy
    from gscan_ros.runtime import configure_torch
    from gscan_ros.training.evaluate import evaluate_episodes

    configure_torch(args.threads)
    policy = Policy.from_checkpoint(args.checkpoint)
    with dataset_or_generated(args.data, examples=20000) as data:
        episodes = []
        for ep in iter_episodes(data, [args.split]):
            episodes.append(ep)
            if len(episodes) >= args.episodes:
                break
    rng = random.Random(args.seed)
    paraphrased = [replace(ep, command=paraphrase(ep.command, rng)) for ep in episodes]

    kinds: Counter[str] = Counter()
    for ep in paraphrased:
        for mapping in canonicalize(ep.command).mappings:
            kinds["synonym" if mapping.reason.startswith("WordNet") else mapping.reason.split(":")[0]] += 1
    rewritten = sum(p.command.lower().rstrip(".!") != ep.command for p, ep in zip(paraphrased, episodes))
    other_graphs = sum(policy.parse(p.command) != policy.parse(ep.command) for p, ep in zip(paraphrased, episodes))
    print(f"{len(episodes)} {args.split} episodes, {rewritten} commands rewritten beyond case/punctuation; "
          f"rewrites: {dict(sorted(kinds.items()))}")
    shown = [(p, ep) for p, ep in zip(paraphrased, episodes) if len(canonicalize(p.command).mappings) >= 3][:3]
    for p, ep in shown:
        print(f"  {p.command!r} -> {ep.command!r}")

    results = {}
    for label, eps in (("canonical", episodes), ("paraphrased", paraphrased)):
        start = time.time()
        results[label] = evaluate_episodes(policy, eps)
        print(f"{label:12s} exact match {results[label].exact_match:6.2f} %  "
              f"token accuracy {results[label].token_accuracy:6.2f} %  ({time.time() - start:.1f} s)")
    other_actions = sum(a.actions != b.actions for a, b in
                        zip(results["canonical"].predictions, results["paraphrased"].predictions))
    print(f"graphs that differ: {other_graphs}; action sequences that differ: {other_actions}")


if __name__ == "__main__":
    main()
