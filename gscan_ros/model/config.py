"""The hyper-parameters of every model kind: the frozen dataclasses checkpoints store.

`ModelConfig` is the compositional network's (Kuo et al. 2021; defaults from their code,
ylkuo/compositional-gscan, "CG"); the visual encoder every kind shares
(`encoders.VisualEncoder`) reads its CNN settings from one. `Seq2SeqConfig` is the gSCAN
baseline's (LauraRuis/multimodal_seq2seq_gSCAN, "MM"), `AuxLossConfig` and `LCGNConfig`
those of Table 1's other baselines. A checkpoint holds a config's `to_dict()`, plain
values only, so loading one never executes code.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

from gscan_ros.errors import CheckpointError, quoted
from gscan_ros.world.types import GRID_SIZE, NUM_CHANNELS, SUPPORTED_GRID_SIZES, Action

MESSAGES = ("attention", "state", "attention+state")
ATTENTION_STATES = ("broadcast", "add")
SIZE_MAPS = ("softmax", "minmax")
OVERLAPS = ("minmax", "cosine")
INIT_FAN_INS = ("module", "table")
# Model settings that shape only the initial weights: a loaded checkpoint's weights replace
# them, so loading into a model does not compare them.
INIT_SETTINGS = ("init_fan_in",)


class SerializableConfig:
    """to_dict/from_dict of the frozen config dataclasses that checkpoints store (tuples
    as lists; unknown keys are a CheckpointError)."""

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict):
        unknown = sorted(set(d) - {f.name for f in fields(cls)})
        if unknown:
            raise CheckpointError(f"unknown {cls.__name__} keys {quoted(unknown)}")
        return cls(**d)


# Bounds of the sizes, far above any real config (the shipped ones: widths up to 100, 2 GRU
# layers, 4 LCGN rounds, 3 kernels of at most 13): a size in the thousands would only fail
# in torch's allocator, or take the machine's memory.
MAX_WIDTH = 512
"""Most units of a layer: channels, embedding, attention, hidden and node widths."""
MAX_DEPTH = 8
"""Most stacked layers (`rnn_layers`), message-passing rounds (`rounds`) and conv branches (`cnn_kernels`)."""
MAX_KERNEL = 2 * SUPPORTED_GRID_SIZES[-1] - 1
"""The widest conv kernel (31): a wider one sees no more of the largest grid."""


def check_settings(cfg, sizes: tuple[str, ...], rates: tuple[str, ...], depths: tuple[str, ...] = ()) -> None:
    """ValueError unless the settings `sizes` of `cfg` are integers in [1, MAX_WIDTH], its
    `depths` in [1, MAX_DEPTH], its `rates` numbers in [0, 1) and its `cnn_kernels` at most
    MAX_DEPTH odd integers in [1, MAX_KERNEL] (stored as a tuple). Settings come from YAML
    and checkpoints: a list, a float, a negative or a huge size fails here, not in torch."""
    for name in (*sizes, *depths):
        value = getattr(cfg, name)
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {quoted(value)}")
        bound = MAX_DEPTH if name in depths else MAX_WIDTH
        if value > bound:
            raise ValueError(f"{name} must be at most {bound}, got {quoted(value)}")
    kernels = cfg.cnn_kernels
    if not (isinstance(kernels, (list, tuple)) and 0 < len(kernels) <= MAX_DEPTH
            and all(isinstance(k, int) and not isinstance(k, bool) and 0 < k <= MAX_KERNEL and k % 2
                    for k in kernels)):
        raise ValueError(f"cnn_kernels must be a list of 1 to {MAX_DEPTH} odd integers in [1, {MAX_KERNEL}], "
                         f"got {quoted(kernels)}")
    object.__setattr__(cfg, "cnn_kernels", tuple(kernels))
    for name in rates:
        value = getattr(cfg, name)
        if not (isinstance(value, (int, float)) and 0 <= value < 1):
            raise ValueError(f"{name} must be a number in [0, 1), got {quoted(value)}")
    if "num_actions" in sizes and cfg.num_actions != len(Action):  # an output per Action id, <eos> included
        raise ValueError(f"num_actions must be {len(Action)} (the actions and <eos>), got {quoted(cfg.num_actions)}")


@dataclass(frozen=True)
class ModelConfig(SerializableConfig):
    """Hyper-parameters of the compositional network (defaults: CG `config_train.yaml`)."""

    grid_size: int = GRID_SIZE
    """Side of the square grid; the CNN keeps it ('same' padding), 36 cells for gSCAN."""
    in_channels: int = NUM_CHANNELS
    """Channels of the one-hot observation (16 in the released order, LauraRuis/groundedSCAN `Grid.encode`)."""
    cnn_kernels: tuple[int, ...] = (1, 5, 7)
    """Kernel sizes of the parallel conv branches (CG: 1, 5 and `cnn_kernel_size` 7)."""
    cnn_channels: int = 50
    """Output channels per conv branch; cell features have len(cnn_kernels) * this."""
    cnn_dropout: float = 0.1
    """Dropout on the concatenated, ReLU'd cell features (training only)."""
    att_dim: int = 10
    """Width each attention input (weighted features per slot, hidden state) is projected to."""
    rnn_layers: int = 2
    """GRU layers per word module; every layer's state feeds the module's attention."""
    rnn_dim: int = 20
    """GRU hidden size per layer (CG main config 20; its no-attention config uses 40)."""
    message: str = "attention"
    """What children pass to parents: 'attention' maps (paper), 'state' (hidden states, no
    attention at all: CG `no_attention`), or 'attention+state' (CG `pass_state`)."""
    antonym_weight: float = 1.0
    """Weight of the antonym overlap loss (CG `compare_weight`); 0 disables the term."""
    attention_state: str = "broadcast"
    """How a module's previous state enters its attention MLP. 'broadcast' (CG's
    `AttentionArgN`): projected, concatenated after the arguments' projections and broadcast over the
    cells, where it cancels in the softmax. 'add': added to every argument's projection
    before the ReLU, so the module's own state shapes its map (one reading of the paper's
    "mapped to the same dimension before being combined"). Same parameters either way;
    'add' runs every module's GRU and trains step by step."""
    size_map: str = "softmax"
    """The map an antonym-pair module (big|small) passes to its parent: its 'softmax'
    attention (this project's default), or 'minmax': the min-max normalised map of the
    overlap loss, as the original code passes it (CG `SentenceNetwork.loss`; quirk Q16, docs/model.md) and as the
    published numbers were produced."""
    overlap: str = "minmax"
    """How the antonym overlap loss compares a word's map with its antonym head's:
    'minmax' (CG `SentenceNetwork.loss`): Σ_cells minmax(a)·minmax(b) / cells, which a
    flat map satisfies for free (it normalises to zeros) — the way out Dependency's "small"
    head takes (docs/results.md, "The size words"); 'cosine': Σ a·b / (|a| |b|) of the maps
    as passed, which is 0 only for maps on disjoint cells, so a flat head pays for it
    (1/√cells against a one-hot map)."""
    num_actions: int = len(Action)
    """Output classes: the six gSCAN actions plus EOS, ids = `Action` values (always 7; kept in
    checkpoints)."""
    init_fan_in: str = "module"
    """The fan-in that scales the uniform initialisation of a module's attention output layer
    (`att_out_*`) and child-state layer (`state_*`): 'module', its own argument slots, as a
    Linear of that module's size is initialised (CG builds one per module); 'table', the
    widest module's slots, the initialisation of runs before 2026-12-06. The two differ only
    in a table whose modules take different numbers of arguments (the constituency and
    dependency parses, not the semantic one), and only in the initial weights: a loaded
    checkpoint's weights replace them (`INIT_SETTINGS`)."""

    def __post_init__(self) -> None:
        if self.message not in MESSAGES:
            raise ValueError(f"message must be one of {MESSAGES}, got {quoted(self.message)}")
        if self.attention_state not in ATTENTION_STATES:
            raise ValueError(f"attention_state must be one of {ATTENTION_STATES}, got {quoted(self.attention_state)}")
        if self.size_map not in SIZE_MAPS:
            raise ValueError(f"size_map must be one of {SIZE_MAPS}, got {quoted(self.size_map)}")
        if self.overlap not in OVERLAPS:
            raise ValueError(f"overlap must be one of {OVERLAPS}, got {quoted(self.overlap)}")
        if self.init_fan_in not in INIT_FAN_INS:
            raise ValueError(f"init_fan_in must be one of {INIT_FAN_INS}, got {quoted(self.init_fan_in)}")
        if self.attention_state == "add" and not self.uses_attention:
            raise ValueError("attention_state='add' needs attention maps; message='state' has none")
        check_settings(self, ("grid_size", "in_channels", "cnn_channels", "att_dim", "rnn_dim", "num_actions"),
                       ("cnn_dropout",), ("rnn_layers",))
        if self.grid_size not in SUPPORTED_GRID_SIZES:
            raise ValueError(f"grid_size {self.grid_size} is not supported "
                             f"({SUPPORTED_GRID_SIZES[0]} to {SUPPORTED_GRID_SIZES[-1]})")
        if not (isinstance(self.antonym_weight, (int, float)) and 0 <= self.antonym_weight < math.inf):
            raise ValueError(f"antonym_weight must be a finite number >= 0, got {quoted(self.antonym_weight)}")

    @property
    def feature_dim(self) -> int:
        return self.cnn_channels * len(self.cnn_kernels)

    @property
    def cells(self) -> int:
        return self.grid_size * self.grid_size

    @property
    def uses_attention(self) -> bool:
        return self.message != "state"

    @property
    def passes_state(self) -> bool:
        return self.message != "attention"

    @property
    def state_in_attention(self) -> bool:
        """A module's state changes its map (so every module's GRU matters)."""
        return self.attention_state == "add"

    @property
    def runs_every_gru(self) -> bool:
        """Every slot's GRU runs, block by block; otherwise only the root's (see `CompositionalNetwork.step`)."""
        return self.passes_state or self.state_in_attention


