"""`gscan-ros report`: the paper's Table 1 and Table 2 from runs' results.json, ours beside theirs.

Runs are grouped by column and by what they were trained on:
- compositional data with the released single "cautiously" example (k_shot 1) gives
  Table 1's rows A-F, H and G k=1; data with another k_shot gives only its G row (the
  paper's label, `paper_figures.K_SHOT_LABELS`: k_shot 11 is the paper's "k=10");
- length data gives a Table 2 column per longest trained target length, rows = exact
  match per target length pooled over the run's test splits (test and target_lengths).
A cell is the mean ± sample std over the group's seeds; the paper's figure sits beside
it. Notes flag every cell further from the paper's mean than the paper's std, say
whether that column's dev curve is still rising, and check the paper's qualitative
claims; a results folder's `reading.md` (why ours differs, by hand) follows them. The
markdown depends on the results only (sorted, fixed formats), so the same files give
byte-identical output.
"""
from __future__ import annotations

import math
import os
import statistics
from dataclasses import dataclass, field
from pathlib import Path

from gscan_ros.errors import GscanError, quoted, shortened
from gscan_ros.experiments.paper_figures import (
    COLUMN_TITLES,
    K_SHOT_LABELS,
    PAPER_EXAMPLES,
    PAPER_EXAMPLES_DEFAULT,
    TABLE1,
    TABLE1_ROWS,
    TABLE1_SOURCE,
    TABLE2,
    TABLE2_ROWS,
    TABLE2_SOURCE,
)
from gscan_ros.outputs import replacing, write_text
from gscan_ros.training.failures import FAILURE_KINDS, failure_label
from gscan_ros.training.metrics_log import read_events
from gscan_ros.user_files import read_json, read_yaml

RISING_POINTS = 1.0  # dev exact match gained over the last 20 % of updates that counts as "still rising"
MUCH_POINTS = 10.0  # "≫": ahead by more than this many points
LENGTH_ROWS = TABLE2_ROWS + ("I",)


class ReportError(GscanError):
    """Run results that cannot be read or merged into the tables."""


@dataclass(frozen=True)
class Group:
    """Runs that form one column of a table: same column id, same training data kind."""

    table: int  # 1 or 2
    column: str
    variant: str  # "" (Table 1 main), "G k=10" (k-shot data), "<=14" (Table 2)
    paper_column: str | None
    title: str

    @property
    def label(self) -> str:
        if self.variant.startswith("<="):
            return f"{self.title}, trained ≤ {self.variant[2:]}"
        return f"{self.title}, {self.variant}" if self.variant else self.title

    def sort_key(self) -> tuple:
        """The groups' order in the report: total, so it never rests on set order."""
        order = list(COLUMN_TITLES)
        rank = order.index(self.paper_column) if self.paper_column in order else len(order)
        cut = -int(self.variant[2:]) if self.variant.startswith("<=") else 0
        return (self.table, rank, self.column != self.paper_column, self.column, cut, self.variant,
                self.paper_column or "", self.title)


@dataclass
class RunResult:
    name: str
    group: Group
    seed: int
    updates: int
    max_updates: int
    best_dev: float | None
    batch_size: int | None  # from the run's config.yaml (None: not there)
    config: dict | None  # the run's config.yaml (None: not there, or unreadable)
    rows: dict[str, float]  # table row -> exact match %
    curve: list[tuple[int, float]]  # (update, dev exact match %) from metrics.jsonl
    lengths: dict[int, tuple[float, int]]  # split I runs: target length -> (correct, episodes), splits pooled
    screen: list[tuple[int, bool]] = field(default_factory=list)  # seed screen: (candidate seed, passed)
    kept_seed: int | None = None  # the screened seed that trained (None: not screened)
    # split letter -> (episodes, failed episodes per failure kind); the earliest runs have none
    failures: dict[str, tuple[int, dict[str, int]]] = field(default_factory=dict)
    eval_max_examples: int = 0  # a seeded sample of this many episodes per test split (0: all)
    train_seconds: float | None = None  # wall time of training, screen and validation included
    eval_seconds: float | None = None  # wall time of the test evaluation
    directory: Path | None = None  # the run's folder


# ------------------------------------------------------------------------------ loading
def load_runs(dirs: list[Path]) -> list[RunResult]:
    """Every run under `dirs` (a run directory, or folders holding run directories at any
    depth); a run name found twice is an error (merging workers' copies of one run)."""
    found: dict[str, Path] = {}
    runs = []
    for root in dirs:
        for path in _result_files(Path(root)):
            run = _read_run(path)
            if run.name in found:
                raise ReportError(f"run {run.name!r} is in both {found[run.name].parent} and {path.parent}")
            found[run.name] = path
            runs.append(run)
    if not runs:
        raise ReportError(f"no run results.json under {', '.join(str(d) for d in dirs)}")
    return sorted(runs, key=lambda r: (r.group.sort_key(), r.seed, r.name))


