"""Field-calibration configs and inputs, from an outside smoke pass (fifth): keys a field job does not read, a
discovery on a field config, a kelvin reference temperature, a CSV without a header and the missing-column hints.
Each case was silent or misleading before (the test fails on the code before its fix)."""

from __future__ import annotations

import numpy as np
import pytest

import bayesmag
from bayesmag._src.app.cli import main
from bayesmag._src.app.config import ConfigError, config_from_dict
from bayesmag._src.core.data import DataError, load_csv


@pytest.mark.parametrize("section, key, value, instead", [
    ("physics", "temperature_terms", False, "measurement.temperature_terms instead of physics.temperature_terms"),
    ("physics", "covariance", "ar1", "measurement.covariance instead of physics.covariance"),
    ("physics", "extra_terms", ["cubic_nonlinearity"], None),
    ("uq", "reference_sd", 0.01, "measurement.reference_sd instead of uq.reference_sd"),
    ("uq", "method", "psqmc", None),
    ("network", "enabled", True, None),
])
def test_a_field_job_refuses_the_vector_keys_it_does_not_read(section, key, value, instead):
    """`physics.temperature_terms = false` still fitted thermal terms; `uq.reference_sd` left the scalar fit
    unweighted (the key read is `measurement.reference_sd`); `network.enabled` trained nothing: all with exit 0."""
    with pytest.raises(ConfigError) as e:
        config_from_dict({"data": {"source": "field_simulated"}, section: {key: value}})
    msg = str(e.value)
    assert f"'{section}.{key}'" in msg and "field calibration" in msg
    assert instead is None or instead in msg
    for packaged in ("field_simulated", "scalar_belsten"):                 # the packaged field configs still load
        bayesmag.load_config(packaged)
    config_from_dict({"data": {"source": "field_simulated"}, "physics": {"t0": 20.0}, "uq": {"level": 0.9}})


@pytest.mark.parametrize("name", ["scalar_belsten", "field_simulated"])
def test_discover_refuses_a_field_config(name, tmp_path, capsys):
    """`discover scalar_belsten` ran a vector discovery on the reference the config withholds (exit 0)."""
    from bayesmag._src.app.discover_cli import main as discover_main
    assert discover_main([name, "--out", str(tmp_path / "d"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "vector reference" in err and "field calibration" in err and "\n" not in err.strip()
    assert not (tmp_path / "d").exists()


@pytest.mark.parametrize("kind", ["vector", "field"])
@pytest.mark.extended
def test_a_kelvin_reference_temperature_is_refused(kind, tmp_path, capsys):
    """`physics.t0 = 298.15` beside kelvin data (converted to C) gave a certificate at "T0 = 298.1 C" with parameters
    extrapolated 270 C and correlation notes blaming the motion; now refused naming the key, the gap and kelvin."""
    if kind == "vector":
        d = bayesmag.simulate.simulate(900, design="campaign", seed=1, noise_sd=0.05)
        frame = bayesmag.to_frame(d)
        extra = '[uq]\nmethod = "analytic"\n'
    else:
        from bayesmag.simulate import simulate_field
        c = simulate_field("two_temperature", n=900, sensor_seed=7, seed=1)
        frame = bayesmag.to_frame(c.data).drop(columns=["bx_ref", "by_ref", "bz_ref"])
        extra = '[measurement]\nkind = "constant"\nfield = 50.0\n'
    frame["temperature"] += 273.15
    frame.to_csv(tmp_path / "k.csv", index=False)
    (tmp_path / "k.toml").write_text(f'name = "k"\n[data]\npath = "k.csv"\ntemperature_unit = "K"\n[physics]\n'
                                     f't0 = 298.15\n{extra}[output]\nfigures = false\n')
    assert main(["run", str(tmp_path / "k.toml"), "--out", str(tmp_path / "out"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "'physics.t0' = 298.15 C lies" in err and "kelvin" in err
    assert not (tmp_path / "out").exists()
    (tmp_path / "k.toml").write_text((tmp_path / "k.toml").read_text().replace("298.15", "25.0"))
    assert main(["run", str(tmp_path / "k.toml"), "--out", str(tmp_path / "out"), "--no-progress"]) == 0


def test_a_reference_temperature_near_the_data_is_accepted():
    from bayesmag._src.core.physics import check_t0, resolve_t0
    assert resolve_t0(0.0, [20.0, 30.0]) == 0.0                       # 20 C below: a choice, not a slip
    check_t0(-100.0, [20.0, 30.0])                                    # 120 C: still accepted (threshold 150 C)
    with pytest.raises(DataError, match="t0 = 200.0 C lies 170 C"):
        check_t0(200.0, [20.0, 30.0])


def test_a_csv_without_a_header_is_named_as_such(tmp_path):
    """Belsten's own full_data.csv (no header) gave "no column 'bx_meas'. Columns found: ['1598356349', ...]"."""
    d = bayesmag.simulate.simulate(50, design="campaign", seed=1, noise_sd=0.05)
    bayesmag.to_frame(d).to_csv(tmp_path / "h.csv", index=False, header=False)
    with pytest.raises(DataError, match=r"has no header row: its first line holds numbers"):
        load_csv(tmp_path / "h.csv")


def test_missing_column_hints_name_the_callers_option_and_a_missing_temperature(tmp_path, capsys):
    """`apply` on a renamed file said "or a [data.columns] mapping" (apply's option is --columns); a missing
    temperature column gave no hint for a sensor without one."""
    d = bayesmag.simulate.simulate(300, design="campaign", seed=1, noise_sd=0.05)
    f = bayesmag.to_frame(d)
    f.rename(columns={"temperature": "temp"}).to_csv(tmp_path / "r.csv", index=False)
    with pytest.raises(DataError) as e:
        load_csv(tmp_path / "r.csv")
    assert "[data.columns]" in str(e.value) and "constant value" in str(e.value)
    bayesmag.Calibrator(config={"uq": {"method": "analytic"}}).fit(d).save(tmp_path / "cal")
    assert main(["apply", "--model", str(tmp_path / "cal"), "--data", str(tmp_path / "r.csv"), "--out",
                 str(tmp_path / "o.csv"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "--columns" in err and "[data.columns]" not in err
    np.testing.assert_equal((tmp_path / "o.csv").exists(), False)
