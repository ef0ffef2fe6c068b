"""A time column in ms or us (as many loggers stamp): declared with ``[data] time_unit`` / ``--time-unit`` and
converted to seconds at load; an undeclared one is named (an outside smoke pass found it accepted silently by
``run`` and ``discover``: discover then reported correlation times of 1.3e4 s)."""

from __future__ import annotations

import numpy as np
import pytest

import bayesmag
from bayesmag._src.app.config import ConfigError, config_from_dict
from bayesmag._src.core.data import CalibrationData, DataError, load_csv, time_step_warning
from bayesmag._src.core.frames import load_table


@pytest.fixture(scope="module")
def data():
    return bayesmag.simulate.simulate(400, design="campaign", seed=3, noise_sd=0.05)


@pytest.mark.parametrize("unit, factor", [("s", 1.0), ("ms", 1e3), ("us", 1e6), ("min", 1 / 60), ("h", 1 / 3600)])
@pytest.mark.parametrize("fmt", ["csv", "parquet"])
def test_declared_time_unit_is_converted_to_seconds(data, tmp_path, unit, factor, fmt):
    df = bayesmag.to_frame(data).assign(time=data.time * factor)
    path = tmp_path / f"r.{fmt}"
    if fmt == "csv":
        df.to_csv(path, index=False, float_format="%.17g")
    else:
        pytest.importorskip("pyarrow")
        df.to_parquet(path, index=False)
    got = load_table(path, time_unit=unit)
    np.testing.assert_allclose(got.time, data.time, rtol=1e-12, atol=1e-9)
    assert (time_step_warning(got) is None) and (time_step_warning(load_table(path)) is None) == (unit in ("s", "min"))


def test_an_undeclared_millisecond_column_is_named(data):
    """The warning fires for ms and us stamps read as seconds (4 Hz: 250 / 2.5e5 "s" apart), not for seconds, and
    not for rows without times."""
    ms = CalibrationData(data.b_meas, data.temperature, data.b_ref, data.time * 1e3, data.run)
    assert "time_unit" in time_step_warning(ms) and "250 s" in time_step_warning(ms)
    assert time_step_warning(data) is None
    assert time_step_warning(CalibrationData(data.b_meas, data.temperature, data.b_ref)) is None


def test_time_unit_is_checked_at_the_boundary(tmp_path, data):
    with pytest.raises(ConfigError, match="data.time_unit"):
        config_from_dict({"data": {"source": "simulated", "time_unit": "sec"}})
    assert config_from_dict({"data": {"source": "simulated", "time_unit": "ms"}}).data.time_unit == "ms"
    bayesmag.to_frame(data).to_csv(tmp_path / "r.csv", index=False)
    with pytest.raises(DataError, match="time_unit is 'sec'.*'ms'"):
        load_csv(tmp_path / "r.csv", time_unit="sec")


def test_apply_time_unit_reads_a_logger_in_ms_as_training_in_s(data, tmp_path, capsys):
    """``apply --time-unit ms`` on a recording stamped in ms: no time-step warning, the rate flags those of seconds."""
    from bayesmag._src.app.cli import main
    cal = bayesmag.Calibrator({"uq": {"n_params": 20, "n_qmc": 32}}).fit(data).save(tmp_path / "cal")
    df = bayesmag.to_frame(data)
    df.to_csv(tmp_path / "s.csv", index=False, float_format="%.17g")
    df.assign(time=data.time * 1e3).to_csv(tmp_path / "ms.csv", index=False, float_format="%.17g")
    assert main(["apply", "--model", str(cal), "--data", str(tmp_path / "s.csv"), "--out", str(tmp_path / "a.csv"),
                 "--no-progress"]) == 0
    assert main(["apply", "--model", str(cal), "--data", str(tmp_path / "ms.csv"), "--out", str(tmp_path / "b.csv"),
                 "--no-progress"]) == 0
    assert "time step" in capsys.readouterr().err               # undeclared ms: the step differs from training's
    assert main(["apply", "--model", str(cal), "--data", str(tmp_path / "ms.csv"), "--out", str(tmp_path / "c.csv"),
                 "--no-progress", "--time-unit", "ms"]) == 0
    assert "time step" not in capsys.readouterr().err
    import pandas as pd
    a, c = pd.read_csv(tmp_path / "a.csv", comment="#"), pd.read_csv(tmp_path / "c.csv", comment="#")
    np.testing.assert_array_equal(a["in_domain_reason"], c["in_domain_reason"])
    np.testing.assert_allclose(a["x_calibrated"], c["x_calibrated"], rtol=1e-12)


def test_run_names_an_undeclared_ms_column_and_reads_a_declared_one(data, tmp_path):
    import json

    from bayesmag._src.app.cli import main
    bayesmag.to_frame(data).assign(time=data.time * 1e3).to_csv(tmp_path / "ms.csv", index=False, float_format="%.17g")
    base = ["run", "quickstart", "--no-progress", "--set", f'data.path="{tmp_path / "ms.csv"}"', "--set",
            "network.enabled=false", "--set", "output.figures=false", "--set", 'split.kind="by_run"']
    assert main(base + ["--out", str(tmp_path / "a")]) == 0
    said = json.loads((tmp_path / "a" / "metrics.json").read_text())["warnings"]
    assert any("median time step" in w and "time_unit" in w for w in said)
    assert main(base + ["--set", 'data.time_unit="ms"', "--out", str(tmp_path / "b")]) == 0
    said = json.loads((tmp_path / "b" / "metrics.json").read_text())["warnings"]
    assert not any("median time step" in w for w in said)