def _result_files(root: Path) -> list[Path]:
    if (root / "results.json").is_file():
        return [root / "results.json"]
    return sorted(p for p in root.rglob("results.json")
                  if not any(part.startswith(".") for part in p.relative_to(root).parts))


def _read_run(path: Path) -> RunResult:
    doc = read_json(path, str(path), ReportError)
    missing = [k for k in _RESULT_KEYS if k not in doc] if isinstance(doc, dict) else list(_RESULT_KEYS)
    if missing:
        raise ReportError(f"{path} is not a run's results.json (no {missing[0]!r}; made by `gscan-ros experiment`?)")
    _check(doc, _RESULTS, "", path)
    metrics = _metrics(path.parent / "metrics.jsonl")
    try:
        return _run_result(path, doc, metrics)
    except (KeyError, OverflowError, ValueError) as exc:  # e.g. a target length that is not a number
        raise ReportError(f"{path}: malformed results.json ({type(exc).__name__}: {exc})") from None


_KINDS = {
    "a string": lambda v: isinstance(v, str),
    "an integer": lambda v: isinstance(v, int) and not isinstance(v, bool),
    "an integer >= 0": lambda v: isinstance(v, int) and not isinstance(v, bool) and v >= 0,
    "a finite number": lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v),
    "a mapping": lambda v: isinstance(v, dict),
}

# What the tables read from a results.json, each value's kind (a `_KINDS` key) or, for a
# mapping, its own schema; "*" stands for every key of a mapping, and a key ending in "?"
# may be missing or null. Other keys are not read, so they are not checked.
_SPLIT = {
    "letter": "a string", "exact_match": "a finite number", "examples": "an integer >= 0",
    "failures?": {"*": "an integer >= 0"},
    "by_target_length?": {"*": {"exact_match": "a finite number", "examples": "an integer >= 0"}},
}
_RESULTS = {
    "run": "a string", "column": "a string", "title": "a string", "paper_column?": "a string",
    "seed": "an integer >= 0", "updates": "an integer >= 0", "max_updates": "an integer >= 0",
    "best_dev_exact_match?": "a finite number", "max_train_target_length?": "an integer",
    "data": {"split_kind?": "a string", "k_shot?": "an integer", "cut_off_target_length?": "an integer"},
    "splits": {"*": _SPLIT},
    "evaluation?": {"max_examples?": "an integer"},
}
_RESULT_KEYS = tuple(key for key in _RESULTS if not key.endswith("?"))


def _check(value, schema: str | dict, field: str, source: Path, *, optional: bool = False) -> None:
    """Raise a ReportError naming the file and the field where `value` does not fit
    `schema`: a value of the wrong type would otherwise fail later, far from its file, or
    be printed in a table."""
    kind = schema if isinstance(schema, str) else "a mapping"
    if optional and value is None:
        return
    if not _KINDS[kind](value):
        raise ReportError(f"{source}: {field} must be {kind}{' or null' if optional else ''}, got {quoted(value)}")
    if isinstance(schema, str):
        return
    for key, inner in schema.items():
        if key == "*":
            for name, item in value.items():
                _check(item, inner, f"{field}.{shortened(str(name))}".lstrip("."), source)
        else:
            name = key.removesuffix("?")
            _check(value.get(name), inner, f"{field}.{name}".lstrip("."), source, optional=key.endswith("?"))


def _run_result(path: Path, doc: dict, metrics: dict) -> RunResult:
    """The run in a results.json that `_check` accepted."""
    data, splits = doc["data"], doc["splits"]
    if data.get("split_kind") == "length":
        cut = doc.get("max_train_target_length") or data.get("cut_off_target_length") or 15
        lengths = _length_counts(splits)
        table, variant, rows = 2, f"<={cut}", _length_rows(lengths, splits)
    else:
        lengths = {}
        k_shot = 1 if data.get("k_shot") is None else data["k_shot"]
        g_row = f"G k={K_SHOT_LABELS[k_shot]}" if k_shot in K_SHOT_LABELS else f"G k_shot={k_shot}"
        table, variant = 1, "" if k_shot == 1 else g_row
        rows = {}
        for split in splits.values():
            letter = split["letter"]
            if letter == "G" or k_shot == 1:
                rows[g_row if letter == "G" else letter] = float(split["exact_match"])
    group = Group(table, doc["column"], variant, doc.get("paper_column"), doc["title"])
    config = _config(path.parent / "config.yaml")
    failures = {split["letter"] or key: (split["examples"], split["failures"])
                for key, split in splits.items() if split.get("failures") is not None}
    return RunResult(name=doc["run"], group=group, seed=doc["seed"], updates=doc["updates"],
                     max_updates=doc["max_updates"], best_dev=doc.get("best_dev_exact_match"),
                     batch_size=_batch_size(config), config=config, rows=rows, lengths=lengths,
                     failures=failures, **metrics,
                     eval_max_examples=(doc.get("evaluation") or {}).get("max_examples") or 0,
                     train_seconds=doc.get("train_seconds"), eval_seconds=(doc.get("evaluation") or {}).get("seconds"),
                     directory=path.parent)


