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
    ({"data": {"source": "simulated"}, "uq": "x"}, r"\[uq\] must be a table"),
    ({"data": {"source": "simulated"}, "network": {"conformal_folds": 1}}, r"'network.conformal_folds' = 1 is not valid"),
    ({"data": {"source": "simulated"}, "network": {"conformal_folds": 10}}, r"folds x fraction < 1"),
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


# Four independent vmapped triangular solves in one program, each large enough for jaxlib 0.10.2 to split its
# batch over the CPU thread pool: with two pool threads both block waiting for pieces nobody runs (hangs 4 of 4
# times on the 2-core CI machine with JAX's own thread settings).
_POOL_DEADLOCK = """
import jax, jax.numpy as jnp
import bayesmag
from jax.scipy.linalg import solve_triangular
def g(A, b):
    outs = [jax.vmap(lambda a, c: solve_triangular(a, c, lower=True))(jnp.tanh(A * (k + 1)) + 5 * jnp.eye(8), b * k)
            for k in range(4)]
    return sum(o.sum() for o in outs)
f = jax.jit(g)
A, b = jnp.tril(jnp.ones((4000, 8, 8))), jnp.ones((4000, 8, 3))
for i in range(300):
    f(A + i, b).block_until_ready()
print(bayesmag.CPU_POOL_AT_IMPORT)
"""


@pytest.mark.parametrize("setting", ["", "default"])
def test_import_keeps_batched_lapack_from_deadlocking_the_cpu_pool(setting):
    """`import bayesmag` (before JAX's CPU client exists) sizes the pool to one thread where jaxlib splits batched
    LAPACK calls over it (bayesmag/__init__.py): 300 runs of a program of four concurrent batched triangular solves
    finish (about 2 s). With BAYESMAG_CPU_THREADS=default (JAX's own pool of one thread per core) the same program
    hangs on a 2-core machine; checked only where the pool has exactly two threads and jaxlib has the split."""
    import os
    import subprocess
    import sys

    import bayesmag
    env = {**os.environ, "BAYESMAG_CPU_THREADS": setting, "JAX_PLATFORMS": "cpu"}
    env.pop("PJRT_NPROC", None)
    env.pop("NPROC", None)
    if not setting:
        out = subprocess.run([sys.executable, "-c", _POOL_DEADLOCK], env=env, capture_output=True, text=True,
                             timeout=240)
        assert out.returncode == 0, out.stderr[-2000:]
        assert out.stdout.split()[-1] == str(bayesmag._lapack_pool_deadlocks())
        return
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    if cores != 2 or not bayesmag._lapack_pool_deadlocks():
        pytest.skip("the contrast is checked on 2-core machines with a jaxlib that splits LAPACK batches")
    with pytest.raises(subprocess.TimeoutExpired):
        subprocess.run([sys.executable, "-c", _POOL_DEADLOCK], env=env, capture_output=True, text=True, timeout=20)


def test_import_after_jax_ran_warns_that_the_pool_cannot_be_sized():
    """JAX computed before `import bayesmag`: its pool is fixed, so bayesmag cannot size it and says so (naming
    the fix), where the installed jaxlib has the hang; nothing is said with PJRT_NPROC set."""
    import os
    import subprocess
    import sys

    import bayesmag
    code = """
import warnings, jax.numpy as jnp
jnp.ones(2).sum().block_until_ready()
with warnings.catch_warnings(record=True) as w:
    warnings.simplefilter("always")
    import bayesmag
print(bayesmag.CPU_POOL_AT_IMPORT, any("PJRT_NPROC=1" in str(x.message) for x in w))
"""
    for nproc, want in (("", str(bayesmag._lapack_pool_deadlocks())), ("2", "False")):
        env = {**os.environ, "JAX_PLATFORMS": "cpu", "BAYESMAG_CPU_THREADS": "", "PJRT_NPROC": nproc}
        env.pop("NPROC", None)
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
        assert out.returncode == 0, out.stderr[-2000:]
        assert out.stdout.split() == ["False", want], (nproc, out.stdout)


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
