"""Config validation: unknown keys, wrong types, bad choices, --set overrides."""

import pytest

from bayesmag import ConfigError, load_config
from bayesmag._src.config import apply_overrides, config_from_dict, to_toml
import tomllib

BASE = {"data": {"source": "simulated"}}


def test_defaults_and_round_trip():
    cfg = config_from_dict(BASE)
    assert cfg.uq.n_params == 500 and cfg.split.kind == "random"
    again = config_from_dict(tomllib.loads(to_toml(cfg.to_dict())))
    assert again == cfg


@pytest.mark.parametrize("raw, match", [
    ({"data": {"source": "simulated"}, "uq": {"n_param": 5}}, r"Unknown config key 'uq.n_param'.*n_params"),
    ({"data": {"source": "simulated"}, "bogus": 1}, r"Unknown config key 'bogus'"),
    ({"data": {"source": "simulated"}, "uq": {"n_params": "many"}}, r"'uq.n_params' = 'many' has the wrong type: expected int"),
    ({"data": {"source": "simulated"}, "split": {"kind": "shuffle"}}, r"'split.kind' = 'shuffle' is not valid.*by_run"),
    ({"data": {"source": "simulated"}, "uq": {"method": "qmc"}}, r"must be one of \['psqmc', 'mc', 'analytic'\]"),
    ({"data": {}}, r"needs 'source'"),
    ({"data": {"source": "a", "path": "b"}}, r"both 'source' and 'path'"),
    ({"data": {"source": "simulated"}, "uq": {"sigma_in": [1, 2]}}, r"sigma_in"),
    ({"data": {"source": "simulated"}, "physics": {"t0": "median"}}, r"physics.t0"),
    ({"data": {"source": "simulated"}, "uq": "x"}, r"\[uq\] must be a table"),
])
def test_bad_configs_name_the_key(raw, match):
    with pytest.raises(ConfigError, match=match):
        config_from_dict(raw)


def test_set_overrides_and_data_path_replaces_source(tmp_path):
    p = tmp_path / "c.toml"
    p.write_text('[data]\nsource = "belsten2023"\n[uq]\nn_params = 500\n')
    cfg = load_config(p, ["uq.n_params=100", "data.path=rec.csv", 'split.kind="by_run"', "physics.t0=25.5"])
    assert cfg.uq.n_params == 100 and cfg.data.path == "rec.csv" and cfg.data.source is None
    assert cfg.split.kind == "by_run" and cfg.physics.t0 == 25.5
    with pytest.raises(ConfigError, match="key=value"):
        apply_overrides({}, ["nonsense"])


def test_missing_file_and_bad_toml(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(tmp_path / "none.toml")
    p = tmp_path / "bad.toml"
    p.write_text("[data\nsource=1")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(p)


def test_shipped_configs_validate():
    from pathlib import Path
    for p in sorted((Path(__file__).resolve().parents[1] / "configs").glob("*.toml")):
        load_config(p)
