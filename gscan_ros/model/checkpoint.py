"""Checkpoints: one plain dict, loadable with `torch.load(..., weights_only=True)`.

Layout (format 1)::

    {"format": 1, "kind": "compositional" | "seq2seq" | "auxloss" | "lcgn",
     "model_config": {...}, "vocabulary": {...}, "lexicon": {...}, "parser": "semantic",
     "state_dict": {...}, "step": int, "metrics": {...},
     # training checkpoints only (stripped from shipped models):
     "train_config": {...}, "optimizer": {...}, "rng": {...}}

Configs and vocabularies are stored as plain dicts/lists, never pickled objects, so a
checkpoint never executes code on load. A checkpoint whose tensors or vocabulary do not
fit the model it is loaded into raises `CheckpointError` naming the mismatch.

This module sits above the model kinds: it builds a checkpoint's model through the
`MODEL_CLASSES` table, and no model kind imports it.
"""
from __future__ import annotations

import os
import zipfile
from pathlib import Path

import torch
from torch import nn

from gscan_ros.errors import CheckpointError, LexiconError, quoted, shortened
from gscan_ros.language.lexicon import Lexicon
from gscan_ros.model.auxloss import AuxLoss
from gscan_ros.model.compositional import CompositionalNetwork
from gscan_ros.model.config import INIT_SETTINGS, AuxLossConfig, LCGNConfig, ModelConfig, Seq2SeqConfig
from gscan_ros.model.lcgn import LCGN
from gscan_ros.model.modules import ModuleTable
from gscan_ros.model.seq2seq import Seq2Seq
from gscan_ros.outputs import replace_durably

FORMAT = 1
MODEL_CLASSES = {model.kind: (model, config) for model, config in [
    (CompositionalNetwork, ModelConfig),
    (Seq2Seq, Seq2SeqConfig),
    (AuxLoss, AuxLossConfig),
    (LCGN, LCGNConfig),
]}
"""Model kind (a checkpoint's "kind", the class's `kind`) -> its model class and config dataclass."""
KINDS = tuple(MODEL_CLASSES)
MAX_CHECKPOINT_BYTES = 1 << 30
"""Most bytes a checkpoint may hold, its file and its tensors as its zip declares them: the
shipped model holds 1.1 MB, a training checkpoint with its optimizer state a few MB."""
MAX_CHECKPOINT_ENTRIES = 10_000
"""Most files in a checkpoint's zip: one per tensor and a few more (28 in the shipped model)."""


def model_classes(kind: str) -> tuple[type, type]:
    """The model class of `kind` and its config dataclass; CheckpointError for an unknown kind."""
    if kind not in KINDS:  # a tuple: a checkpoint's kind may be any value, hashable or not
        raise CheckpointError(f"unknown model kind {quoted(kind)}; expected one of {KINDS}")
    return MODEL_CLASSES[kind]


def build_model(kind: str, model_config: dict, vocabulary: dict) -> nn.Module:
    """A fresh model of `kind` from plain-dict config and vocabulary (command tokens, or the
    compositional network's modules)."""
    model_class, config_class = model_classes(kind)
    if kind == "compositional":
        return model_class(config_class.from_dict(model_config), ModuleTable.from_list(vocabulary["modules"]))
    return model_class(config_class.from_dict(model_config), list(vocabulary["tokens"]))


def parameter_count(model: nn.Module) -> int:
    """The parameters a model computes with: a compositional network's stacked entries past
    a module's own slots (`WordModuleBank.unused_parameters`) do not count."""
    total = sum(p.numel() for p in model.parameters())
    return total - model.bank.unused_parameters() if model.kind == "compositional" else total


def model_vocabulary(model: nn.Module) -> dict:
    if model.kind == "compositional":
        return {"modules": model.table.to_list()}
    return {"tokens": list(model.tokens)}


def checkpoint_dict(model: nn.Module, *, parser: str, lexicon: Lexicon, step: int, metrics: dict,
                    **training_state) -> dict:
    return {
        "format": FORMAT,
        "kind": model.kind,
        "model_config": model.cfg.to_dict(),
        "vocabulary": model_vocabulary(model),
        "lexicon": lexicon.to_dict(),
        "parser": parser,
        # on the CPU, whatever the device
        "state_dict": {k: v.detach().to("cpu", copy=True) for k, v in model.state_dict().items()},
        "step": int(step),
        "metrics": dict(metrics),
        **training_state,
    }


def previous_checkpoint(path: str | os.PathLike) -> Path:
    """Where `save_checkpoint(path, ..., keep_previous=True)` keeps the checkpoint it replaced
    (`last.pt` -> `last.prev.pt`)."""
    path = Path(path)
    return path.with_name(f"{path.stem}.prev{path.suffix}")


