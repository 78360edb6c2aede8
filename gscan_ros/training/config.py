"""TrainConfig: every training knob, from a YAML file plus `--set key=value` overrides.

Model hyper-parameters live under `model:` (fields of `ModelConfig`, or of
`Seq2SeqConfig` when `model_kind: seq2seq`); `--set model.rnn_dim=40` reaches them.
Unknown keys are an error naming the key, so a typo never silently trains the default.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import yaml

from gscan_ros.errors import GscanError


class ConfigError(GscanError):
    """A training config file or override that is malformed or names an unknown key."""


@dataclass
class TrainConfig:
    """Training run settings (defaults: the original's, GSCAN_SPEC §8.7, unless noted)."""

    model_kind: str = "compositional"
    """'compositional' (Kuo et al.) or 'seq2seq' (the gSCAN baseline, GSCAN_SPEC §9)."""
    model: dict = field(default_factory=dict)
    """Overrides of the model config's fields (see ModelConfig / Seq2SeqConfig docstrings)."""
    parser: str = "semantic"
    """Command parser building the network: semantic | constituency | dependency."""
    lexicon: str = "wordnet"
    """'wordnet': share modules between WordNet-related words (big/small); 'none': no sharing."""
    batching: str = "mixed"
    """'mixed': batches mix commands (one pass over many graphs); 'per_command': the
    original one-command-per-batch scheme (quirk Q9)."""
    batch_size: int = 200
    """Episodes per update."""
    lr: float = 1e-3
    """Adam learning rate (betas 0.9/0.999, no decay, no clipping, as the original)."""
    max_updates: int = 150_000
    """Stop after this many updates (the paper trains 150k at batch 200)."""
    max_minutes: float = 0.0
    """Wall-clock budget in minutes; 0 = none. Checked after each update."""
    seed: int = 0
    """Seeds python random, numpy and torch; epoch e's order comes from (seed, e)."""
    train_split: str = "train"
    """Split trained on."""
    dev_split: str = "dev"
    """Split used for periodic closed-loop validation."""
    max_train_examples: int = 0
    """Use only the first N training episodes; 0 = all."""
    validate_every: int = 500
    """Updates between validations (closed-loop exact match on the dev subset)."""
    max_dev_examples: int = 500
    """Cap on dev episodes per validation (quirk Q1: the original ignored its cap of 2000);
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
            "model_kind": ("compositional", "seq2seq"),
            "lexicon": ("wordnet", "none"),
            "batching": ("mixed", "per_command"),
        }
        for key, allowed in checks.items():
            if getattr(self, key) not in allowed:
                raise ConfigError(f"{key} must be one of {list(allowed)}, got {getattr(self, key)!r}")
        for key in ("batch_size", "max_updates", "validate_every", "checkpoint_every", "log_every", "eval_batch_size"):
            if int(getattr(self, key)) <= 0:
                raise ConfigError(f"{key} must be positive, got {getattr(self, key)!r}")
        if int(self.snapshot_every) < 0:
            raise ConfigError(f"snapshot_every must be >= 0, got {self.snapshot_every!r}")
        if not isinstance(self.model, dict):
            raise ConfigError(f"model must be a mapping of model settings, got {self.model!r}")
        self.model_config()  # validates model keys

    def model_config(self):
        """The ModelConfig / Seq2SeqConfig these settings describe (ConfigError on bad keys)."""
        if self.model_kind == "compositional":
            from gscan_ros.model.compositional import ModelConfig as cls
        else:
            from gscan_ros.model.seq2seq import Seq2SeqConfig as cls
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(self.model) - known)
        if unknown:
            raise ConfigError(f"unknown model setting(s) {unknown}; known: {sorted(known)}")
        try:
            return cls(**self.model)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"bad model setting: {exc}") from None

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        if not isinstance(d, dict):
            raise ConfigError(f"a training config must be a mapping, got {type(d).__name__}")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ConfigError(f"unknown config key(s) {unknown}; known: {sorted(known)}")
        types = {f.name: f.type for f in fields(cls)}
        values = {}
        for key, value in d.items():
            kind = {"int": int, "float": float, "str": str, "dict": dict}[types[key]]
            try:
                values[key] = kind(value) if kind is not dict else dict(value or {})
            except (TypeError, ValueError):
                raise ConfigError(f"config key {key!r} expects {types[key]}, got {value!r}") from None
        return cls(**values)

    @classmethod
    def load(cls, path: str | Path | None, overrides: list[str] = ()) -> "TrainConfig":
        """YAML file (None: defaults) + 'key=value' overrides ('model.key=value' for model fields)."""
        data: dict = {}
        if path is not None:
            try:
                data = yaml.safe_load(Path(path).read_text()) or {}
            except OSError as exc:
                raise ConfigError(f"cannot read config {str(path)!r}: {exc.strerror}") from None
            except yaml.YAMLError as exc:
                raise ConfigError(f"config {str(path)!r} is not valid YAML: {exc}") from None
            if not isinstance(data, dict):
                raise ConfigError(f"config {str(path)!r} must be a mapping")
        data = {**data, "model": dict(data.get("model") or {})}
        for item in overrides:
            key, sep, raw = item.partition("=")
            if not sep or not key:
                raise ConfigError(f"override {item!r} must look like key=value")
            value = yaml.safe_load(raw)
            if key.startswith("model."):
                data["model"][key[len("model."):]] = value
            else:
                data[key] = value
        return cls.from_dict(data)