def _config(path: Path) -> dict | None:
    """A run's merged config.yaml (the runner writes it), if readable."""
    try:
        doc = read_yaml(path, f"config {str(path)!r}", ReportError)
    except ReportError:
        return None
    return doc if isinstance(doc, dict) else None


def _batch_size(config: dict | None) -> int | None:
    value = (config or {}).get("batch_size")
    return int(value) if isinstance(value, int) else None


def _length_rows(lengths: dict[int, tuple[float, int]], splits: dict) -> dict[str, float]:
    """Exact match for target lengths 15, 16, 17 and >= 18 from the per-length counts
    (`_length_counts`), and split I (target_lengths) as a whole."""
    pooled: dict[str, list[float]] = {row: [0.0, 0] for row in TABLE2_ROWS}
    for length, (correct, n) in lengths.items():
        row = ">=18" if length >= 18 else str(length)
        if row in pooled:
            pooled[row][0] += correct
            pooled[row][1] += n
    rows = {row: 100 * correct / n for row, (correct, n) in pooled.items() if n}
    if "target_lengths" in splits:
        rows["I"] = float(splits["target_lengths"]["exact_match"])
    return rows


def _length_counts(splits: dict) -> dict[int, tuple[float, int]]:
    """Correct episodes and episodes per target length, pooled over the splits."""
    counts: dict[int, list[float]] = {}
    for split in splits.values():
        for length, cell in (split.get("by_target_length") or {}).items():
            pooled = counts.setdefault(int(length), [0.0, 0])
            pooled[0] += cell["exact_match"] * cell["examples"] / 100
            pooled[1] += cell["examples"]
    return {length: (correct, int(n)) for length, (correct, n) in sorted(counts.items())}


def _metrics(metrics: Path) -> dict:
    """From a run's metrics.jsonl: `curve`, dev exact match per validated update (a resumed
    run's repeat of an update: the last), and the seed screen's candidates and kept seed."""
    points: dict[int, float] = {}
    screen: dict[int, bool] = {}
    kept = None
    for rec in read_events(metrics):
        event = rec.get("event")
        if event == "validation":
            _check(rec.get("step"), "an integer", "step of a validation record", metrics)
            _check(rec.get("dev_exact_match"), "a finite number", "dev_exact_match of a validation record", metrics)
            points[rec["step"]] = float(rec["dev_exact_match"])
        elif event == "screen":
            _check(rec.get("seed"), "an integer", "seed of a screen record", metrics)
            screen[rec["seed"]] = bool(rec.get("passed"))
        elif event == "screen_end":
            _check(rec.get("seed"), "an integer", "seed of a screen_end record", metrics)
            kept = rec["seed"]
    return {"curve": sorted(points.items()), "screen": list(screen.items()), "kept_seed": kept}


# ------------------------------------------------------------------------------ numbers
@dataclass(frozen=True)
class Cell:
    values: tuple[float, ...]

    @property
    def mean(self) -> float:
        return statistics.fmean(self.values)

    @property
    def std(self) -> float | None:
        return statistics.stdev(self.values) if len(self.values) > 1 else None

    def text(self) -> str:
        return f"{self.mean:.2f}" + (f" ± {self.std:.2f}" if self.std is not None else "")


def rise(curve: list[tuple[int, float]]) -> float | None:
    """Dev exact match gained over the last 20 % of the run's updates (None: < 2 validations)."""
    if len(curve) < 2:
        return None
    last_step, last = curve[-1]
    before = [em for step, em in curve[:-1] if step <= 0.8 * last_step] or [curve[0][1]]
    return last - before[-1]


