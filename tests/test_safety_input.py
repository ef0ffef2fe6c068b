"""Issue 21 items 5-15 and 19, issue 22 item 3: nothing unusable written, bad inputs one line, the library checked.

Command-line cases go through ``bayesmag._src.app.cli.main`` and assert exit status 2 with one
``bayesmag: error:`` line on stderr naming the key, column, row or field (and the fix), never a
traceback. Library cases call the public entry points with the same bad inputs.
"""

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

import bayesmag
from bayesmag import CalibrationData, DataError, write_csv


def _mod(name: str):
    """``bayesmag._src.<name>`` wherever the layout puts it (flat, or core/pipeline/app)."""
    import importlib
    for pkg in ("bayesmag._src", "bayesmag._src.core", "bayesmag._src.pipeline", "bayesmag._src.app"):
        try:
            return importlib.import_module(f"{pkg}.{name}")
        except ModuleNotFoundError as e:
            if e.name != f"{pkg}.{name}":
                raise
    raise ModuleNotFoundError(f"bayesmag._src has no module {name!r}")


A = _mod("artifact")
D = _mod("data")
ArtifactError, load, save_calibration = A.ArtifactError, A.load, A.save_calibration
main = _mod("cli").main
load_csv = D.load_csv
from bayesmag.simulate import simulate

CONFIG = """name = "t"
[data]
path = "{data}"
{data_extra}
[split]
kind = "{split}"
test_fraction = 0.2
[uq]
method = "analytic"
n_params = 10
n_qmc = 16
{uq_extra}
[output]
figures = false
progress = false
"""


def _rec(n=200, seed=0, **kw) -> CalibrationData:
    return simulate(n, design="iid", seed=seed, **kw)


def _csv(path, data=None, **replace) -> Path:
    d = data or _rec()
    write_csv(CalibrationData(replace.get("b_meas", d.b_meas), replace.get("temperature", d.temperature),
                              replace.get("b_ref", d.b_ref), replace.get("time", d.time),
                              replace.get("run", d.run)), path)
    return Path(path)


def _config(folder: Path, data: Path, *, split="random", data_extra="", uq_extra="") -> Path:
    p = folder / "cfg.toml"
    p.write_text(CONFIG.format(data=data, split=split, data_extra=data_extra, uq_extra=uq_extra))
    return p


def _strict(text: str):
    """json.loads that refuses the non-standard NaN/Infinity tokens."""
    def bad(tok):
        raise ValueError(f"non-standard JSON token {tok}")
    return json.loads(text, parse_constant=bad)


def _error(capsys) -> str:
    """The single ``bayesmag: error:`` line on stderr (no traceback)."""
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if "error:" in ln]
    assert len(lines) == 1, err
    return lines[0]


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    """One finished physics run folder (copied by tests that tamper with it)."""
    folder = tmp_path_factory.mktemp("model")
    rec = _csv(folder / "rec.csv")
    assert main(["run", str(_config(folder, rec)), "--out", str(folder / "run"), "--no-progress"]) == 0
    return folder / "run"


def _tampered(tmp_path, model, edit) -> Path:
    run = tmp_path / "run"
    shutil.copytree(model, run)
    doc = json.loads((run / "calibration.json").read_text())
    edit(doc)
    (run / "calibration.json").write_text(json.dumps(doc))
    return run


# --------------------------------------------------------------------------- item 5: run writes only loadable files


@pytest.mark.parametrize("case", ["ten_rows", "one_belsten_run"])
def test_run_writes_a_calibration_apply_and_export_accept(tmp_path, capsys, case, belsten):
    if case == "ten_rows":
        rec, split = _csv(tmp_path / "rec.csv", _rec(10, seed=3)), "none"
    else:
        one = belsten.subset(belsten.run == 3)                 # 589 rows, one real run alone
        assert one.n == 589
        rec, split = _csv(tmp_path / "rec.csv", one), "random"
    out = tmp_path / "run"
    assert main(["run", str(_config(tmp_path, rec, split=split)), "--out", str(out), "--no-progress"]) == 0
    cal = load(out)                                            # the loader apply and export use
    np.testing.assert_array_equal(cal.cov, np.swapaxes(cal.cov, -1, -2))
    assert main(["export", str(out), "--format", "json", "--out", str(tmp_path / "c.export.json")]) == 0
    assert main(["apply", "--model", str(out), "--data", str(rec), "--out", str(tmp_path / "cal.csv"),
                 "--no-progress"]) == 0


