"""TrainConfig: YAML + --set overrides, unknown keys rejected with the key named."""
import pytest

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
])
def test_bad_settings_are_named(overrides, message):
    with pytest.raises(ConfigError, match=message):
        TrainConfig.load(None, overrides)