@dataclass(frozen=True)
class Seq2SeqConfig(SerializableConfig):
    """Hyper-parameters of the seq2seq baseline (defaults: MM `all_experiments.sh`)."""

    embedding_dim: int = 25
    """Command-token embedding width (the previous action's embedding is `hidden` wide, as MM's)."""
    hidden: int = 100
    """Encoder (per direction, summed) and decoder LSTM width."""
    dropout: float = 0.3
    """Dropout on embeddings and decoder outputs."""
    cnn_kernels: tuple[int, ...] = (1, 5, 7)
    """Kernel sizes of the shared-design visual encoder."""
    cnn_channels: int = 50
    """Channels per conv branch."""
    cnn_dropout: float = 0.1
    """Dropout on the cell features."""
    num_actions: int = len(Action)
    """Output classes: six actions + EOS (`Action` values)."""
    grid_size: int = GRID_SIZE
    """Side of the square grid the observations have (6 compositional, 12 for split I)."""

    def __post_init__(self) -> None:
        check_settings(self, ("embedding_dim", "hidden", "cnn_channels", "num_actions", "grid_size"),
                       ("dropout", "cnn_dropout"))


THINK_SCORERS = ("additive", "dot")


@dataclass(frozen=True)
class AuxLossConfig(Seq2SeqConfig):
    """The baseline's hyper-parameters plus the target-location classifier's loss weight and form."""

    target_loss_weight: float = 0.3
    """Weight of the target-location cross-entropy in the loss (a choice: MM's
    `--weight_target_loss` default)."""
    think_scorer: str = "additive"
    """How the target-location classifier scores a cell against its query: "additive"
    (MM's attention, v·tanh(q + k(cell))) or "dot" (q·k(cell)/√hidden, linear in the cell's
    features, so a cell's score is the sum of what its colour, shape and size contribute).
    The published classifier's form is not known (docs/model.md, "AuxLoss")."""

    def __post_init__(self) -> None:
        super().__post_init__()
        weight = self.target_loss_weight
        if isinstance(weight, bool) or not isinstance(weight, (int, float)) or not math.isfinite(weight) or weight < 0:
            raise ValueError(f"target_loss_weight must be a finite number >= 0, got {quoted(weight)}")
        if self.think_scorer not in THINK_SCORERS:
            raise ValueError(f"think_scorer must be one of {', '.join(THINK_SCORERS)}, got {quoted(self.think_scorer)}")


