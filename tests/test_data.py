"""Data layer: loaders, validation messages, splits."""

import numpy as np
import pytest

from bayesmag import CalibrationData, DataError, load_csv, make_split, validate, write_csv


def _synthetic(n=50, seed=0):
    r = np.random.default_rng(seed)
    b = r.uniform(-50, 50, (n, 3))
    t = np.linspace(10, 40, n)
    return CalibrationData(b, t, b * 1.1 + 0.3, time=np.arange(n) * 0.25, run=np.repeat([1, 2], n // 2))


def test_calibration_data_is_immutable():
    d = _synthetic()
    with pytest.raises(ValueError):
        d.b_meas[0, 0] = 1.0
    with pytest.raises(Exception):
        d.n_rows = 3


def test_csv_round_trip(tmp_path):
    d = _synthetic()
    write_csv(d, tmp_path / "a.csv")
    e = load_csv(tmp_path / "a.csv")
    np.testing.assert_allclose(e.b_meas, d.b_meas, rtol=1e-9)
    np.testing.assert_allclose(e.b_ref, d.b_ref, rtol=1e-9)
    np.testing.assert_array_equal(e.run, d.run)


def test_column_mapping_and_kelvin(tmp_path):
    p = tmp_path / "other.csv"
    p.write_text("t,Bx,By,Bz,TempK,Rx,Ry,Rz\n" + "\n".join(
        f"{i},{i},{2*i},{3*i},{293.15 + i},{i},{i},{i}" for i in range(12)))
    cols = dict(time="t", bx_meas="Bx", by_meas="By", bz_meas="Bz", temperature="TempK", bx_ref="Rx", by_ref="Ry",
                bz_ref="Rz")
    d = load_csv(p, columns=cols, temperature_unit="K")
    np.testing.assert_allclose(d.temperature, 20.0 + np.arange(12))
    assert (d.run == 0).all()


def test_missing_column_is_named(tmp_path):
    p = tmp_path / "bad.csv"
    p.write_text("time,bx_meas,by_meas,temperature,bx_ref,by_ref,bz_ref\n0,1,2,20,1,2,3\n")
    with pytest.raises(DataError, match="no column 'bz_meas'"):
        load_csv(p)


def test_non_numeric_cell_names_row_and_column(tmp_path):
    p = tmp_path / "bad.csv"
    p.write_text("time,bx_meas,by_meas,bz_meas,temperature,bx_ref,by_ref,bz_ref\n0,1,2,3,20,1,2,3\n1,1,abc,3,20,1,2,3\n")
    with pytest.raises(DataError, match=r"row 2, column 'by_meas' holds 'abc'"):
        load_csv(p)


@pytest.mark.parametrize("value", [np.nan, np.inf])
def test_nonfinite_values_named(value):
    d = _synthetic()
    b = d.b_meas.copy()
    b[7, 1] = value
    with pytest.raises(DataError, match=r"Column 'by_meas'.*row\(s\) 8"):
        validate(CalibrationData(b, d.temperature, d.b_ref, d.time, d.run))


def test_too_few_rows():
    d = _synthetic(n=6)
    with pytest.raises(DataError, match="6 rows but the physics model has 8 parameters"):
        validate(d, n_params=8)


def test_kelvin_detected():
    d = _synthetic()
    with pytest.raises(DataError, match="looks like kelvin"):
        validate(CalibrationData(d.b_meas, d.temperature + 273.15, d.b_ref, d.time, d.run))


def test_constant_temperature_offers_fix():
    d = _synthetic()
    e = CalibrationData(d.b_meas, np.full(d.n, 21.0), d.b_ref, d.time, d.run)
    with pytest.raises(DataError, match="temperature_terms = false"):
        validate(e)
    validate(e, need_temperature_variation=False)


def test_duplicate_timestamps_named():
    d = _synthetic()
    t = d.time.copy()
    t[5] = t[4]
    with pytest.raises(DataError, match=r"duplicated timestamps within run 1 at data row\(s\) 6"):
        validate(CalibrationData(d.b_meas, d.temperature, d.b_ref, t, d.run))


def test_random_split_is_seeded_and_disjoint():
    d = _synthetic(200)
    a = make_split(d, kind="random", test_fraction=0.1, seed=3)
    b = make_split(d, kind="random", test_fraction=0.1, seed=3)
    c = make_split(d, kind="random", test_fraction=0.1, seed=4)
    np.testing.assert_array_equal(a.test, b.test)
    assert not np.array_equal(a.test, c.test)
    assert a.test.size == 20 and np.intersect1d(a.train, a.test).size == 0
    assert np.union1d(a.train, a.test).size == 200


def test_by_run_and_time_blocks():
    d = _synthetic(200)
    s = make_split(d, kind="by_run", test_runs=[2])
    assert set(d.run[s.test]) == {2} and set(d.run[s.train]) == {1}
    tb = make_split(d, kind="time_blocks", test_fraction=0.2, seed=0)
    for r in (1, 2):
        rows = tb.test[d.run[tb.test] == r]
        assert rows.size == 20 and np.all(np.diff(rows) == 1)   # one contiguous block per run
    with pytest.raises(ValueError, match="must be one of"):
        make_split(d, kind="bogus")
    one = CalibrationData(d.b_meas, d.temperature, d.b_ref, d.time, np.zeros(d.n))
    with pytest.raises(ValueError, match="needs at least two runs"):
        make_split(one, kind="by_run")


def test_belsten_loader(belsten):
    d = belsten
    assert d.n == 3378
    counts = [int((d.run == r).sum()) for r in d.runs]
    assert counts == [486, 486, 589, 584, 560, 673]
    assert 23 < d.temperature[:486].mean() < 25 and d.temperature[d.run == 6].max() > 60
    validate(d)   # spread timestamps: no duplicates, all finite, Celsius
    np.testing.assert_allclose(np.sqrt(np.mean((d.b_ref - d.b_meas) ** 2, axis=0)), [3.3614, 2.1746, 1.5968],
                               atol=5e-5)   # the paper's Table 5 "raw" row


def test_a_header_without_rows_is_one_error_and_no_numpy_warning(tmp_path):
    """A CSV with a header and no rows: one DataError (numpy's "input contained no data" warning was printed first)."""
    import warnings

    from bayesmag._src.core.data import DataError, load_csv
    p = tmp_path / "empty.csv"
    p.write_text("time,run,bx_meas,by_meas,bz_meas,temperature\n")
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        with pytest.raises(DataError, match="header but no data rows"):
            load_csv(p, require_reference=False)
    assert not w, [str(x.message) for x in w]