def test_save_symmetrises_the_covariance_and_run_reads_its_calibration_back(tmp_path, capsys, monkeypatch):
    fit = bayesmag.fit_physics(_rec())
    Domain, Predictor = _mod("domain").Domain, _mod("predictor").Predictor
    pred = Predictor(fit=fit, sigma_in=np.eye(4) * 0.01, residual_sd=np.zeros(3),
                              domain=Domain.from_data(_rec()))
    cov = np.array(fit.cov)
    cov[:, 0, 1] *= 1 + 1.5e-7                                 # the asymmetry the issue measured
    import dataclasses
    pred = dataclasses.replace(pred, fit=dataclasses.replace(fit, cov=cov))
    save_calibration(tmp_path, pred, config={})
    saved = A.read_calibration(tmp_path).cov
    np.testing.assert_array_equal(saved, np.swapaxes(saved, -1, -2))
    # a calibration the loader refuses makes the run fail (exit 2), and nothing is written
    art = A
    real = art.save_calibration

    def broken(path, *a, **k):
        real(path, *a, **k)
        (Path(path) / "calibration.json").write_text("{}")
    monkeypatch.setattr(art, "save_calibration", broken)
    rec = _csv(tmp_path / "rec.csv")
    out = tmp_path / "out"
    assert main(["run", str(_config(tmp_path, rec)), "--out", str(out), "--no-progress"]) == 2
    assert "its own loader refuses" in _error(capsys) and not out.exists()


# --------------------------------------------------------------------------- item 6: training rows, strict JSON


def test_too_few_training_rows_after_the_split_is_refused(tmp_path, capsys):
    rec = _csv(tmp_path / "rec.csv")
    rc = main(["run", str(_config(tmp_path, rec)), "--out", str(tmp_path / "o"), "--no-progress",
               "--set", "split.test_fraction=0.999"])
    line = _error(capsys)
    assert rc == 2 and "[split] leaves 0 training rows" in line and "split.test_fraction" in line
    assert not (tmp_path / "o").exists()


def test_every_json_file_a_run_writes_is_strict(model):
    files = sorted(model.glob("*.json"))
    assert {"metrics.json", "params.json", "calibration.json"} <= {f.name for f in files}
    for f in files:
        _strict(f.read_text())


def test_a_run_with_a_nan_metric_writes_null(tmp_path, monkeypatch):
    M = _mod("metrics")
    monkeypatch.setattr(M, "mae", lambda y, x: np.full(3, np.nan))      # a metric that came out NaN
    rec = _csv(tmp_path / "rec.csv")
    assert main(["run", str(_config(tmp_path, rec)), "--out", str(tmp_path / "o"), "--no-progress"]) == 0
    m = _strict((tmp_path / "o" / "metrics.json").read_text())
    assert m["raw"]["mae"] == {"x": None, "y": None, "z": None}
    assert (tmp_path / "o" / "report.md").exists()                      # the report reads the nulls back


@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf"), np.float64("nan"), np.array([1.0, np.nan])])
def test_jsonio_writes_null_for_non_finite(value, tmp_path):
    jsonio = _mod("jsonio")
    jsonio.write_json(tmp_path / "m.json", {"a": value, "b": [1, {"c": value}]})
    doc = _strict((tmp_path / "m.json").read_text())
    flat = json.dumps(doc)
    assert "NaN" not in flat and "Infinity" not in flat and "null" in flat


# --------------------------------------------------------------------------- items 7, 12, 19: CSV reading


def _write_text(path, text, encoding="utf-8") -> Path:
    Path(path).write_bytes(text.encode(encoding))
    return Path(path)


def _canonical_text(n=60, *, quote=False, extra=None, sep=","):
    d = _rec(n)
    names = ["time", "run", "bx_meas", "by_meas", "bz_meas", "temperature", "bx_ref", "by_ref", "bz_ref"]
    head = [f'"{c}"' if quote else c for c in names] + ([extra[0]] if extra else [])
    rows = [sep.join(head)]
    for i in range(d.n):
        vals = [f"{d.time[i]:.3f}", "0", *(f"{v:.6f}" for v in d.b_meas[i]), f"{d.temperature[i]:.4f}",
                *(f"{v:.6f}" for v in d.b_ref[i])] + ([extra[1](i)] if extra else [])
        rows.append(sep.join(vals))
    return "\n".join(rows) + "\n"


