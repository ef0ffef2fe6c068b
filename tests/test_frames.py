"""pandas at the edges: DataFrame <-> CalibrationData, predictions as DataFrames, the sklearn-style Calibrator."""

import importlib.util

import numpy as np
import pandas as pd
import pytest

import bayesmag
from bayesmag import CalibrationData, DataError, PhysicsModel, fit_physics, inputs_from_data
from bayesmag._src.core.frames import from_frame, prediction_frame, read_parquet, to_frame
from helpers import affine_data


@pytest.fixture(scope="module")
def data():
    d, _ = affine_data(500, seed=2, noise=0.05)
    return CalibrationData(d.b_meas, d.temperature, d.b_ref, d.time, np.repeat([1, 2], 250))


def test_frame_round_trip_is_exact(data):
    df = to_frame(data)
    assert list(df.columns) == list(bayesmag._src.core.data.CANONICAL_COLUMNS)
    back = from_frame(df)
    for k in ("b_meas", "temperature", "b_ref", "time", "run"):
        np.testing.assert_array_equal(getattr(back, k), getattr(data, k))


def test_column_mapping_and_units(data):
    df = pd.DataFrame({"t_s": data.time, "Bx [nT]": data.b_meas[:, 0] * 1e3, "By [nT]": data.b_meas[:, 1] * 1e3,
                       "Bz [nT]": data.b_meas[:, 2] * 1e3, "T [K]": data.temperature + 273.15})
    d = from_frame(df, columns={"time": "t_s", "bx_meas": "Bx [nT]", "by_meas": "By [nT]", "bz_meas": "Bz [nT]",
                                "temperature": "T [K]"}, field_unit="nT", temperature_unit="K")
    np.testing.assert_allclose(d.b_meas, data.b_meas, rtol=1e-12)
    np.testing.assert_allclose(d.temperature, data.temperature, atol=1e-9)
    assert d.b_ref is None and (d.run == 0).all()


@pytest.mark.parametrize("drop, match", [(["by_meas"], "no column 'by_meas'"),
                                         (["bz_ref"], r"some reference columns but not \['bz_ref'\]")])
def test_bad_frames_name_the_column(data, drop, match):
    with pytest.raises(DataError, match=match):
        from_frame(to_frame(data).drop(columns=drop))


def test_bad_unit_names_the_valid_set(data):
    with pytest.raises(DataError, match=r"field_unit is 'T'; it must be one of \['uT', 'nT'"):
        from_frame(to_frame(data), field_unit="T")


def test_prediction_frame_columns_and_index():
    pred = {"calibrated": np.arange(6.0).reshape(2, 3), "lower": np.zeros((2, 3)), "valid": np.array([True, False])}
    df = prediction_frame(pred, index=pd.Index([10, 11], name="row"))
    assert list(df.columns) == ["x_calibrated", "x_lower", "y_calibrated", "y_lower", "z_calibrated", "z_lower",
                                "valid"]
    assert df.index.tolist() == [10, 11] and df.loc[11, "z_calibrated"] == 5.0


def test_physics_fit_predict_accepts_frames_and_data(data):
    fit = fit_physics(data, PhysicsModel.paper(t0=20.0))
    want = fit.predict(inputs_from_data(data))
    np.testing.assert_array_equal(fit.predict(data), want)
    df = to_frame(data).set_index(pd.RangeIndex(100, 600))
    out = fit.predict(df)
    assert isinstance(out, pd.DataFrame) and out.index[0] == 100
    np.testing.assert_array_equal(out[["x_calibrated", "y_calibrated", "z_calibrated"]].to_numpy(), want)


def test_calibrator_fit_predict_matches_the_physics_fit(data, tmp_path):
    df = to_frame(data)
    cal = bayesmag.Calibrator(out=tmp_path).fit(df)
    ref = fit_physics(data, PhysicsModel.paper(t0=float(np.mean(data.temperature))))
    np.testing.assert_allclose(cal.physics_fit_.theta, ref.theta, rtol=1e-7, atol=1e-9)   # CSV keeps 10 digits
    field = df.drop(columns=["bx_ref", "by_ref", "bz_ref"]).iloc[::5]
    out = cal.predict(field)
    assert isinstance(out, pd.DataFrame) and (out.index == field.index).all()
    np.testing.assert_allclose(out["y_calibrated"].to_numpy(), ref.predict(data)[::5, 1], rtol=1e-8)
    # Calibration.predict: a DataFrame gives a DataFrame, CalibrationData still gives the dict
    as_df = cal.calibration_.predict(field)
    as_dict = cal.calibration_.predict(from_frame(field))
    np.testing.assert_array_equal(as_df["x_upper"].to_numpy(), as_dict["upper"][:, 0])
    assert as_df["in_domain"].dtype == bool and isinstance(as_dict, dict)
    assert (tmp_path / "run" / "calibration.json").exists()
    # the command line: another layout, field in nT, semicolons would be data.py's business; commas here
    f = field.rename(columns={"bx_meas": "Bx", "by_meas": "By", "bz_meas": "Bz", "temperature": "T"})
    f[["Bx", "By", "Bz"]] *= 1e3
    f.to_csv(tmp_path / "nt.csv", index=False)
    from bayesmag._src.app.cli import main
    assert main(["apply", "--model", str(tmp_path / "run"), "--data", str(tmp_path / "nt.csv"), "--out",
                 str(tmp_path / "o.csv"), "--columns", "bx_meas=Bx,by_meas=By,bz_meas=Bz,temperature=T",
                 "--field-unit", "nT", "--no-progress"]) == 0
    got = pd.read_csv(tmp_path / "o.csv")
    np.testing.assert_allclose(got["z_calibrated"].to_numpy(), as_dict["calibrated"][:, 2], rtol=1e-7)


def test_calibrator_needs_a_reference_and_a_fit(data):
    with pytest.raises(DataError, match="reference"):
        bayesmag.Calibrator().fit(CalibrationData(data.b_meas, data.temperature, None))
    with pytest.raises(RuntimeError, match="not fitted"):
        bayesmag.Calibrator().predict(data)


def test_parquet_reads_or_says_what_is_missing(data, tmp_path):
    p = tmp_path / "d.parquet"
    if importlib.util.find_spec("pyarrow") is None:
        p.write_bytes(b"PAR1")
        with pytest.raises(DataError, match="needs pyarrow"):
            read_parquet(p)
    else:
        to_frame(data).to_parquet(p)
        np.testing.assert_array_equal(read_parquet(p).b_ref, data.b_ref)
