"""Install anywhere: packaged configs, --version, the wheel's contents; the compilation cache."""

import os
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

import bayesmag
from bayesmag._src.core import cache
from bayesmag._src.app.cli import _resolve_config, main, packaged_configs_dir

ROOT = Path(__file__).resolve().parents[1]


def test_version_matches_pyproject(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    version = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    assert capsys.readouterr().out.strip() == f"bayesmag {version}" == f"bayesmag {bayesmag.__version__}"


def test_packaged_config_by_name_from_another_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for name in ("quickstart", "quickstart.toml", "configs/paper_hybrid.toml"):
        p = _resolve_config(name)
        assert p.exists(), name
        assert p.read_text() == (ROOT / "configs" / Path(name).name.removesuffix(".toml")).with_suffix(".toml").read_text()
    assert sorted(x.name for x in packaged_configs_dir().glob("*.toml")) == sorted(
        x.name for x in (ROOT / "configs").glob("*.toml"))
    with pytest.raises(bayesmag.ConfigError, match="not a packaged config; those are: .*quickstart"):
        _resolve_config("no_such_config")


def _check_tree(names: set[str]) -> None:
    for cfg in (ROOT / "configs").glob("*.toml"):
        assert f"bayesmag/configs/{cfg.name}" in names, cfg.name
    for mod in (ROOT / "bayesmag").rglob("*.py"):
        assert mod.relative_to(ROOT).as_posix() in names, mod


def test_build_ships_every_config_and_module(tmp_path):
    """setuptools' build_py (what a wheel copies) puts configs/*.toml into bayesmag/configs/."""
    r = subprocess.run([sys.executable, "-c", "from setuptools import setup; setup()", "-q", "build_py",
                        "--build-lib", str(tmp_path)], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    _check_tree({p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*") if p.is_file()})


@pytest.mark.slow
def test_wheel_ships_every_config_and_module(tmp_path):
    """A real non-editable wheel build (isolated: needs the package index for setuptools and wheel)."""
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp_path), str(ROOT)],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    (whl,) = tmp_path.glob("bayesmag-*.whl")
    names = set(zipfile.ZipFile(whl).namelist())
    _check_tree(names)
    assert any(n.endswith("entry_points.txt") for n in names)


# --------------------------------------------------------------------------- compilation cache


@pytest.mark.parametrize("value, expected", [
    ("0", None), ("off", None), ("false", None), ("", None), ("1", "default"), ("/x/y", "/x/y")])
def test_cache_dir_from_env(value, expected):
    got = cache.cache_dir_from_env({cache.ENV_VAR: value})
    want = cache.default_cache_dir() if expected == "default" else (None if expected is None else Path(expected))
    assert got == want


def test_default_cache_dir_follows_xdg(monkeypatch, tmp_path):
    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert cache.default_cache_dir() == tmp_path / "bayesmag" / "jax"


_SNIPPET = """
import time, jax, jax.numpy as jnp, bayesmag
assert jax.config.values["jax_compilation_cache_dir"] is None     # configured on first use, not at import
bayesmag.fit_physics                                               # first use of the API
f = jax.jit(lambda x: jnp.sin(x) @ jnp.cos(x).T + jnp.linalg.inv(x @ x.T + 3 * jnp.eye(x.shape[0])))
print(jax.config.values["jax_compilation_cache_dir"])
f(jnp.ones((7, 7))).block_until_ready()
"""


def _run(env_value, tmp_path):
    env = {**os.environ, cache.ENV_VAR: env_value, "JAX_PLATFORMS": "cpu", "PYTHONPATH": str(ROOT)}
    if env_value is None:
        env.pop(cache.ENV_VAR)
    r = subprocess.run([sys.executable, "-c", _SNIPPET], env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    return r.stdout.strip()


def test_compile_cache_off_by_default_and_the_env_switches_it_on(tmp_path):
    assert _run(None, tmp_path) == "None"                         # the library leaves JAX's setting alone
    d = tmp_path / "jaxcache"
    assert _run(str(d), tmp_path) == str(d)
    entries = {p.name for p in d.rglob("*") if p.is_file()}
    assert entries, "a compiled function should have been written to the cache"
    assert _run(str(d), tmp_path) == str(d)                       # second process: reads, adds nothing new
    assert {p.name for p in d.rglob("*") if p.is_file()} == entries
    off = tmp_path / "off"
    assert _run("0", tmp_path) == "None"
    assert not off.exists()


def test_config_switch_turns_the_cache_off(monkeypatch):
    import jax
    before = (jax.config.values["jax_compilation_cache_dir"], jax.config.values["jax_enable_compilation_cache"])
    monkeypatch.delenv(cache.ENV_VAR, raising=False)
    try:
        assert cache.configure_compile_cache(False) is None
        assert jax.config.values["jax_compilation_cache_dir"] is None
        assert bayesmag.load_config(ROOT / "configs/quickstart.toml").output.compile_cache == "auto"
        with pytest.raises(bayesmag.ConfigError, match="'output.compile_cache' = 'yes' must be true, false or"):
            bayesmag.load_config(ROOT / "configs/quickstart.toml", ["output.compile_cache='yes'"])
        cfg = bayesmag.load_config(ROOT / "configs/quickstart.toml", ["output.compile_cache=true"])
        assert cfg.output.compile_cache is True
    finally:
        jax.config.update("jax_compilation_cache_dir", before[0])
        jax.config.update("jax_enable_compilation_cache", before[1])


def test_job_with_the_cache_switched_off_runs_without_it_and_restores_it(tmp_path, monkeypatch):
    """[output] compile_cache = false from Python: off during the job, the caller's setting back after."""
    import jax

    from bayesmag._src.pipeline import stages
    cache.ensure_compile_cache()                    # as the first use of bayesmag does
    seen = []
    real = stages.run_physics_stage

    def spy(*args, **kwargs):
        seen.append((jax.config.values["jax_enable_compilation_cache"], jax.config.values["jax_compilation_cache_dir"]))
        return real(*args, **kwargs)

    monkeypatch.setattr(stages, "run_physics_stage", spy)
    before = (jax.config.values["jax_enable_compilation_cache"], jax.config.values["jax_compilation_cache_dir"])
    overrides = ["output.compile_cache=false", "output.figures=false", "output.progress=false", "network.enabled=false",
                 "data.simulate.n=400", "uq.n_params=20", "uq.n_qmc=32"]
    bayesmag.run_job(bayesmag.load_config(ROOT / "configs/quickstart.toml", overrides), tmp_path / "off")
    assert seen == [(False, None)]
    assert (jax.config.values["jax_enable_compilation_cache"], jax.config.values["jax_compilation_cache_dir"]) == before
    bayesmag.run_job(bayesmag.load_config(ROOT / "configs/quickstart.toml", overrides[1:]), tmp_path / "on")
    assert seen[1] == before                                        # the default ("auto"): the caller's setting
    assert (jax.config.values["jax_enable_compilation_cache"], jax.config.values["jax_compilation_cache_dir"]) == before


def test_import_is_lazy_and_every_public_name_resolves():
    code = ("import sys, bayesmag, bayesmag._src.app.cli; heavy = [m for m in ('numpyro', 'arviz', 'bayesmag._src.pipeline.discover',"
            " 'bayesmag._src.pipeline.nuts', 'optax') if m in sys.modules]; print(heavy);"
            " assert all(hasattr(bayesmag, n) for n in bayesmag.__all__); print(len(bayesmag.EXTRA_TERMS) > 0)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                       env={**os.environ, "PYTHONPATH": str(ROOT), "JAX_PLATFORMS": "cpu"})
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.split() == ["[]", "True"]


@pytest.mark.parametrize("argv0,preset,expected", [
    ("bayesmag", None, "1"),             # the console script: one BLAS thread (small matrices only)
    ("bayesmag", "4", "4"),              # the user's own setting is never overridden
    ("notebook.py", None, "unset"),      # a library import leaves the process alone
])
def test_command_sets_one_blas_thread_only_for_itself(argv0, preset, expected):
    code = ("import sys; sys.argv[0] = %r; import bayesmag, os, numpy; "
            "print(os.environ.get('OPENBLAS_NUM_THREADS', 'unset'))" % argv0)
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    if preset is not None:
        env["OPENBLAS_NUM_THREADS"] = preset
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == expected


@pytest.mark.parametrize("held, acts", [(40_000, True), (30_000, False), (100, False)])
def test_compiled_programs_released_near_the_mapping_limit(monkeypatch, held, acts):
    """Past half of vm.max_map_count the compiled programs are dropped (the CI SIGSEGV's cause), not before."""
    from bayesmag._src.core import cache
    calls = []
    monkeypatch.setattr(cache, "_map_counts", lambda: (held, 65530))
    monkeypatch.setattr("jax.clear_caches", lambda: calls.append(1))
    assert cache.release_compiled_if_crowded() is acts
    assert len(calls) == int(acts)


def test_mapping_counts_read_on_linux():
    from bayesmag._src.core import cache
    counts = cache._map_counts()
    if not sys.platform.startswith("linux"):
        assert counts is None
        return
    held, limit = counts
    assert 0 < held < limit


@pytest.mark.parametrize("env_value, on", [(None, True), ("0", False)])
def test_command_line_switches_the_cache_on_unless_told_not_to(tmp_path, env_value, on):
    """The command line caches compiled programs by default (second runs start faster); =0 keeps it off."""
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": str(ROOT), "XDG_CACHE_HOME": str(tmp_path)}
    env.pop(cache.ENV_VAR, None)
    if env_value is not None:
        env[cache.ENV_VAR] = env_value
    r = subprocess.run([sys.executable, "-m", "bayesmag", "config", "list"], env=env, capture_output=True,
                       text=True, timeout=120, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    assert (tmp_path / "bayesmag" / "jax").is_dir() is on
