"""TrainConfig: every training knob, from a YAML file plus `--set key=value` overrides.

Model hyper-parameters live under `model:` (fields of the `model_kind`'s config: `ModelConfig`,
`Seq2SeqConfig`, `AuxLossConfig` or `LCGNConfig`); `--set model.rnn_dim=40` reaches them.
Unknown keys are an error naming the key, so a typo never silently trains the default.
"""
from __future__ import annotations

import functools
import math
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

from gscan_ros.errors import GscanError, quoted
from gscan_ros.language.lexicon import LEXICONS
from gscan_ros.language.registry import DEFAULT_PARSER, get_parser
from gscan_ros.model.checkpoint import KINDS, model_classes
from gscan_ros.training.batches import BATCHING
from gscan_ros.user_files import parse_yaml, read_yaml

# Keys that may differ between a run's saved config and the config it goes on with (a
# resume, the plan of a finished run) without making it another run: the budget and the
# machine. `max_updates` only where it cannot move the learning-rate schedule
# (`_decays_to_budget`).
UNTRACKED_KEYS = ("max_updates", "max_minutes", "threads")


# Candidate k of a seed screen trains with seed + SCREEN_SEED_STRIDE * k (distinct for runs
# with seeds below the stride); every seed must be one numpy takes.
SCREEN_SEED_STRIDE = 1000
MAX_SEED = 2**32 - 1


class ConfigError(GscanError):
    """A training config file or override that is malformed or names an unknown key."""