def test_two_columns_of_one_name_are_refused_naming_both(tmp_path, capsys):
    text = _canonical_text(extra=("temperature", lambda i: "99.0"))
    p = _write_text(tmp_path / "dup.csv", text)
    with pytest.raises(DataError, match=r"column 'temperature' twice \(column 6 and column 10\)"):
        load_csv(p)
    assert main(["run", str(_config(tmp_path, p)), "--out", str(tmp_path / "o"), "--no-progress"]) == 2
    assert "twice" in _error(capsys)
    import pandas as pd
    df = pd.DataFrame(np.ones((3, 5)), columns=["bx_meas", "by_meas", "bz_meas", "temperature", "temperature"])
    with pytest.raises(DataError, match="two columns named 'temperature'"):
        _mod("frames").from_frame(df)


@pytest.mark.parametrize("damage", ["huge_field", "unbalanced_quote"])
@pytest.mark.parametrize("command", ["run", "apply", "discover"])
def test_csv_errors_are_one_line(tmp_path, capsys, model, damage, command):
    text = _canonical_text(120)
    lines = text.splitlines()
    if damage == "huge_field":
        lines[5] = lines[5] + "x" * 140_000                    # one field over csv's 131072-character limit
        lines[5] = lines[5].replace("x", "", 1)
        lines[5] = ",".join(lines[5].split(",")[:-1] + ['"' + "x" * 140_000 + '"'])
    else:
        lines[5] = lines[5].replace(",", ',"', 1)              # an opening quote never closed
        lines = lines + [lines[-1]] * 2000
        lines[40] = lines[40] + "x" * 140_000
    p = _write_text(tmp_path / "bad.csv", "\n".join(lines) + "\n")
    out = tmp_path / ("o.csv" if command == "apply" else "o")
    argv = {"run": ["run", str(_config(tmp_path, p)), "--out", str(out), "--no-progress"],
            "apply": ["apply", "--model", str(model), "--data", str(p), "--out", str(out), "--no-progress"],
            "discover": ["discover", "--data", str(p), "--out", str(out), "--no-figures", "--no-progress"]}[command]
    assert main(argv) == 2
    line = _error(capsys)
    assert str(p) in line and ("line" in line or "row" in line) and "quote" in line
    assert not out.exists()


def test_quoted_header_is_read(tmp_path):
    p = _write_text(tmp_path / "q.csv", _canonical_text(quote=True))
    d = load_csv(p)
    assert d.n == 60 and d.b_ref is not None


