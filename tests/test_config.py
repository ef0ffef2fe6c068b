"""Config validation: unknown keys, wrong types, bad choices, --set overrides."""

import pytest

from bayesmag import ConfigError, load_config
from bayesmag._src.app.config import apply_overrides, config_from_dict, to_toml
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
    ({"data": {"source": "simulated"}, "uq": {"method": "qmc"}}, r"must be one of \['auto', 'psqmc', 'mc', 'analytic'\]"),
    ({"data": {}}, r"needs 'source'"),
    ({"data": {"source": "a", "path": "b"}}, r"both 'source' and 'path'"),
    ({"data": {"source": "simulated"}, "uq": {"sigma_in": [1, 2]}}, r"sigma_in"),
    ({"data": {"source": "simulated"}, "physics": {"t0": "median"}}, r"physics.t0"),
    ({"data": {"source": "simulated"}, "physics": {"t0": 1e9}}, r"'physics.t0' = 1000000000.0 is not a reference temp"),
    ({"data": {"source": "simulated"}, "uq": "x"}, r"\[uq\] must be a table"),
    ({"data": {"source": "simulated"}, "network": {"conformal_folds": 1}}, r"'network.conformal_folds' = 1 is not valid"),
    ({"data": {"source": "simulated"}, "network": {"conformal_folds": 10}}, r"folds x fraction < 1"),
    ({"data": {"source": "simulated"}, "uq": {"transfer": "hierarchical"},
      "physics": {"extra_terms": [{"name": "run_offset", "runs": [1, 2, 3]}]}},
     r"'physics.extra_terms' holds 'run_offset'.*random effect.*uq.transfer = \"loro\""),
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
    import tomllib
    from bayesmag._src.app.fleet import load_fleet_config
    for p in sorted((Path(__file__).resolve().parents[1] / "configs").glob("*.toml")):
        if "fleet" in tomllib.loads(p.read_text()):     # a fleet config is for `bayesmag fleet` (issue 27)
            load_fleet_config(p)
        else:
            load_config(p)


def test_choice_lists_come_from_the_library():
    """config.py holds no copy of the library's choice lists: a name the library registers is valid."""
    from bayesmag._src.core import network
    from bayesmag._src.pipeline.nuts import CHAIN_METHODS
    with pytest.raises(ConfigError, match=r"'nuts.chain_method' = 'pmap'.*" + str(list(CHAIN_METHODS)).replace("[", r"\[")):
        config_from_dict({**BASE, "nuts": {"chain_method": "pmap"}})
    with pytest.raises(ConfigError, match=r"'network.activation' = 'swish' is not valid"):
        config_from_dict({**BASE, "network": {"activation": "swish"}})
    network.ACTIVATIONS["swish"] = network.ACTIVATIONS["silu"]
    try:
        assert config_from_dict({**BASE, "network": {"activation": "swish"}}).network.activation == "swish"
    finally:
        del network.ACTIVATIONS["swish"]


def test_float64_opt_out_leaves_the_callers_jax_state_alone():
    """BAYESMAG_ENABLE_X64=0: importing bayesmag keeps JAX in float32; enable_x64() scopes float64 and
    restores the caller's setting; a float64 entry point run in float32 warns."""
    import os
    import subprocess
    import sys
    code = """
import warnings, jax, numpy as np
import bayesmag as bm
assert not jax.config.jax_enable_x64 and not bm.X64_AT_IMPORT
with bm.enable_x64():
    assert bm.x64_enabled() and jax.numpy.zeros(1).dtype == np.float64
assert not jax.config.jax_enable_x64
from bayesmag._src.core.simulate import simulate_from_config
d = simulate_from_config({"n": 200, "seed": 0})
with warnings.catch_warnings(record=True) as w:
    warnings.simplefilter("always")
    bm.fit_physics(d)
assert any(issubclass(x.category, bm.Float64Warning) for x in w)
print("ok")
"""
    env = {**os.environ, "BAYESMAG_ENABLE_X64": "0", "JAX_PLATFORMS": "cpu"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and out.stdout.strip().endswith("ok"), out.stderr[-2000:]


@pytest.mark.parametrize("key, value", [("transfer_likelihood", "laplace"), ("transfer_df", 6.0),
                                        ("transfer_uninformed", "fixed"), ("transfer_check", "warn")])
def test_session_model_keys_without_the_session_model_are_refused(key, value):
    """Sixth outside pass: `uq.transfer_likelihood = "laplace"` with the default `transfer = "loro"` ran with no
    word, and config.resolved.toml kept the key as if it had been used. It is read by the hierarchical model only."""
    raw = {"name": "t", "data": {"source": "simulated"}, "uq": {key: value}}
    with pytest.raises(ConfigError, match=rf"\['uq.{key}'\] set the hierarchical session model; uq.transfer = 'loro'"):
        config_from_dict(raw)
    assert getattr(config_from_dict({**raw, "uq": {key: value, "transfer": "hierarchical"}}).uq, key) == value