class Tables:
    """The cells of both tables, per group, from the runs."""

    def __init__(self, runs: list[RunResult], retrains: dict[str, str] | None = None):
        self.runs = runs
        self.retrains = retrains or {}  # run name -> why the plan retrains it
        self.groups: list[Group] = sorted({r.group for r in runs}, key=Group.sort_key)
        self.members = {g: [r for r in runs if r.group == g] for g in self.groups}

    def mixed_recipes(self) -> list[str]:
        """One line per run whose recipe differs from its cell's first seed's (`config_changes`,
        the runner's rule: the budget and the machine aside; the seed and the seed screen too,
        which the selection rule places): such a cell mixes two recipes."""
        from gscan_ros.training.config import ConfigError, TrainConfig, config_changes

        lines = []
        for g in self.groups:
            members = [r for r in self.members[g] if r.config is not None]
            for run in members[1:]:
                try:
                    ref = TrainConfig.from_dict({**members[0].config, "seed": run.config.get("seed", 0)})
                    changed = config_changes(run.config, ref)
                except (ConfigError, TypeError, ValueError):  # a config of keys since removed: not compared
                    continue
                changed = [k for k in changed if k not in ("screen_seeds", "screen_updates")]
                if changed:
                    lines.append(f"- {g.label}: `{run.name}` differs from `{members[0].name}` in "
                                 f"{', '.join(changed)}; the cell averages both.")
        return lines

    def table1_columns(self) -> list[tuple[str, str, str | None]]:
        """(column id, title, paper column) of the Table 1 groups, in order."""
        seen: dict[str, tuple[str, str, str | None]] = {}
        for g in self.groups:
            if g.table == 1 and g.column not in seen:
                seen[g.column] = (g.column, g.title, g.paper_column)
        return list(seen.values())

    def runs1(self, column: str, row: str) -> list[RunResult]:
        """The runs behind a Table 1 cell."""
        return [r for g in self.groups if g.table == 1 and g.column == column for r in self.members[g] if row in r.rows]

    def runs2(self, group: Group, row: str) -> list[RunResult]:
        return [r for r in self.members[group] if row in r.rows]

    def cell1(self, column: str, row: str) -> Cell | None:
        return _cell(self.runs1(column, row), row)

    def cell2(self, group: Group, row: str) -> Cell | None:
        return _cell(self.runs2(group, row), row)

    def retrained(self, runs: list[RunResult]) -> bool:
        """One of `runs` (a cell's) is a run the plan retrains."""
        return any(r.name in self.retrains for r in runs)

    def table1_rows(self) -> list[str]:
        """The paper's rows (its figures show even where we have none), then any others."""
        rows = {row for r in self.runs if r.group.table == 1 for row in r.rows}
        return list(TABLE1_ROWS) + sorted(rows - set(TABLE1_ROWS))

    def group_rise(self, group: Group) -> float | None:
        rises = [x for x in (rise(r.curve) for r in self.members[group]) if x is not None]
        return statistics.fmean(rises) if rises else None

    def column_rise(self, column: str, table: int, row: str) -> float | None:
        """The rise of the group that fills this cell."""
        for g in self.groups:
            if g.table == table and g.column == column and any(row in r.rows for r in self.members[g]):
                return self.group_rise(g)
        return None


def _cell(runs: list[RunResult], row: str) -> Cell | None:
    return Cell(tuple(r.rows[row] for r in runs)) if runs else None


def _paper1(paper_column: str | None, row: str):
    return TABLE1.get(paper_column or "", {}).get(row)


def _paper2(group: Group, row: str):
    cut = int(group.variant[2:])
    return TABLE2.get((group.paper_column or "", cut), {}).get(row)


def _paper_text(figure) -> str:
    if figure is None:
        return ""
    if isinstance(figure, str):
        return f"paper {figure}"
    return f"paper {figure[0]:.2f} ± {figure[1]:.2f}"


def _cell_text(cell: Cell | None, figure) -> str:
    ours = cell.text() if cell is not None else "–"
    paper = _paper_text(figure)
    return f"{ours}<br>{paper}" if paper else ours


def _length_name(row: str) -> str:
    return "≥ 18" if row == ">=18" else row


def _rise_text(value: float | None) -> str:
    if value is None:
        return "too few validations to tell"
    trend = "still rising" if value >= RISING_POINTS else "flat"
    return f"dev curve {trend} ({value:+.2f} points over the last 20 % of updates)"


# ------------------------------------------------------------------------------ markdown
READING = "reading.md"  # a results folder's hand-written reading of its tables


# How seeds were chosen, stated above the tables (configs/experiments/paper.yaml).
SELECTION_RULE = (
    "**Selection rule:** every seed trains as it comes, with no screen, as in the paper. The screened "
    "recipe (a seed's attention maps must land on the target after 1,000 updates, up to 8 candidate "
    "initialisations, the cost counted in the run's time) has its own columns, titled \"screened seeds\"; "
    "a screened run whose first candidate passed is the unscreened run of its seed and counts in the main "
    "column. Columns titled \"(screened)\" are single-seed studies beyond the paper, trained screened."
)


RETRAIN_MARK = "†"