def test_unused_text_column_is_ignored_with_a_note(tmp_path, capsys):
    p = _write_text(tmp_path / "t.csv", _canonical_text(extra=("comment", lambda i: f"operator {i % 3}")))
    with pytest.warns(D.DataNote, match="column 'comment' holds text"):
        d = load_csv(p)
    assert d.n == 60
    rc = main(["run", str(_config(tmp_path, p)), "--out", str(tmp_path / "o"), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 0 and "bayesmag: note:" in err and "comment" in err
    # a text value in a column the calibration uses is still refused, naming the row
    bad = _canonical_text().replace("\n0.000,", "\n0.000,", 1).splitlines()
    bad[3] = bad[3].split(",", 1)[0] + ",0,abc," + bad[3].split(",", 3)[3]
    with pytest.raises(DataError, match=r"data row 3, column 'bx_meas' holds 'abc'"):
        load_csv(_write_text(tmp_path / "b.csv", "\n".join(bad) + "\n"))


def test_a_latin1_byte_is_decoded_with_a_note(tmp_path):
    text = _canonical_text(extra=("note", lambda i: "Müller" if i == 7 else "x"))
    p = _write_text(tmp_path / "l1.csv", text, encoding="latin-1")
    with pytest.warns(D.DataNote, match=r"line 9 holds the byte 0xfc, which is not UTF-8; the file was read as Latin-1"):
        d = load_csv(p)
    assert d.n == 60
    (tmp_path / "bin.csv").write_bytes(b"\x00\x01\x02binary")
    with pytest.raises(DataError, match="not a text file"):
        load_csv(tmp_path / "bin.csv")


# --------------------------------------------------------------------------- item 19: field units


def test_all_zero_field_is_called_zero(tmp_path, capsys):
    d = _rec()
    p = _csv(tmp_path / "z.csv", d, b_meas=np.zeros_like(d.b_meas))
    assert main(["run", str(_config(tmp_path, p)), "--out", str(tmp_path / "o"), "--no-progress"]) == 2
    line = _error(capsys)
    assert "zero in every row" in line and "mT" not in line and "gauss" not in line


@pytest.mark.parametrize("how", ["flag", "config"])
def test_low_field_session_is_accepted_when_the_unit_is_declared(tmp_path, capsys, how):
    d = _rec(300, noise_sd=0.0005)
    k = 0.69 / np.percentile(np.abs(d.b_ref), 99)              # a genuine low-field session: p99 0.69 uT
    p = _csv(tmp_path / "low.csv", d, b_meas=d.b_meas * k, b_ref=d.b_ref * k)
    cfg = _config(tmp_path, p)
    assert main(["run", str(cfg), "--out", str(tmp_path / "refused"), "--no-progress"]) == 2
    line = _error(capsys)
    assert "looks like mT" in line and "--field-unit uT" in line
    if how == "flag":
        argv = ["run", str(cfg), "--field-unit", "uT"]
    else:
        argv = ["run", str(_config(tmp_path, p, data_extra='field_unit = "uT"'))]
    assert main(argv + ["--out", str(tmp_path / "ok"), "--no-progress"]) == 0
    assert max(np.abs(load(tmp_path / "ok").domain.high[:3])) < 5.0      # trained on the low field itself


def test_field_unit_declared_on_apply_and_discover(tmp_path, capsys, model):
    d = _rec(120, seed=4)
    p = _csv(tmp_path / "nt.csv", d, b_meas=d.b_meas * 1000, b_ref=d.b_ref * 1000)
    out = tmp_path / "o.csv"
    assert main(["apply", "--model", str(model), "--data", str(p), "--out", str(out), "--no-progress"]) == 2
    assert "looks like nT" in _error(capsys)
    assert main(["apply", "--model", str(model), "--data", str(p), "--out", str(out), "--no-progress",
                 "--field-unit", "nT"]) == 0
    assert main(["discover", "--data", str(p), "--out", str(tmp_path / "d"), "--no-figures", "--no-progress"]) == 2
    assert "looks like nT" in capsys.readouterr().err


def test_a_reference_in_another_unit_than_the_declared_one_is_not_scored(tmp_path, model):
    """Readings logged in nT, the reference in uT, ``--field-unit nT``: both were divided by 1000 and the reference
    scored as RMSE 22 uT, coverage 10 % with no word. Now the rows are written and the reference is not scored."""
    from bayesmag._src.app.apply import apply_calibration
    d = _rec(120, seed=4)
    p = _csv(tmp_path / "mixed.csv", d, b_meas=d.b_meas * 1000, b_ref=d.b_ref)
    s = apply_calibration(model, p, tmp_path / "o.csv", field_unit="nT")
    # seventh outside pass: two overlapping warnings, the first "the calibrated values are wrong by that factor",
    # while the calibrated values (from the nT readings) are right: one warning, saying what is affected
    ref = [w for w in s["warnings"] if "reference" in w]
    assert "metrics" not in s and len(ref) == 1, s["warnings"]
    assert "look like another unit than the readings" in ref[0] and "no RMSE or coverage" in ref[0]
    assert "calibrated values are unaffected" in ref[0] and "are in uT" in ref[0]
    assert not any("wrong by that factor" in w for w in s["warnings"])
    both = _csv(tmp_path / "both.csv", d, b_meas=d.b_meas * 1000, b_ref=d.b_ref * 1000)
    s = apply_calibration(model, both, tmp_path / "o2.csv", field_unit="nT")
    assert max(s["metrics"]["rmse"].values()) < 1.0                     # the same unit: scored


@pytest.mark.extended
def test_a_recording_without_temperature_is_told_what_applying_needs(tmp_path, capsys, model):
    """Seventh outside pass: apply on a recording without a temperature column advised
    `measurement.temperature_terms = false`, a training key that does nothing for a calibration already fitted. Now
    one line: the calibration needs each row's temperature (a column, or --columns temperature=NAME), or a
    recalibration without thermal terms; a calibration without thermal terms needs only a constant for its domain
    check."""
    import pandas as pd
    d = pd.read_csv(_csv(tmp_path / "r.csv", _rec(80, seed=3)))
    d.drop(columns=["temperature"]).to_csv(tmp_path / "no_t.csv", index=False)

    def err(run):
        assert main(["apply", "--model", str(run), "--data", str(tmp_path / "no_t.csv"), "--out",
                     str(tmp_path / "o.csv"), "--no-progress"]) == 2
        return _error(capsys)

    e = err(model)
    assert "no column 'temperature'" in e and "--columns temperature=NAME" in e and "needs each row's temperature" in e
    assert "recalibrate without thermal terms ([physics] temperature_terms = false" in e
    assert "measurement.temperature_terms" not in e and not (tmp_path / "o.csv").exists()
    folder = tmp_path / "plain"
    folder.mkdir()
    cfg = _config(folder, _csv(folder / "rec.csv"))
    cfg.write_text(cfg.read_text() + "[physics]\ntemperature_terms = false\n")
    assert main(["run", str(cfg), "--out", str(folder / "run"), "--no-progress"]) == 0
    capsys.readouterr()
    e = err(folder / "run")
    assert "has no thermal terms" in e and "constant temperature column" in e and "recalibrate" not in e


# --------------------------------------------------------------------------- item 8, 13: config values


@pytest.mark.parametrize("key,value,needle", [
    ("uq.sigma_in", "[-1, -1, -1, -1]", "'uq.sigma_in'"),
    ("uq.sigma_in", "[0.1, 0.1, 0.1, 1e300]", "'uq.sigma_in'"),
    ("uq.reference_sd", "1e300", "'uq.reference_sd'"),
    ("uq.reference_sd", "[0.1, 0.1, 1e300]", "'uq.reference_sd'"),
])
def test_bad_uq_values_are_refused(tmp_path, capsys, key, value, needle):
    rec = _csv(tmp_path / "rec.csv")
    assert main(["run", str(_config(tmp_path, rec)), "--out", str(tmp_path / "o"), "--no-progress",
                 "--set", f"{key}={value}"]) == 2
    assert needle in _error(capsys)


@pytest.mark.parametrize("table,needle", [
    ("n = 5", "'n' = 5 must be an integer of at least 50"),
    ("n = -1", "'n' = -1"),
    ("noise_sd = -1.0", "'noise_sd' = -1.0"),
    ("temp_noise_sd = nan", "'temp_noise_sd'"),
    ('effects = ["no_such_effect"]', "unknown effect 'no_such_effect'; valid effects:"),
    ('effects = [{name = "axis_quadratic", bogus = 1}]', "has no parameter(s) ['bogus']"),
    ('design = "nope"', "'design' = 'nope' is not known; it must be one of ['campaign', 'iid']"),
    ("colour = 1", "unknown simulation config key(s) ['colour']"),
])
def test_bad_simulate_tables_are_one_line(tmp_path, capsys, table, needle):
    cfg = tmp_path / "s.toml"
    cfg.write_text(f'[data]\nsource = "simulated"\n[data.simulate]\n{table}\n[output]\nfigures = false\n')
    assert main(["run", str(cfg), "--out", str(tmp_path / "o"), "--no-progress"]) == 2
    line = _error(capsys)
    assert "[data.simulate]" in line and needle in line


def test_quickstart_with_almost_everything_held_out(tmp_path, capsys):
    assert main(["run", "quickstart", "--out", str(tmp_path / "o"), "--no-progress",
                 "--set", "split.test_fraction=0.999", "--set", "output.figures=false"]) == 2
    assert "[split] leaves" in _error(capsys)


# --------------------------------------------------------------------------- items 9, 15, 19: calibration.json


def _set_t0(v):
    def edit(doc):
        doc["model"]["terms"][0]["settings"]["t0"] = v
    return edit


@pytest.mark.parametrize("edit,needle", [
    (_set_t0(float("nan")), "model.thermo_affine.t0"),
    (_set_t0(1e300), "model.thermo_affine.t0"),
    (_set_t0("20"), "'model.thermo_affine.t0' = '20' must be a number, not str"),
    (lambda doc: doc["domain"].__setitem__("low", [1e300] * 4), "domain.low"),
    (lambda doc: doc.__setitem__("format_version", "1"), "'format_version' = '1' must be an integer"),
    (lambda doc: doc.__setitem__("format_version", 999), "written by a newer bayesmag"),
])
def test_tampered_calibration_json_is_refused(tmp_path, capsys, model, edit, needle):
    run = _tampered(tmp_path, model, edit)
    with pytest.raises(ArtifactError, match=None) as e:
        load(run)
    assert needle in str(e.value)
    for argv in (["export", str(run), "--format", "px4", "--out", str(tmp_path / "x.params")],
                 ["apply", "--model", str(run), "--data", str(_csv(tmp_path / "r.csv")), "--out",
                  str(tmp_path / "o.csv"), "--no-progress"]):
        assert main(argv) == 2
        assert needle.split("'")[0] in _error(capsys)
    assert not (tmp_path / "x.params").exists() and not (tmp_path / "o.csv").exists()
    if "newer" in needle:
        assert "upgrade bayesmag" in str(e.value) and "install that version" not in str(e.value)


@pytest.mark.parametrize("value", [1e300, float("nan")])
def test_absurd_parameters_in_the_npz_are_refused(tmp_path, model, value):
    run = tmp_path / "run"
    shutil.copytree(model, run)
    with np.load(run / "calibration.npz") as f:
        arrays = {k: f[k] for k in f.files}
    arrays["theta"] = arrays["theta"].copy()
    arrays["theta"][0, 6] = value
    np.savez(run / "calibration.npz", **arrays)
    with pytest.raises(ArtifactError, match="field 'theta'"):
        load(run)


def test_export_never_writes_a_non_finite_value():
    ex_mod = _mod("export")
    Export, ExportError, _check_finite = ex_mod.Export, ex_mod.ExportError, getattr(ex_mod, "_check_finite", None)
    assert _check_finite is not None, "export has no finiteness check"
    coef = {"S": np.eye(3), "Ks": np.zeros((3, 3)), "O": np.zeros(3), "Ko": np.zeros(3), "t0": 0.0}
    ex = Export(coef, 20.0, (10.0, 30.0), np.eye(3), np.zeros(3), {"CAL_MAG0_XOFF": float("nan")}, {}, (), False,
                None, "test")
    with pytest.raises(ExportError, match="px4.CAL_MAG0_XOFF would be non-finite"):
        _check_finite(ex)


# --------------------------------------------------------------------------- item 14: export --temperature


@pytest.mark.parametrize("t", ["nan", "inf", "-inf", "1e308", "-300"])
def test_export_temperature_must_be_usable(tmp_path, capsys, model, t):
    out = tmp_path / "c.h"
    assert main(["export", str(model), "--format", "c-header", "--out", str(out), f"--temperature={t}"]) == 2
    assert "--temperature" in _error(capsys) and not out.exists()


def test_export_temperature_outside_training_range_warns(tmp_path, capsys, model):
    out = tmp_path / "c.h"
    assert main(["export", str(model), "--format", "magcal", "--out", str(out), "--temperature", "150"]) == 0
    assert "WARNING: --temperature 150 C lies outside the training range" in capsys.readouterr().out


# --------------------------------------------------------------------------- item 10: apply options


@pytest.mark.parametrize("flags,needle", [
    (["--level", "1.5"], "--level 1.5 must be a number in (0, 1)"),
    (["--level", "nan"], "--level nan"),
    (["--level", "0"], "--level 0.0"),
    (["--n-qmc", "0", "--uq", "psqmc"], "--n-qmc 0 must be an integer of at least 2"),
    (["--n-params", "0", "--uq", "psqmc"], "--n-params 0"),
])
def test_apply_options_are_validated(tmp_path, capsys, model, flags, needle):
    rec = _csv(tmp_path / "r.csv")
    out = tmp_path / "o.csv"
    assert main(["apply", "--model", str(model), "--data", str(rec), "--out", str(out), "--no-progress"] + flags) == 2
    assert needle in _error(capsys) and not out.exists()


def test_apply_exits_non_zero_when_no_row_is_calibrated(tmp_path, capsys, model):
    d = _rec(50)
    rec = _csv(tmp_path / "r.csv", d, temperature=np.full(d.n, np.nan))
    out = tmp_path / "o.csv"
    assert main(["apply", "--model", str(model), "--data", str(rec), "--out", str(out), "--no-progress"]) == 2
    assert "no row can be calibrated" in _error(capsys) and not out.exists()


# --------------------------------------------------------------------------- item 11: run ids, kelvin, reference units


def test_run_ids_beyond_int64_are_refused(tmp_path, capsys):
    d = _rec()
    run = np.where(np.arange(d.n) < 100, 1e20, 2e20)           # two runs that int64 would merge
    p = _csv(tmp_path / "r.csv", d)
    text = p.read_text().splitlines()
    text = [text[0]] + [",".join([ln.split(",")[0], f"{run[i]:.0f}"] + ln.split(",")[2:])
                        for i, ln in enumerate(text[1:])]
    p.write_text("\n".join(text) + "\n")
    assert main(["run", str(_config(tmp_path, p)), "--out", str(tmp_path / "o"), "--no-progress"]) == 2
    line = _error(capsys)
    assert "Column 'run'" in line and "2**53" in line and "data row(s) 1" in line
    with pytest.raises(DataError, match="2\\*\\*53"):
        CalibrationData(np.zeros((2, 3)), np.zeros(2), None, run=np.array([2**63 - 1, 1], dtype=np.int64))
    assert CalibrationData(np.zeros((2, 3)), np.zeros(2), None, run=[2**52, 2**52 + 1]).runs.size == 2


def test_temperature_below_absolute_zero_is_refused(tmp_path, capsys):
    d = _rec()
    t = d.temperature.copy()
    t[17] = -300.0
    p = _csv(tmp_path / "r.csv", d, temperature=t)
    assert main(["run", str(_config(tmp_path, p)), "--out", str(tmp_path / "o"), "--no-progress"]) == 2
    line = _error(capsys)
    assert "below absolute zero" in line and "data row(s) 18" in line


def test_apply_refuses_reference_columns_in_nT(tmp_path, capsys, model):
    d = _rec(100, seed=5)
    p = _csv(tmp_path / "r.csv", d, b_ref=d.b_ref * 1000)
    out = tmp_path / "o.csv"
    assert main(["apply", "--model", str(model), "--data", str(p), "--out", str(out), "--no-progress"]) == 2
    line = _error(capsys)
    assert "reference field (bx_ref, by_ref, bz_ref)" in line and "nT" in line and not out.exists()


# --------------------------------------------------------------------------- issue 22 item 3: the library's checks


@pytest.fixture(scope="module")
def frame():
    import pandas as pd
    d = _rec(300, seed=2)
    return pd.DataFrame({"bx_meas": d.b_meas[:, 0], "by_meas": d.b_meas[:, 1], "bz_meas": d.b_meas[:, 2],
                         "temperature": d.temperature, "bx_ref": d.b_ref[:, 0], "by_ref": d.b_ref[:, 1],
                         "bz_ref": d.b_ref[:, 2]})


def _scaled(df, field=1.0, kelvin=False):
    out = df.copy()
    for c in out.columns:
        if c != "temperature":
            out[c] = out[c] * field
    if kelvin:
        out["temperature"] = out["temperature"] + 273.15
    return out


@pytest.mark.parametrize("field,kelvin,kwargs,needle", [
    (1000.0, False, {}, "looks like nT"),
    (1e-3, False, {}, "looks like mT"),
    (1e-2, False, {}, "gauss"),
    (1.0, True, {}, "looks like kelvin"),
])
def test_fit_physics_refuses_wrong_units(frame, field, kelvin, kwargs, needle):
    with pytest.raises(DataError, match=needle) as e:
        bayesmag.fit_physics(_scaled(frame, field, kelvin), **kwargs)
    assert "field_unit=" in str(e.value) or "temperature_unit='K'" in str(e.value)


@pytest.mark.parametrize("unit,factor", [("nT", 1000.0), ("mT", 1e-3), ("G", 1e-2)])
def test_fit_physics_converts_declared_units(frame, unit, factor):
    ref = bayesmag.fit_physics(frame)
    fit = bayesmag.fit_physics(_scaled(frame, factor, kelvin=True), field_unit=unit, temperature_unit="K")
    np.testing.assert_allclose(fit.theta, ref.theta, rtol=1e-7, atol=1e-9)


def test_numpy_arrays_in_the_documented_order(frame):
    assert D.ARRAY_COLUMNS[:4] == ("bx_meas", "by_meas", "bz_meas", "temperature")
    x = frame[list(D.ARRAY_COLUMNS)].to_numpy()
    np.testing.assert_array_equal(bayesmag.fit_physics(x).theta, bayesmag.fit_physics(frame).theta)
    cal = bayesmag.Calibrator().fit(frame)
    out = cal.calibration_.predict(x[:, :4])
    assert isinstance(out, dict) and out["calibrated"].shape == (300, 3)
    with pytest.raises(DataError, match=r"shape \(n, 4\) or \(n, 7\)"):
        bayesmag.fit_physics(x[:, :5])


def test_calibration_predict_checks_units_and_returns_a_frame(frame, tmp_path):
    cal = bayesmag.Calibrator(out=tmp_path / "api").fit(frame).calibration_
    df = frame.drop(columns=["bx_ref", "by_ref", "bz_ref"])
    with pytest.raises(DataError, match="looks like kelvin"):
        cal.predict(_scaled(df, kelvin=True))
    with pytest.raises(DataError, match="looks like nT"):
        cal.predict(_scaled(df, 1000.0))
    with pytest.raises(DataError, match="gauss"):          # before: calibrated as uT with a warning only
        cal.predict(_scaled(df, 1e-2))
    good = cal.predict(df)
    np.testing.assert_allclose(cal.predict(_scaled(df, 1e-2), field_unit="G")["x_calibrated"], good["x_calibrated"],
                               rtol=1e-9)
    conv = cal.predict(_scaled(df, 1000.0, kelvin=True), field_unit="nT", temperature_unit="K")
    import pandas as pd
    assert isinstance(good, pd.DataFrame) and list(good.index) == list(df.index)
    np.testing.assert_allclose(conv["x_calibrated"], good["x_calibrated"], rtol=1e-9)
    renamed = df.rename(columns={"bx_meas": "X", "temperature": "T"})
    mapped = cal.predict(renamed, columns={"bx_meas": "X", "temperature": "T"})
    np.testing.assert_array_equal(mapped["x_calibrated"], good["x_calibrated"])
    for r in (repr(cal), repr(cal.predictor())):
        assert len(r) < 300 and "array" not in r


def test_discover_refuses_nT_from_the_library(frame):
    with pytest.raises(DataError, match="looks like nT"):
        bayesmag.discover(_scaled(frame, 1000.0), figures=False)


def test_repeated_timestamps_spread_on_request(frame, tmp_path):
    df = frame.copy()
    df["time"] = np.repeat(np.arange(75), 4).astype(float)     # whole-second stamps at 4 Hz, as in the real files
    with pytest.raises(DataError, match="duplicate_times='spread'") as e:
        bayesmag.Calibrator(out=tmp_path / "a", duplicate_times="refuse").fit(df)
    assert "tmp" not in str(e.value) and "fit_data.csv" not in str(e.value)
    assert bayesmag.Calibrator().fit(df).calibration_.theta.shape == (3, 8)     # default: time is not used
    cal = bayesmag.Calibrator(out=tmp_path / "b", duplicate_times="spread").fit(df)
    assert cal.calibration_.theta.shape == (3, 8)
    # a physics fit does not use time: repeated stamps are fine there
    assert bayesmag.fit_physics(df).theta.shape == (3, 8)
    d = CalibrationData(np.ones((6, 3)) * 40, np.full(6, 20.0), None, time=[0, 0, 0, 0, 1, 1], run=[1] * 6)
    np.testing.assert_allclose(D.spread_duplicate_times(d).time, [0, 0.25, 0.5, 0.75, 1, 1.5])


def test_low_field_from_the_library_with_a_declared_unit(frame):
    small = _scaled(frame, 0.69 / np.percentile(np.abs(frame["bx_ref"]), 99) / 2)
    with pytest.raises(DataError, match="field_unit='uT'"):
        bayesmag.fit_physics(small)
    assert math.isfinite(float(bayesmag.fit_physics(small, field_unit="uT").theta[0, 0]))


def test_one_field_column_out_of_range_is_named_not_called_nt(frame):
    """One column 2000 uT off while the other two are plausible: the message said "looks like nT ... divide by 1000"
    (wrong advice for a corrupt column or a broken unit); it now names the column and both readings."""
    bad = frame.copy()
    bad["bx_meas"] = bad["bx_meas"] + 2000.0
    with pytest.raises(DataError, match=r"bx_meas reaches .* either that one column is corrupt") as e:
        bayesmag.fit_physics(bad)
    assert "by_meas" in str(e.value) and "bz_meas" in str(e.value)
    with pytest.raises(DataError, match="looks like nT"):                 # all three scaled: still the unit
        bayesmag.fit_physics(_scaled(frame, 1000.0))