def save_checkpoint(path: str | os.PathLike, ckpt: dict, keep_previous: bool = False) -> None:
    """Write to a temp file and rename it into place durably (`replace_durably`), so neither
    an interrupted save nor a crash leaves `path` half written. `keep_previous`: the
    checkpoint `path` held moves to `previous_checkpoint(path)`, one generation back for a
    reader that finds `path` damaged or missing all the same."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    try:
        torch.save(ckpt, tmp)
    except (OSError, RuntimeError) as exc:  # torch reports a full disk as a RuntimeError
        tmp.unlink(missing_ok=True)
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc).strip().splitlines()[-1]
        raise CheckpointError(f"cannot write checkpoint {str(path)!r}: {shortened(reason)}") from None
    replace_durably(tmp, path, keep_old_as=previous_checkpoint(path) if keep_previous else None)


def read_checkpoint(path: str | os.PathLike) -> dict:
    """The raw checkpoint dict; CheckpointError if missing, unreadable or of another format."""
    path = Path(path)
    if path.is_dir():
        raise CheckpointError(f"checkpoint {str(path)!r} is a directory, not a checkpoint file")
    if not path.is_file():
        raise CheckpointError(f"checkpoint {str(path)!r} does not exist")
    _check_archive(path)
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for corrupt/unsafe files
        raise CheckpointError(f"cannot read checkpoint {str(path)!r}: {_load_problem(exc)}") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        raise CheckpointError(f"{str(path)!r} is not a gscan_ros checkpoint of format {FORMAT}")
    missing = [k for k in ("kind", "model_config", "vocabulary", "lexicon", "parser", "state_dict") if k not in ckpt]
    if missing:
        raise CheckpointError(f"checkpoint {str(path)!r} lacks {missing}")
    validate_checkpoint(ckpt, path)
    return ckpt


def _check_archive(path: Path) -> None:
    """Refuse, before torch unpacks anything, a file that is not a zip archive, whose
    sizes pass the bounds (torch allocates every tensor at the size the zip declares, so a
    5 MB file that declares 4 GB of tensors would otherwise cost 4 GB before any check), or
    whose bytes no longer match their CRCs."""
    where = f"checkpoint {str(path)!r}"
    try:
        size = path.stat().st_size
        if size > MAX_CHECKPOINT_BYTES:
            raise CheckpointError(f"{where} has {size:,} bytes, more than the {MAX_CHECKPOINT_BYTES:,} allowed")
        with open(path, "rb") as f:
            # zipfile's reader of the end record (zip64 too): the entry count, read before
            # ZipFile lists the entries (~500 bytes of memory each)
            end = zipfile._EndRecData(f)
            f.seek(0)
            zip_start = f.read(4) == b"PK\x03\x04"
        if end is None and zip_start:  # a zip archive cut short: a copy or download that did not finish
            raise CheckpointError(f"{where} is truncated (a zip archive without its end record)")
        if end is None:
            raise CheckpointError(f"{where} is not a checkpoint (torch.save writes a zip archive)")
        entries = end[zipfile._ECD_ENTRIES_TOTAL]
        if entries > MAX_CHECKPOINT_ENTRIES:
            raise CheckpointError(f"{where} holds {entries:,} files, more than the {MAX_CHECKPOINT_ENTRIES:,} allowed")
        with zipfile.ZipFile(path) as archive:
            declared = sum(info.file_size for info in archive.infolist())
            if declared > MAX_CHECKPOINT_BYTES:
                raise CheckpointError(f"{where} declares {declared:,} bytes of content, more than the "
                                      f"{MAX_CHECKPOINT_BYTES:,} allowed")
            damaged = _damaged_entry(archive)
    except (OSError, zipfile.BadZipFile) as exc:
        raise CheckpointError(f"cannot read {where}: {exc}") from None
    if damaged:
        raise CheckpointError(f"{where} is corrupt: {damaged}")


def _damaged_entry(archive: zipfile.ZipFile) -> str | None:
    """What of `archive` fails its CRC or cannot be unpacked, or None. torch.load checks no
    CRC, so flipped bytes inside a tensor would load as other weights without a word."""
    try:
        name = archive.testzip()
    except Exception as exc:  # zipfile raises many types for a damaged entry (zlib.error, EOFError, ...)
        return f"an entry cannot be unpacked ({type(exc).__name__}: {exc})"
    return None if name is None else f"the CRC of {name} does not match its bytes"


def validate_checkpoint(ckpt: dict, path: str | os.PathLike) -> None:
    """Refuse, at load, a checkpoint no working model can come from: an unknown kind, an
    empty or malformed vocabulary, a config with non-positive sizes, NaN/inf weights (which
    would otherwise decode garbage and score 0 % without a word)."""
    where = f"checkpoint {str(path)!r}"
    kind = ckpt["kind"]
    if kind not in KINDS:
        raise CheckpointError(f"{where}: unknown model kind {quoted(kind)}; expected one of {KINDS}")
    entries = "modules" if kind == "compositional" else "tokens"
    vocabulary = ckpt["vocabulary"].get(entries) if isinstance(ckpt["vocabulary"], dict) else None
    if not isinstance(vocabulary, list) or not vocabulary:
        raise CheckpointError(f"{where}: empty vocabulary (no {entries})")
    if kind == "compositional":
        for spec in ModuleTable.from_list(vocabulary).specs:
            if spec.arity < 0 or spec.num_heads < 1:
                raise CheckpointError(f"{where}: module {quoted(spec.key)} has arity {spec.arity} and "
                                      f"{spec.num_heads} heads (need >= 0 and >= 1)")
    _, config_class = model_classes(kind)
    try:
        config_class.from_dict(ckpt["model_config"])
    except (TypeError, ValueError, AttributeError) as exc:
        raise CheckpointError(f"{where}: model_config: {exc}") from None
    state = ckpt["state_dict"]
    if not isinstance(state, dict) or not state:
        raise CheckpointError(f"{where}: state_dict holds no tensors")
    for name, tensor in state.items():
        if not isinstance(tensor, torch.Tensor):
            raise CheckpointError(f"{where}: state_dict entry {quoted(name)} is not a tensor")
        if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
            raise CheckpointError(f"{where}: tensor {quoted(name)} holds NaN or infinite values")


def _load_problem(exc: Exception) -> str:
    """torch's reason, without its advice to load with `weights_only=False`.

    That advice means executing the file's code, which a checkpoint never needs (and a
    node must never do with a file it was handed), so only the unpickler's finding is kept.
    """
    text = str(exc)
    if "weights_only" not in text:
        return f"{type(exc).__name__}: {text}"
    finding = text.partition("WeightsUnpickler error:")[2].strip()
    finding = finding.splitlines()[0].split(". ")[0].rstrip(".") if finding else "unsupported content"
    return f"not a plain tensor checkpoint ({finding}); gscan_ros loads checkpoints without running their code"


def restore_model(ckpt: dict, model: nn.Module | None = None) -> nn.Module:
    """Load the checkpoint's weights into `model` (built from the checkpoint when None).

    With a given model, its kind, config (but the settings of the initialisation alone,
    `INIT_SETTINGS`) and vocabulary must equal the checkpoint's.
    """
    if model is None:
        model = build_model(ckpt["kind"], ckpt["model_config"], ckpt["vocabulary"])
    else:
        if model.kind != ckpt["kind"]:
            raise CheckpointError(f"checkpoint holds a {ckpt['kind']} model, not a {model.kind} model")
        # settings added after the checkpoint was written take their defaults; those of the
        # initialisation alone do not matter here
        saved = type(model.cfg).from_dict(ckpt["model_config"]).to_dict()
        diff = sorted(k for k, v in model.cfg.to_dict().items() if saved.get(k) != v and k not in INIT_SETTINGS)
        if diff:
            raise CheckpointError(f"checkpoint model config differs from the model's in {diff}")
        if model_vocabulary(model) != ckpt["vocabulary"]:
            raise CheckpointError(_vocabulary_diff(model_vocabulary(model), ckpt["vocabulary"]))
    state = ckpt["state_dict"]
    own = model.state_dict()
    for key, value in own.items():
        if key not in state:
            raise CheckpointError(f"checkpoint lacks tensor {key!r}")
        if tuple(state[key].shape) != tuple(value.shape):
            raise CheckpointError(
                f"tensor {key!r} has shape {tuple(state[key].shape)} in the checkpoint, "
                f"{tuple(value.shape)} in the model"
            )
    extra = sorted(set(state) - set(own))
    if extra:
        raise CheckpointError(f"checkpoint has tensors the model lacks: {quoted(extra)}")
    model.load_state_dict(state)
    return model


def checkpoint_lexicon(ckpt: dict) -> Lexicon:
    try:
        return Lexicon.from_dict(ckpt["lexicon"])
    except LexiconError as exc:
        raise CheckpointError(f"checkpoint lexicon: {exc}") from None


def _vocabulary_diff(mine: dict, theirs: dict) -> str:
    def keys(v: dict) -> set[str]:
        return {m["key"] for m in v.get("modules", [])} | set(v.get("tokens", []))

    only_model, only_ckpt = sorted(keys(mine) - keys(theirs)), sorted(keys(theirs) - keys(mine))
    if only_model or only_ckpt:
        detail = f"model-only {quoted(only_model)}, checkpoint-only {quoted(only_ckpt)}"
    else:
        detail = "arity/heads differ"
    return f"checkpoint vocabulary does not match the model's ({detail})"