def render(runs: list[RunResult], curves_link: str | None, readings: list[tuple[str, str]] = (),
           retrains: dict[str, str] | None = None) -> str:
    """The markdown report; `readings` (source, text) are hand-written explanations (the
    results folders' `reading.md`), appended after the generated notes; `retrains` (run
    name -> why), the runs the plan retrains, whose cells are marked RETRAIN_MARK."""
    tables = Tables(runs, retrains)
    out = ["# The paper's tables, reproduced", "",
           "Generated by `gscan-ros report` from each run's `results.json` and `metrics.jsonl` "
           "(`gscan-ros experiment` writes them); do not edit by hand. Closed-loop exact match %. "
           "Ours: mean ± sample standard deviation over the seeds (a value without ± is one seed); "
           f"paper: {TABLE1_SOURCE} and {TABLE2_SOURCE} (mean ± std over three runs).", "",
           SELECTION_RULE, ""]
    out += _table1(tables) + _table2(tables) + _budget(tables) + _screens(tables) + _failures(tables)
    if curves_link:
        out += ["## Learning curves", "", f"![dev exact match vs updates, one panel per column]({curves_link})", ""]
    out += _notes(tables)
    for source, text in readings:
        out += [f"### Reading (hand-written, `{source}`)", "", text.strip(), ""]
    return "\n".join(out).rstrip("\n") + "\n"


def _head(first: str, columns: list[str]) -> list[str]:
    """A markdown table's header and alignment rows: a label column, then right-aligned figures."""
    return ["| " + " | ".join([first, *columns]) + " |", "|---|" + "---:|" * len(columns)]


def _table1(t: Tables) -> list[str]:
    columns = t.table1_columns()
    if not columns:
        return []
    out = ["## Table 1: compositional splits A–H", "", *_head("split", [title for _, title, _ in columns])]
    for row in t.table1_rows():
        cells = [_cell_text(t.cell1(column, row), _paper1(paper, row)) + _mark(t.retrained(t.runs1(column, row)))
                 for column, _, paper in columns]
        out.append(f"| {row} | " + " | ".join(cells) + " |")
    return out + [""]


def _mark(retrained: bool) -> str:
    return f" {RETRAIN_MARK}" if retrained else ""


def _table2(t: Tables) -> list[str]:
    groups = [g for g in t.groups if g.table == 2]
    if not groups:
        return []
    samples = sorted({run.eval_max_examples for g in groups for run in t.members[g]})
    if samples == [0]:
        evaluated = "Row I: the whole target_lengths split."
    else:
        sizes = " or ".join("all" if n == 0 else f"{n:,}" for n in samples)
        evaluated = (f"Row I: every run decodes a seeded sample of {sizes} episodes of target_lengths (and of "
                     f"test), the same sample for every run of a size.")
    out = ["## Table 2: split I, exact match by target length", "",
           f"Columns: the longest target length trained on. {evaluated}", "",
           *_head("target length", [g.label for g in groups])]
    for row in LENGTH_ROWS:
        cells = [t.cell2(g, row) for g in groups]
        if row not in TABLE2_ROWS and all(c is None for c in cells):
            continue
        texts = (_cell_text(c, _paper2(g, row)) + _mark(t.retrained(t.runs2(g, row))) for c, g in zip(cells, groups))
        out.append(f"| {_length_name(row)} | " + " | ".join(texts) + " |")
    return out + [""] + _length_histogram(t, groups)


def _length_histogram(t: Tables, groups: list[Group]) -> list[str]:
    """Exact match at every target length (the paper gives 15, 16, 17 and >= 18 only),
    the episodes of a group's seeds pooled."""
    pooled = []
    for g in groups:
        counts: dict[int, list[float]] = {}
        for run in t.members[g]:
            for length, (correct, n) in run.lengths.items():
                cell = counts.setdefault(length, [0.0, 0])
                cell[0] += correct
                cell[1] += n
        pooled.append(counts)
    lengths = sorted({length for counts in pooled for length in counts})
    if not lengths:
        return []
    out = ["### Split I at every target length", "",
           "Exact match % (episodes), test and target_lengths pooled, and a column's seeds pooled.", "",
           *_head("target length", [g.label for g in groups])]
    for length in lengths:
        cells = [f"{100 * c[length][0] / c[length][1]:.1f} ({c[length][1]})" if c.get(length, (0, 0))[1] else "–"
                 for c in pooled]
        out.append(f"| {length} | " + " | ".join(cells) + " |")
    return out + [""]