@dataclass
class TrainConfig:
    """Training run settings (defaults: the original's, ylkuo/compositional-gscan `configs/`, unless noted)."""

    model_kind: str = "compositional"
    """'compositional' (Kuo et al.), 'seq2seq' (the gSCAN baseline, LauraRuis/multimodal_seq2seq_gSCAN),
    'auxloss' (Heinze-Deml & Bouchacourt 2020) or 'lcgn' (Gao et al. 2020); docs/model.md."""
    model: dict = field(default_factory=dict)
    """Overrides of the model config's fields (see the model_kind's config class docstrings)."""
    parser: str = DEFAULT_PARSER
    """Command parser building the network: one of `language.BUILTIN_PARSERS` or a registered one."""
    lexicon: str = "wordnet"
    """'wordnet': share modules between WordNet-related words (big/small); 'none': no sharing."""
    batching: str = "mixed"
    """'mixed': batches mix commands (one pass over many graphs); 'per_command': the
    original one-command-per-batch scheme (quirk Q9, docs/model.md)."""
    oversample_word: str = ""
    """Train episodes whose command has this word appear `oversample_factor` times per
    epoch (an ablation for split G: k "cautiously" examples shown as often as k x factor
    would be, results/paper/reading.md); '' = every episode once (the original)."""
    oversample_factor: int = 1
    """Appearances per epoch of the `oversample_word` episodes."""
    batch_size: int = 200
    """Episodes per update."""
    late_batch_size: int = 0
    """From update `late_batch_from` on, batches of this many episodes (a fresh epoch starts
    at the switch); 0 = `batch_size` throughout. Small batches reach high dev accuracy in
    few examples, large ones weaken the noun's colour preference that costs split C
    (docs/results.md, "The faithful recipe along its first 16,000 updates")."""
    late_batch_from: int = 0
    """The update at which `late_batch_size` takes over."""
    lr: float = 1e-3
    """Adam (peak) learning rate, betas 0.9/0.999 (the original: 1e-3, constant)."""
    warmup_updates: int = 0
    """Linear warm-up from 0 to `lr` over this many updates; 0 = none (the original)."""
    lr_decay: str = "none"
    """After warm-up: 'none' (constant, the original), 'cosine' or 'linear' decay to
    `lr * min_lr_ratio` at update `decay_updates`, constant afterwards."""
    decay_updates: int = 0
    """Update at which the decay ends; 0 = `max_updates`."""
    min_lr_ratio: float = 0.1
    """Final learning rate as a fraction of `lr` (with `lr_decay`)."""
    grad_clip: float = 0.0
    """Clip the global gradient norm to this; 0 = no clipping (the original)."""
    target_dev_exact_match: float = 0.0
    """Stop once a validation reaches this dev exact match (%); 0 = train to `max_updates`."""
    max_updates: int = 150_000
    """Stop after this many updates (the paper trains 150k at batch 200)."""
    max_minutes: float = 0.0
    """Wall-clock budget in minutes; 0 = none. Checked after each update."""
    seed: int = 0
    """Seeds python random, numpy and torch; epoch e's order comes from (seed, e)."""
    screen_seeds: int = 0
    """Seed screening (docs/results.md, "The sign of the maps"): start up to this many
    candidates (seeds `seed`, `seed` + 1000, `seed` + 2000, ...), train each for
    `screen_updates` updates, and continue the first whose noun-phrase maps peak on the
    target at least half as often as chance (else the one that peaks there most often). The chosen
    candidate trains on exactly as a run with its seed would, validated on the dev subset of
    the run's own `seed`; the clock counts every candidate. 0 or 1 = no screening; needs a
    model that passes attention maps."""
    screen_updates: int = 1000
    """Updates each screened candidate trains before its maps are read."""
    train_split: str = "train"
    """Split trained on."""
    dev_split: str = "dev"
    """Split used for periodic closed-loop validation."""
    max_train_examples: int = 0
    """Use only the first N training episodes; 0 = all."""
    max_train_target_length: int = 0
    """Train only on episodes of at most this many actions (the original's `max_seq_length`;
    the paper's Table 2 trains split I at 15, 14 and 13); 0 = all."""
    max_dev_target_length: int = 0
    """Validate only on dev episodes of at most this many actions, so that model selection
    sees the distribution trained on (Table 2's 14 and 13 set it to their train cut); 0 = all."""
    include_incomplete: bool = False
    """Also train on recorded episodes that did not end complete (cut at max_steps, preempted,
    rejected): off, since they are no demonstrations (docs/bags.md "Outcomes")."""
    validate_every: int = 500
    """Updates between validations (closed-loop exact match on the dev subset)."""
    max_dev_examples: int = 500
    """Cap on dev episodes per validation (quirk Q1, docs/model.md: the original ignored its cap of 2000);
    a fixed, seeded subset. 0 = the whole dev split."""
    eval_batch_size: int = 1024
    """Episodes decoded together in closed-loop validation."""
    checkpoint_every: int = 500
    """Updates between checkpoints (last.pt; best.pt on better dev exact match)."""
    snapshot_every: int = 0
    """Also keep the weights every N updates as step_<N>.pt (e.g. to evaluate a long run
    at the budget of shorter ones); 0 = never."""
    log_every: int = 50
    """Updates between metrics log lines."""
    threads: int = 0
    """torch intra-op threads; 0 = torch's default."""

    def __post_init__(self) -> None:
        checks = {
            "model_kind": KINDS,
            "lexicon": LEXICONS,
            "batching": BATCHING,
            "lr_decay": ("none", "cosine", "linear"),
        }
        for key, allowed in checks.items():
            if getattr(self, key) not in allowed:
                raise ConfigError(f"{key} must be one of {list(allowed)}, got {quoted(getattr(self, key))}")
        for key in ("batch_size", "max_updates", "validate_every", "checkpoint_every", "log_every", "eval_batch_size"):
            if int(getattr(self, key)) <= 0:
                raise ConfigError(f"{key} must be positive, got {quoted(getattr(self, key))}")
        for key in ("screen_seeds", "screen_updates", "warmup_updates", "decay_updates", "max_train_examples",
                    "max_train_target_length", "max_dev_target_length", "max_dev_examples", "threads"):
            if int(getattr(self, key)) < 0:
                raise ConfigError(f"{key} must be >= 0, got {quoted(getattr(self, key))}")
        for key in ("lr", "min_lr_ratio", "grad_clip", "target_dev_exact_match", "max_minutes"):
            value = float(getattr(self, key))
            if not math.isfinite(value) or value < 0:
                raise ConfigError(f"{key} must be a finite number >= 0, got {quoted(getattr(self, key))}")
        if self.lr <= 0:
            raise ConfigError(f"lr must be positive, got {quoted(self.lr)}")
        last_seed = int(self.seed) + SCREEN_SEED_STRIDE * max(int(self.screen_seeds) - 1, 0)
        if int(self.seed) < 0 or last_seed > MAX_SEED:
            raise ConfigError(f"seed must be in [0, {MAX_SEED}] (numpy's range) for every screen candidate "
                              f"(seed + {SCREEN_SEED_STRIDE} k), got {quoted(self.seed)}")
        if self.lr_decay != "none" and 0 < int(self.decay_updates) <= int(self.warmup_updates):
            raise ConfigError(f"decay_updates ({self.decay_updates}) must come after warmup_updates "
                              f"({self.warmup_updates}): the decay would start at its end")
        if self.min_lr_ratio > 1:
            raise ConfigError(f"min_lr_ratio must be in [0, 1], got {quoted(self.min_lr_ratio)}")
        if self.target_dev_exact_match > 100:
            raise ConfigError("target_dev_exact_match is a percentage (0-100), "
                              f"got {quoted(self.target_dev_exact_match)}")
        if isinstance(self.oversample_factor, bool) or not isinstance(self.oversample_factor, int) \
                or self.oversample_factor < 1:
            raise ConfigError(f"oversample_factor must be an integer >= 1, got {quoted(self.oversample_factor)}")
        if not isinstance(self.oversample_word, str) or (self.oversample_factor > 1) != bool(self.oversample_word):
            raise ConfigError("oversample_word and oversample_factor > 1 go together "
                              f"(got {quoted(self.oversample_word)} and {quoted(self.oversample_factor)})")
        if int(self.late_batch_size) < 0 or int(self.late_batch_from) < 0:
            raise ConfigError("late_batch_size and late_batch_from must be >= 0, "
                              f"got {quoted(self.late_batch_size)} and {quoted(self.late_batch_from)}")
        if bool(self.late_batch_size) != bool(self.late_batch_from):
            raise ConfigError("late_batch_size and late_batch_from go together "
                              f"(got {quoted(self.late_batch_size)} and {quoted(self.late_batch_from)})")
        if self.late_batch_from and self.screen_seeds > 1 and self.late_batch_from <= self.screen_updates:
            raise ConfigError(f"late_batch_from ({self.late_batch_from}) must come after the seed screen's "
                              f"{self.screen_updates} updates")
        if int(self.snapshot_every) < 0:
            raise ConfigError(f"snapshot_every must be >= 0, got {quoted(self.snapshot_every)}")
        if not isinstance(self.model, dict):
            raise ConfigError(f"model must be a mapping of model settings, got {quoted(self.model)}")
        model_config = self.model_config()  # validates model keys
        if self.screen_seeds > 1:
            if not getattr(model_config, "uses_attention", False):
                raise ConfigError("screen_seeds needs a model that passes attention maps "
                                  f"(model_kind compositional, message attention); set screen_seeds: 0 for "
                                  f"{self.model_kind} / {self.model.get('message', 'attention')}")
            if not 0 < self.screen_updates < self.max_updates:
                raise ConfigError(f"screen_updates must be in (0, max_updates), got {quoted(self.screen_updates)}")
        if getattr(model_config, "message", None) == "state" and self.lexicon != "none":
            # One module serves big and small, its words told apart by their attention heads
            # alone; a state message reads no head, so "big" and "small" would act the same.
            raise ConfigError(f"message 'state' passes no attention map, so the words a shared module serves "
                              f"(big|small under lexicon {self.lexicon}) would be one word; set lexicon: none")

    def batch_size_at(self, step: int) -> int:
        """Episodes in update `step` (0-based)."""
        return self.late_batch_size if self.late_batch_size and step >= self.late_batch_from else self.batch_size

    def lr_factor(self, step: int) -> float:
        """Multiplier of `lr` for update `step` (0-based): warm-up, then the decay."""
        if step < self.warmup_updates:
            return (step + 1) / self.warmup_updates
        if self.lr_decay == "none":
            return 1.0
        end = self.decay_updates or self.max_updates
        span = max(end - self.warmup_updates, 1)
        progress = min(max(step - self.warmup_updates, 0) / span, 1.0)
        shape = 0.5 * (1.0 + math.cos(math.pi * progress)) if self.lr_decay == "cosine" else 1.0 - progress
        return self.min_lr_ratio + (1.0 - self.min_lr_ratio) * shape

    def model_config(self):
        """The config of the `model_kind` these settings describe (ConfigError on bad keys)."""
        return model_config(self.model_kind, self.model)

    def to_dict(self) -> dict:
        return asdict(self)

    def resolved(self) -> dict:
        """`to_dict` with every model setting written out, defaults included: what a run
        saves (config.yaml, checkpoints), so a default that changes later cannot change
        what the saved run says it trained with."""
        return {**asdict(self), "model": self.model_config().to_dict()}

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        if not isinstance(d, dict):
            raise ConfigError(f"a training config must be a mapping, got {type(d).__name__}")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ConfigError(f"unknown config key(s) {quoted(unknown)}; known: {sorted(known)}")
        types = {f.name: f.type for f in fields(cls)}
        values = {}
        for key, value in d.items():
            kind = {"int": int, "float": float, "str": str, "dict": dict, "bool": bool}[types[key]]
            if kind is bool:
                if not isinstance(value, bool):
                    raise ConfigError(f"config key {key!r} expects true or false, got {quoted(value)}")
                values[key] = value
                continue
            if kind is int and (isinstance(value, bool) or (isinstance(value, float) and not value.is_integer())):
                raise ConfigError(f"config key {key!r} expects an integer, got {quoted(value)}")  # int() would truncate
            try:
                values[key] = kind(value) if kind is not dict else dict(value or {})
            except (TypeError, ValueError):
                raise ConfigError(f"config key {key!r} expects {types[key]}, got {quoted(value)}") from None
        return cls(**values)

    @classmethod
    def load(cls, path: str | Path | None, overrides: list[str] = ()) -> "TrainConfig":
        """YAML file (None: defaults) + 'key=value' overrides ('model.key=value' for model fields)."""
        data: dict = {}
        if path is not None:
            data = read_yaml(path, f"config {str(path)!r}", ConfigError)
            if data is None:
                raise ConfigError(f"config {str(path)!r} holds no settings; leave --config out to use the defaults")
            if not isinstance(data, dict):
                raise ConfigError(f"config {str(path)!r} must be a mapping")
        if not isinstance(data.get("model") or {}, dict):
            raise ConfigError(f"model must be a mapping of model settings, got {quoted(data['model'])}")
        data = {**data, "model": dict(data.get("model") or {})}
        for item in overrides:
            key, sep, raw = item.partition("=")
            if not sep or not key:
                raise ConfigError(f"override {quoted(item)} must look like key=value")
            value = parse_yaml(raw, f"override {quoted(item)}", ConfigError)
            if key.startswith("model."):
                data["model"][key[len("model."):]] = value
            else:
                data[key] = value
        return cls.from_dict(data)