@dataclass(frozen=True)
class LCGNConfig(SerializableConfig):
    """Hyper-parameters of LCGN (defaults: HQ01/gSCAN_with_language_conditioned_embedding `model/config.py`)."""

    embedding_dim: int = 32
    """Command-token embedding width (CMD_D_EMBED)."""
    command_dim: int = 64
    """BiLSTM output width, both directions concatenated (CMD_D_ENC); even."""
    attribute_dim: int = 16
    """Width of each of the four attribute embeddings; a node's input is 4x this."""
    node_dim: int = 64
    """Width of the node features, contexts, messages and outputs (SITU_D_CTX)."""
    rounds: int = 4
    """Message-passing rounds T (MSG_ITER_NUM)."""
    cnn_kernels: tuple[int, ...] = (1, 5, 7)
    """Kernel sizes of the CNN over the grid of node outputs."""
    cnn_channels: int = 64
    """Channels per conv branch (SITU_D_CNN_OUTPUT)."""
    cnn_dropout: float = 0.1
    """Dropout on the cell features."""
    hidden: int = 64
    """Decoder LSTM width and its attentions' width (DEC_D_H)."""
    embedding_dropout: float = 0.2
    """Dropout on the command-token embeddings (1 - encInputDropout)."""
    command_dropout: float = 0.08
    """Dropout on the encoder's final state (1 - cmdDropout)."""
    read_dropout: float = 0.15
    """Dropout on the node features where a round reads them (1 - readDropout)."""
    dropout: float = 0.15
    """Dropout on the previous action's embedding (1 - decoderDropout)."""
    num_actions: int = len(Action)
    """Output classes: six actions + EOS (`Action` values)."""
    grid_size: int = GRID_SIZE
    """Side of the square grid the observations have (6 compositional, 12 for split I)."""

    def __post_init__(self) -> None:
        check_settings(self, ("embedding_dim", "command_dim", "attribute_dim", "node_dim", "cnn_channels",
                              "hidden", "num_actions", "grid_size"),
                       ("cnn_dropout", "embedding_dropout", "command_dropout", "read_dropout", "dropout"), ("rounds",))
        if self.command_dim % 2:
            raise ValueError(f"command_dim must be even (two LSTM directions), got {self.command_dim}")