def _budget(t: Tables) -> list[str]:
    out = ["## Runs and budget", "",
           "Training and evaluation are wall times per run as `results.json` logged them (one thread, "
           "most runs beside another training on a 2-core machine): a range where the seeds differ.", "",
           "| column | seeds | updates | budget | training examples (the paper's) | best dev exact match "
           "| dev curve, last 20 % of updates | training, h | evaluation, min |",
           "|---|---|---:|---:|---:|---:|---|---:|---:|"]
    for g in t.groups:
        runs = t.members[g]
        updates = sorted({r.updates for r in runs})
        budgets = sorted({r.max_updates for r in runs})
        best = tuple(r.best_dev for r in runs if r.best_dev is not None)
        trend = t.group_rise(g)
        updates_text = str(updates[0]) if len(updates) == 1 else f"{updates[0]}–{updates[-1]}"
        trend_text = "–" if trend is None else f"{'rising' if trend >= RISING_POINTS else 'flat'} {trend:+.2f}"
        out.append(f"| {g.label} | {', '.join(str(r.seed) for r in runs)} | {updates_text} | "
                   f"{'/'.join(str(b) for b in budgets)} | {_examples_text(g.paper_column or g.column, runs)} | "
                   f"{Cell(best).text() if best else '–'} | {trend_text} | "
                   f"{_time_range((r.train_seconds for r in runs), 3600)} | "
                   f"{_time_range((r.eval_seconds for r in runs), 60)} |")
    return out + [""]


def _time_range(seconds, unit: float) -> str:
    """The lowest to the highest of some wall times in `unit` seconds: "1.3", "1.3–2.1" or "–"."""
    values = [v / unit for v in seconds if v is not None]
    if not values:
        return "–"
    low, high = f"{min(values):.1f}", f"{max(values):.1f}"
    return low if low == high else f"{low}–{high}"


def _screens(t: Tables) -> list[str]:
    """Per column, how many screened candidate starts were on target after the screen's
    updates: how reliably the network starts well, which the exact-match tables hide."""
    rows = []
    for g in t.groups:
        runs = [r for r in t.members[g] if r.screen]
        if not runs:
            continue
        passed = sum(ok for r in runs for _, ok in r.screen)
        tried = sum(len(r.screen) for r in runs)
        detail = " · ".join(f"s{r.seed}: {r.kept_seed} after {len(r.screen)}" if any(ok for _, ok in r.screen)
                            else f"s{r.seed}: none of {len(r.screen)}, {r.kept_seed} trained" for r in runs)
        rows.append(f"| {g.label} | {passed} of {tried} | {detail} |")
    if not rows:
        return []
    return ["## Seed screens", "",
            "A screened run trains candidate initialisations in turn and keeps the first whose maps "
            "peak on the target at least half as often as a uniform pick among the objects, else the best "
            "(`screen_seeds`, docs/results.md \"Seed screening\"). Starts on target per column:", "",
            "| column | candidates on target | runs (seed: kept seed after how many candidates) |",
            "|---|---:|---|", *rows, ""]


def _failures(t: Tables) -> list[str]:
    """Per column and split, the share of episodes failed in each failure kind, pooled over
    the column's seeds whose results.json counts them (named: the others are not in it)."""
    rows = []
    for g in t.groups:
        pooled: dict[str, list] = {}
        for run in t.members[g]:
            for letter, (episodes, kinds) in run.failures.items():
                cell = pooled.setdefault(letter, [0, dict.fromkeys(FAILURE_KINDS, 0), []])
                cell[0] += episodes
                for kind in FAILURE_KINDS:
                    cell[1][kind] += kinds.get(kind, 0)
                cell[2].append(run.seed)
        for letter in sorted(pooled):
            episodes, kinds, seeds = pooled[letter]
            shares = " | ".join(f"{100 * kinds[k] / episodes:.1f}" if episodes else "–" for k in FAILURE_KINDS)
            which = f"{', '.join(f's{s}' for s in sorted(seeds))} of {len(t.members[g])}"
            rows.append(f"| {g.label} | {letter} | {which} | {episodes} | {shares} |")
    if not rows:
        return []
    return ["## Where the failures go", "",
            "% of each split's episodes failed in each way (`gscan-ros evaluate` replays the gold and the "
            "predicted actions: docs/model.md, \"Metrics\"), pooled over the seeds named; runs evaluated before "
            "2026-12-01 did not count them, so a column's profile may leave some of its seeds out.", "",
            "| column | split | seeds | episodes | " + " | ".join(map(failure_label, FAILURE_KINDS)) + " |",
            "|---|---|---|---:|" + "---:|" * len(FAILURE_KINDS), *rows, ""]


def _examples_text(column: str, runs: list[RunResult]) -> str:
    """Examples the runs trained on (mean over seeds) beside those of the paper's `column`,
    e.g. '2.0M (30M: 1/15)'."""
    paper = PAPER_EXAMPLES.get(column, PAPER_EXAMPLES_DEFAULT)
    seen = [r.updates * r.batch_size for r in runs if r.batch_size]
    theirs = "not stated" if paper is None else f"{paper / 1e6:.0f}M"
    if not seen:
        return f"– ({theirs})"
    mean = statistics.fmean(seen)
    ours = f"{mean / 1e6:.1f}M" if mean >= 1e6 else f"{mean / 1e3:.0f}k"
    return f"{ours} ({theirs})" if paper is None else f"{ours} ({theirs}: 1/{paper / mean:.0f})"