def config_changes(saved: dict, cfg: TrainConfig, events: list[dict] = ()) -> list[str]:
    """The keys where a run's saved config (its config.yaml, or the `train_config` of its
    checkpoint) differs from `cfg`, the one rule of what may change under a run: the
    `UNTRACKED_KEYS` aside, model settings compared with their defaults filled in. A field
    added to TrainConfig since the run started counts as its default there (the behaviour
    the run had); keys TrainConfig no longer has are ignored. `screen_seeds` may change
    where the run's seed screen (its metrics.jsonl `events`) would have kept the same seed."""
    defaults = TrainConfig().to_dict()
    old, new = {**defaults, **saved}, cfg.to_dict()
    untracked = set(UNTRACKED_KEYS)
    if _decays_to_budget(old) or _decays_to_budget(new):
        untracked.discard("max_updates")
    keys = sorted(set(new) - untracked - {"model"})
    changed = [k for k in keys if old[k] != new[k]]
    if "screen_seeds" in changed and _screen_kept(events, new["screen_seeds"]):
        changed.remove("screen_seeds")
    old_model, new_model = _saved_model_settings(saved), cfg.model_config().to_dict()
    if old_model is None:
        return changed + ["model"]
    return changed + [f"model.{k}" for k in sorted(set(old_model) & set(new_model)) if old_model[k] != new_model[k]]


