"""TrainConfig: YAML + --set overrides, unknown keys rejected with the key named."""
from pathlib import Path

import pytest
import yaml

from gscan_ros.training.config import ConfigError, TrainConfig


def test_yaml_and_overrides(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("batch_size: 50\nmodel:\n  rnn_dim: 40\n")
    cfg = TrainConfig.load(path, ["lr=0.01", "model.message=attention+state", "parser=dependency"])
    assert cfg.batch_size == 50 and cfg.lr == 0.01 and cfg.parser == "dependency"
    mc = cfg.model_config()
    assert mc.rnn_dim == 40 and mc.message == "attention+state" and mc.passes_state


@pytest.mark.parametrize("overrides, message", [
    (["batch_sise=3"], "batch_sise"),
    (["model.rnn_dimm=3"], "rnn_dimm"),
    (["batching=random"], "batching"),
    (["model.message=telepathy"], "message"),
    (["batch_size"], "key=value"),
    (["batch_size=abc"], "batch_size"),
    (["batch_size=2.5"], "batch_size"),
    (["seed=-1"], "seed must be in"),
    (["seed=4294967296"], "seed must be in"),
    (["seed=4294967000", "screen_seeds=2"], "seed must be in"),  # the second candidate is past numpy's range
])
def test_bad_settings_are_named(overrides, message):
    with pytest.raises(ConfigError, match=message):
        TrainConfig.load(None, overrides)


CONFIGS = sorted((Path(__file__).resolve().parents[1] / "configs").glob("*.yaml"))


@pytest.mark.parametrize("path", CONFIGS, ids=[p.name for p in CONFIGS])
def test_shipped_configs_load_every_setting_they_name(path):
    raw = yaml.safe_load(path.read_text())
    cfg = TrainConfig.load(path, [])
    assert {k: v for k, v in cfg.to_dict().items() if k in raw and k != "model"} == {
        k: v for k, v in raw.items() if k != "model"}
    model = cfg.model_config().to_dict()
    assert {k: model[k] for k in raw.get("model") or {}} == (raw.get("model") or {})
    assert TrainConfig.from_dict(cfg.to_dict()) == cfg


def test_length_config_widens_the_cnn_as_the_original():
    cfg = TrainConfig.load(Path(__file__).resolve().parents[1] / "configs" / "length.yaml", [])
    assert cfg.model_config().cnn_kernels == (1, 5, 13)


def test_default_config_is_the_shipped_models():
    """configs/default.yaml trains the shipped model: the config its run recorded, threads aside."""
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    recorded = yaml.safe_load((repo / "results/recipe/fast_minmax_s0/config.yaml").read_text())
    default = TrainConfig.load(repo / "configs/default.yaml", []).to_dict()
    assert {k: v for k, v in default.items() if k in recorded and k != "threads"} == {
        k: v for k, v in recorded.items() if k in default and k != "threads"}


def test_a_state_message_needs_a_module_per_word():
    with pytest.raises(ConfigError, match=r"big\|small under lexicon wordnet\) would be one word; set lexicon: none"):
        TrainConfig.load(None, ["model.message=state"])
    assert TrainConfig.load(None, ["model.message=state", "lexicon=none"]).model_config().message == "state"


@pytest.mark.parametrize("kind", ["compositional", "seq2seq", "lcgn", "auxloss"])
def test_num_actions_is_the_action_set(kind):
    """An output per Action id: another count would fail in the loss or at decoding."""
    with pytest.raises(ConfigError, match=r"num_actions must be 7 \(the actions and <eos>\), got 5"):
        TrainConfig.load(None, [f"model_kind={kind}", "model.num_actions=5", "lexicon=none"])