def _notes(t: Tables) -> list[str]:
    out = ["## Notes", ""]
    if t.retrains:
        out += [f"### Runs the plan retrains ({RETRAIN_MARK})", "",
                f"Their results stand in the cells marked {RETRAIN_MARK} until their retrains replace them "
                "(`gscan-ros experiment --dry-run` lists the same):", ""]
        out += [f"- `{r.name}` ({r.group.label}): {t.retrains[r.name]}." for r in t.runs if r.name in t.retrains]
        out += [""]
    out += ["### Cells whose seeds were trained with different recipes", ""]
    out += t.mixed_recipes() or ["None."]
    out += ["", "### Further from the paper than the paper's std", ""]
    flagged = []
    for column, title, paper in t.table1_columns():
        for row in t.table1_rows():
            cell, figure = t.cell1(column, row), _paper1(paper, row)
            if cell is not None and isinstance(figure, tuple) and abs(cell.mean - figure[0]) > figure[1]:
                flagged.append(_flag(f"{title}, {row}", cell, figure, t.column_rise(column, 1, row)))
    for g in (g for g in t.groups if g.table == 2):
        for row in TABLE2_ROWS:
            cell, figure = t.cell2(g, row), _paper2(g, row)
            if cell is not None and isinstance(figure, tuple) and abs(cell.mean - figure[0]) > figure[1]:
                flagged.append(_flag(f"{g.label}, length {_length_name(row)}", cell, figure, t.group_rise(g)))
    out += flagged or ["None."]
    out += ["", "### The paper's claims", ""]
    out += [_ordered_claim(t, ("semantic", "attention+state", "state"), "attention-only > +Attention > State")]
    out += _much_claim(t)
    out += [_ordered_claim(t, ("semantic", "constituency"), "semantic > constituency"),
            _ordered_claim(t, ("semantic", "dependency"), "semantic > dependency")]
    return out + [""]


def _flag(where: str, cell: Cell, figure: tuple[float, float], trend: float | None) -> str:
    return (f"- {where}: ours {cell.text()} vs paper {figure[0]:.2f} ± {figure[1]:.2f} "
            f"({cell.mean - figure[0]:+.2f}); {_rise_text(trend)}.")


def _ordered_claim(t: Tables, columns: tuple[str, ...], claim: str) -> str:
    """Columns strictly decreasing in the mean over the Table 1 rows they all have (of
    those, the rows the paper reports for every one of them, when there are any: both
    sides then average the same rows), and how many of those rows keep the order."""
    cells = {c: {row: t.cell1(c, row) for row in t.table1_rows()} for c in columns}
    rows = [row for row in t.table1_rows() if all(cells[c][row] is not None for c in columns)]
    missing = [COLUMN_TITLES[c] for c in columns if not any(cells[c].values())]
    if missing or not rows:
        return f"- {claim}: not checked, no results for {', '.join(missing) or 'a common row'}."
    paper_rows = [row for row in rows if all(row in TABLE1[c] for c in columns)]
    rows = paper_rows or rows
    ours = [statistics.fmean(cells[c][row].mean for row in rows) for c in columns]
    holds = all(a > b for a, b in zip(ours, ours[1:]))
    row_wise = sum(all(cells[a][row].mean > cells[b][row].mean for a, b in zip(columns, columns[1:])) for row in rows)
    paper = ""
    if paper_rows:
        means = [statistics.fmean(TABLE1[c][row][0] for row in paper_rows) for c in columns]
        paper = f"; paper: {' > '.join(f'{m:.2f}' for m in means)}"
    which = " (the rows the paper reports for each)" if paper_rows else ""
    return (f"- {claim}: {'holds' if holds else 'does not hold'} — mean over {', '.join(rows)}{which}: "
            f"{' vs '.join(f'{COLUMN_TITLES[c]} {m:.2f}' for c, m in zip(columns, ours))}; "
            f"the order holds row by row on {row_wise} of {len(rows)}{paper}.")