def _decays_to_budget(config: dict) -> bool:
    """The decay of a config (`TrainConfig.to_dict`) ends at `max_updates` (`decay_updates`
    0, `lr_factor`), so its budget shapes the learning-rate schedule."""
    return config["lr_decay"] != "none" and not config["decay_updates"]


def _screen_kept(events: list[dict], screen_seeds: int) -> bool:
    """The run's seed screen passed at a candidate that `screen_seeds` candidates also
    reach, so screening with that many would have kept the same seed (the same run)."""
    passed = [e["candidate"] for e in events if e.get("event") == "screen" and e.get("passed")]
    return bool(passed) and passed[0] < max(screen_seeds, 1)


def model_config(model_kind: str, model: dict):
    """The model config of `model_kind` from its settings `model` (ConfigError on bad keys)."""
    _, cls = model_classes(model_kind)
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(model) - known)
    if unknown:
        raise ConfigError(f"unknown model setting(s) {quoted(unknown)}; known: {sorted(known)}")
    try:
        return cls(**model)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"bad model setting: {exc}") from None


def _saved_model_settings(config: dict) -> dict | None:
    """Every model setting of a saved config (None if they no longer load). A compositional
    network saved before `init_fan_in` existed was initialised as 'table' does, which
    differs from the default 'module' only where its parse has modules of several arguments."""
    model = dict(config.get("model") or {})
    kind = config.get("model_kind", "compositional")
    try:
        settings = model_config(kind, model).to_dict()
        if "init_fan_in" in settings and "init_fan_in" not in model \
                and _widest_module(config.get("parser", DEFAULT_PARSER)) > 1:
            settings["init_fan_in"] = "table"
    except GscanError:
        return None
    return settings


@functools.lru_cache(maxsize=None)
def _widest_module(parser: str) -> int:
    """The most argument slots a module of `parser`'s parses of the gSCAN commands has."""
    from gscan_ros.language.grammar import all_commands

    parse = get_parser(parser).parse
    return max(max(1, node.arity) for command in all_commands() for node in parse(command).nodes)