def _much_claim(t: Tables) -> list[str]:
    """Semantic ahead of seq2seq by more than MUCH_POINTS on B, C, every G row and split I
    (lengths 16, 17, >= 18 with targets <= 15 in training)."""
    pairs = []  # (row label, ours semantic, seq2seq (ours, else the paper's), paper difference or None)
    for row in [r for r in t.table1_rows() if r in ("B", "C") or r.startswith("G ")]:
        a, b = t.cell1("semantic", row), t.cell1("seq2seq", row)
        pa, pb = _paper1("semantic", row), _paper1("seq2seq", row)
        if a is not None and b is not None:
            pairs.append((row, a.mean, b.mean, pa[0] - pb[0] if pa and pb else None))
        elif a is not None and pb:  # the plan trains Seq2seq at k = 1 only: the paper's (Ruis et al.'s) figure
            pairs.append((f"{row} (Seq2seq: the paper's figure, no run here)", a.mean, pb[0],
                          pa[0] - pb[0] if pa else None))
    sem = next((g for g in t.groups if g.table == 2 and g.column == "semantic" and g.variant == "<=15"), None)
    s2s = next((g for g in t.groups if g.table == 2 and g.column == "seq2seq" and g.variant == "<=15"), None)
    for row in ("16", "17", ">=18"):
        a, b = (t.cell2(sem, row) if sem else None), (t.cell2(s2s, row) if s2s else None)
        if a is not None and b is not None:
            pa, pb = _paper2(sem, row), _paper2(s2s, row)
            paper = pa[0] - pb[0] if isinstance(pa, tuple) and isinstance(pb, tuple) else None
            pairs.append((f"I length {_length_name(row)}", a.mean, b.mean, paper))
    claim = f"compositional ≫ seq2seq on B, C, G, I (Semantic ahead by more than {MUCH_POINTS:.0f} points)"
    if not pairs:
        return [f"- {claim}: not checked, no Semantic and Seq2seq results on a common row."]
    ahead = sum(a - b > MUCH_POINTS for _, a, b, _ in pairs)
    out = [f"- {claim}: holds on {ahead} of {len(pairs)} rows" + (" — holds." if ahead == len(pairs) else ".")]
    for row, a, b, paper in pairs:
        ref = f" (paper {paper:+.2f})" if paper is not None else ""
        out.append(f"  - {row}: {a:.2f} vs {b:.2f}, {a - b:+.2f}{ref}")
    return out


# ------------------------------------------------------------------------------ figure
def plot_curves(runs: list[RunResult], path: Path) -> None:
    """Dev exact match vs updates, one panel per column (group), one line per seed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, MaxNLocator

    thousands = FuncFormatter(lambda x, _: f"{x / 1000:g}k" if x else "0")
    tables = Tables(runs)
    groups = tables.groups
    ncols = min(4, len(groups))
    nrows = math.ceil(len(groups) / ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(3.6 * ncols, 2.8 * nrows), squeeze=False, sharey=True)
    for ax, group in zip(axes.flat, groups):
        for run in tables.members[group]:
            if run.curve:
                ax.plot(*zip(*run.curve), marker=".", label=f"seed {run.seed}")
        ax.set_title(group.label, fontsize=9)
        ax.set_ylim(0, 100)
        ax.set_xlabel("updates", fontsize=8)
        ax.xaxis.set_major_locator(MaxNLocator(5))
        ax.xaxis.set_major_formatter(thousands)  # 160,000-update runs beside 40,000-update ones
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[1]:  # a group whose runs logged no validation has no line
            ax.legend(fontsize=7, loc="lower right")
    for ax in axes.flat[len(groups):]:
        ax.axis("off")
    for ax in axes[:, 0]:
        ax.set_ylabel("dev exact match (%)", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90, metadata={"Software": None})
    plt.close(fig)


def write_report(dirs: list[Path], out: Path, curves: Path | None, plan: Path | None = None) -> list[RunResult]:
    """Read the runs, write the markdown to `out` and the curves PNG to `curves`; with
    `plan`, mark the runs it retrains."""
    runs = load_runs(dirs)
    link = None if curves is None else Path(os.path.relpath(curves, out.parent)).as_posix()
    notes = sorted({Path(d) / READING for d in dirs if (Path(d) / READING).is_file()})
    retrains = plan_retrains(runs, plan) if plan is not None else None
    text = render(runs, link, [(note.as_posix(), note.read_text()) for note in notes], retrains)
    if curves is not None:
        with replacing(curves) as tmp:
            plot_curves(runs, tmp)
    write_text(out, text)
    return runs


def plan_retrains(runs: list[RunResult], plan_path: Path) -> dict[str, str]:
    """Run name -> why `plan_path` retrains it, from the run's committed files alone (its
    config, its data, its weights), so the report is the same on every machine; runs the
    plan does not name are left alone."""
    from gscan_ros.experiments.plan import load_plan, resolve_config
    from gscan_ros.experiments.state import no_weights, plan_changes
    from gscan_ros.training.trainer import RunFiles

    plan = load_plan(plan_path)
    specs = {spec.name: spec for spec in plan.runs}
    retrains = {}
    for run in runs:
        spec = specs.get(run.name)
        if spec is None or run.directory is None:
            continue
        reasons = plan_changes(run.directory, spec, resolve_config(plan, spec), plan.data_root)
        if not RunFiles(run.directory).model.is_file():
            reasons.append(no_weights())
        if reasons:
            retrains[run.name] = "; ".join(reasons)
    return retrains
