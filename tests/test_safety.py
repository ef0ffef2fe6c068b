"""Issue 11: never lose a user's data -- safe outputs, validated calibrations, one-line errors.

Every case works in temporary folders. The bad-input table at the end drives ``run``, ``apply``
and ``discover`` through ``bayesmag._src.app.cli.main`` and asserts exit code 2, a single line on
stderr that names the row, column, key or field, and no traceback.
"""

import json
import os
import re
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bayesmag import CalibrationData, DataError, load_csv, validate, write_csv
from bayesmag._src.app import job as job_module
from bayesmag._src.app import outdir
from bayesmag._src.app.artifact import ArtifactError, load
from bayesmag._src.app.cli import main
from bayesmag._src.core.fit import RANK_RTOL, fit_physics, unidentifiable
from bayesmag._src.app.outdir import MARKER, OutputError, marker_status, recover, staging_dir
from bayesmag.simulate import simulate

from helpers import SMALL_JOB_CONFIG as CONFIG  # noqa: E402


def _recording(n=200, seed=0) -> CalibrationData:
    return simulate(n, design="iid", seed=seed)


def _write(path, data=None, **replace) -> Path:
    d = data or _recording()
    write_csv(CalibrationData(replace.get("b_meas", d.b_meas), replace.get("temperature", d.temperature),
                              replace.get("b_ref", d.b_ref), replace.get("time", d.time), d.run), path)
    return Path(path)


def _config(folder: Path, data: Path) -> Path:
    p = folder / "cfg.toml"
    p.write_text(CONFIG.format(data=data))
    return p


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    """One finished physics run folder (copied by tests that tamper with it)."""
    folder = tmp_path_factory.mktemp("model")
    rec = _write(folder / "rec.csv")
    assert main(["run", str(_config(folder, rec)), "--out", str(folder / "run"), "--no-progress"]) == 0
    return folder / "run"


@pytest.fixture
def no_work(monkeypatch):
    """Fail loudly if the computation starts: refusals must come before it."""
    def boom(*a, **k):
        raise AssertionError("the job started computing")
    monkeypatch.setattr(job_module, "_run_job", boom)


def _err(capsys) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err


# --------------------------------------------------------------------------- 1. foreign --out folders


def test_run_refuses_a_folder_bayesmag_did_not_write(tmp_path, capsys, no_work):
    rec = _write(tmp_path / "rec.csv")
    u = tmp_path / "u"
    u.mkdir()
    (u / "thesis.txt").write_text("x")
    rc = main(["run", str(_config(tmp_path, rec)), "--out", str(u), "--no-progress"])
    err = _err(capsys)
    assert rc == 2 and str(u) in err and "did not write" in err and f"--out {u}_2" in err
    assert (u / "thesis.txt").read_text() == "x" and sorted(os.listdir(u)) == ["thesis.txt"]
    assert not list(tmp_path.glob(".u.*"))                     # no lock or staging left behind


@pytest.mark.parametrize("form", [".", "$PWD"])
def test_run_refuses_the_working_folder(tmp_path, capsys, monkeypatch, no_work, form):
    rec = _write(tmp_path / "rec.csv")
    cfg = _config(tmp_path, rec)
    monkeypatch.chdir(tmp_path)
    before = sorted(os.listdir(tmp_path))
    rc = main(["run", str(cfg), "--out", str(tmp_path) if form == "$PWD" else ".", "--no-progress"])
    assert rc == 2 and "did not write" in _err(capsys)
    assert sorted(os.listdir(tmp_path)) == before


def test_run_refuses_a_run_folder_that_holds_its_input(tmp_path, capsys, model):
    run = tmp_path / "run"
    shutil.copytree(model, run)
    rec = _write(run / "rec.csv")                              # the recording now lives in the run folder
    rc = main(["run", str(_config(tmp_path, rec)), "--out", str(run), "--no-progress"])
    assert rc == 2 and "contains the input" in _err(capsys)
    assert rec.exists()


def test_run_refuses_a_run_folder_holding_a_users_file(tmp_path, capsys, model, no_work):
    run = tmp_path / "run"
    shutil.copytree(model, run)
    (run / "notes.txt").write_text("mine")
    rec = _write(tmp_path / "rec.csv")
    rc = main(["run", str(_config(tmp_path, rec)), "--out", str(run), "--no-progress"])
    assert rc == 2 and "also holds files bayesmag did not write (notes.txt)" in _err(capsys)
    assert (run / "notes.txt").read_text() == "mine"


def test_study_refuses_a_foreign_out_before_computing(tmp_path, capsys, monkeypatch):
    import bayesmag._src.app.study as study
    monkeypatch.setattr(study, "run_study", lambda *a, **k: (_ for _ in ()).throw(AssertionError("computed")))
    (tmp_path / "u").mkdir()
    (tmp_path / "u" / "thesis.txt").write_text("x")
    cfg = tmp_path / "s.toml"
    cfg.write_text('[data]\nsource = "simulated"\n[study]\nsizes = [1000]\n')   # a study needs its sizes
    assert main(["study", str(cfg), "--out", str(tmp_path / "u")]) == 2
    assert "did not write" in _err(capsys) and (tmp_path / "u" / "thesis.txt").exists()


def test_run_refuses_a_file_as_out(tmp_path, capsys, no_work):
    rec = _write(tmp_path / "rec.csv")
    rc = main(["run", str(_config(tmp_path, rec)), "--out", str(rec), "--no-progress"])
    assert rc == 2 and "is not a folder bayesmag wrote" in _err(capsys)
    assert load_csv(rec).n == 200


def test_run_replaces_its_own_run_and_fills_an_empty_folder(tmp_path, capsys):
    rec = _write(tmp_path / "rec.csv")
    cfg = _config(tmp_path, rec)
    out = tmp_path / "out"
    out.mkdir()                                                # empty: allowed
    assert main(["run", str(cfg), "--out", str(out), "--no-progress"]) == 0
    first = (out / "calibration.npz").read_bytes()
    assert marker_status(out)["complete"] is True
    (out / "calibration.npz").write_bytes(b"stale")            # a bayesmag run folder: replaced whole
    assert main(["run", str(cfg), "--out", str(out), "--no-progress"]) == 0
    assert (out / "calibration.npz").read_bytes() == first
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cfg.toml", "out", "rec.csv"]


# --------------------------------------------------------------------------- 2. apply --out


def test_apply_refuses_to_overwrite_the_recording_or_the_calibration(tmp_path, capsys, model):
    rec = _write(tmp_path / "rec.csv")
    before = rec.read_bytes()
    rc = main(["apply", "--model", str(model), "--data", str(rec), "--out", str(rec), "--no-progress"])
    assert rc == 2 and "is the input recording" in _err(capsys)
    assert rec.read_bytes() == before
    cal = (model / "calibration.json").read_bytes()
    for target in (model / "calibration.json", model / "new.csv"):
        rc = main(["apply", "--model", str(model), "--data", str(rec), "--out", str(target), "--no-progress"])
        assert rc == 2 and "inside the calibration folder" in _err(capsys)
    assert (model / "calibration.json").read_bytes() == cal and not (model / "new.csv").exists()


# --------------------------------------------------------------------------- 3. swap, SIGKILL, recovery

_KILLER = """
import os, signal, sys
from pathlib import Path
from bayesmag._src.app.outdir import staging_dir
out, mode = Path(sys.argv[1]), sys.argv[2]
if mode == "between":                      # die right after phase 1 (old folder renamed away)
    orig = Path.rename
    def rename(self, target):
        r = orig(self, target)
        os.kill(os.getpid(), signal.SIGKILL)
        return r
    Path.rename = rename
with staging_dir(out) as tmp:
    (tmp / "a.txt").write_text("new")
    if mode == "during":
        os.kill(os.getpid(), signal.SIGKILL)
"""


def _killed(out: Path, mode: str) -> int:
    p = subprocess.run([sys.executable, "-c", _KILLER, str(out), mode], env={**os.environ, "JAX_PLATFORMS": "cpu"},
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == -signal.SIGKILL, p.stderr
    return p


def _old_run(out: Path):
    with staging_dir(out) as tmp:
        (tmp / "a.txt").write_text("old")


def test_sigkill_while_writing_keeps_the_old_folder_and_the_partial_is_never_loaded(tmp_path, capsys):
    out = tmp_path / "run"
    _old_run(out)
    _killed(out, "during")
    assert (out / "a.txt").read_text() == "old" and marker_status(out)["complete"]
    partial = [p for p in tmp_path.iterdir() if ".partial-" in p.name]
    assert len(partial) == 1 and marker_status(partial[0])["complete"] is False
    with pytest.raises(ArtifactError, match="temporary folder of an unfinished"):
        load(partial[0])
    renamed = tmp_path / "renamed"
    shutil.copytree(partial[0], renamed)                       # even under another name: marker says incomplete
    with pytest.raises(ArtifactError, match="not finished"):
        load(renamed)
    rec = _write(tmp_path / "rec.csv")
    assert main(["apply", "--model", str(partial[0]), "--data", str(rec), "--out", str(tmp_path / "o.csv")]) == 2
    assert "unfinished" in _err(capsys)
    with staging_dir(out) as tmp:                              # the next run into the same parent cleans up
        (tmp / "a.txt").write_text("next")
    assert (out / "a.txt").read_text() == "next"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".run.")]   # stale partial and lock gone


def test_sigkill_between_the_two_renames_is_recovered(tmp_path):
    out = tmp_path / "run"
    _old_run(out)
    _killed(out, "between")
    assert not out.exists()                                    # the instant between phase 1 and phase 2 ...
    old = [p for p in tmp_path.iterdir() if ".old-" in p.name]
    new = [p for p in tmp_path.iterdir() if ".partial-" in p.name]
    assert len(old) == 1 and marker_status(old[0])["complete"] and (old[0] / "a.txt").read_text() == "old"
    assert len(new) == 1 and marker_status(new[0])["complete"]  # ... has both complete folders
    with pytest.raises(ArtifactError, match=r"earlier result in .*\.run\.old-"):
        load(out)
    done = recover(tmp_path)
    assert any("restored" in d for d in done) and (out / "a.txt").read_text() == "old"
    assert not [p for p in tmp_path.iterdir() if ".old-" in p.name or ".partial-" in p.name]


def test_failed_run_leaves_old_folder_untouched(tmp_path):
    out = tmp_path / "run"
    _old_run(out)
    with pytest.raises(RuntimeError):
        with staging_dir(out) as tmp:
            (tmp / "a.txt").write_text("new")
            raise RuntimeError("boom")
    assert (out / "a.txt").read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]


def test_recover_never_touches_unmarked_folders(tmp_path):
    dead = _dead_pid()
    foreign = tmp_path / f".thesis.partial-{dead}"
    foreign.mkdir()
    (foreign / "chapter1.tex").write_text("x")
    assert recover(tmp_path) == [] and (foreign / "chapter1.tex").exists()


# --------------------------------------------------------------------------- 4. concurrent runs


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_second_writer_is_refused_by_the_lock(tmp_path, capsys, no_work):
    rec = _write(tmp_path / "rec.csv")
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (tmp_path / ".out.lock").write_text(f"{holder.pid}\n")
        rc = main(["run", str(_config(tmp_path, rec)), "--out", str(tmp_path / "out"), "--no-progress"])
        assert rc == 2 and f"another bayesmag process (pid {holder.pid})" in _err(capsys)
        with pytest.raises(OutputError, match="another bayesmag process"):
            with staging_dir(tmp_path / "out"):
                pass
    finally:
        holder.kill()
        holder.wait()
    (tmp_path / ".out.lock").write_text(f"{_dead_pid()}\n")     # stale: its owner is gone -> taken over
    with staging_dir(tmp_path / "out") as tmp:
        (tmp / "a.txt").write_text("ok")
    assert (tmp_path / "out" / "a.txt").exists() and not (tmp_path / ".out.lock").exists()


# --------------------------------------------------------------------------- 5. writable before computing


@pytest.mark.parametrize("kind", ["too_long", "parent_is_file", "read_only"])
def test_unwritable_out_fails_before_computing(tmp_path, capsys, no_work, kind):
    rec = _write(tmp_path / "rec.csv")
    if kind == "too_long":
        out = tmp_path / ("x" * 250)
    elif kind == "parent_is_file":
        out = rec / "out"
    else:
        if os.geteuid() == 0:
            pytest.skip("root ignores folder permissions")
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o555)
        out = ro / "out"
    rc = main(["run", str(_config(tmp_path, rec)), "--out", str(out), "--no-progress"])
    err = _err(capsys)
    assert rc == 2 and err.startswith(f"bayesmag: error: --out {out} cannot be written") and err.count("\n") == 1


def test_disk_full_while_writing_is_one_line_and_keeps_the_old_run(tmp_path, capsys, monkeypatch, model):
    import errno

    import bayesmag._src.app.report as report
    rec = _write(tmp_path / "rec.csv")
    out = tmp_path / "out"
    shutil.copytree(model, out)
    before = (out / "calibration.npz").read_bytes()

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device", str(out / "report.md"))
    monkeypatch.setattr(report, "write_report", full)
    rc = main(["run", str(_config(tmp_path, rec)), "--out", str(out), "--no-progress"])
    err = _err(capsys)
    assert rc == 2 and "No space left on device" in err and err.count("\n") == 1
    assert (out / "calibration.npz").read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cfg.toml", "out", "rec.csv"]


@pytest.mark.parametrize("kind", ["missing_folder", "too_long"])
def test_apply_unwritable_out_fails_before_computing(tmp_path, capsys, monkeypatch, model, kind):
    import bayesmag._src.app.apply as apply_module
    monkeypatch.setattr(apply_module, "load", lambda *a: (_ for _ in ()).throw(AssertionError("loaded")))
    rec = _write(tmp_path / "rec.csv")
    out = tmp_path / "nope" / "o.csv" if kind == "missing_folder" else tmp_path / ("o" * 250 + ".csv")
    assert main(["apply", "--model", str(model), "--data", str(rec), "--out", str(out), "--no-progress"]) == 2
    assert ("does not exist" if kind == "missing_folder" else "File name too long") in _err(capsys)


# --------------------------------------------------------------------------- 6. tampered calibrations


def _tamper_npz(run: Path, **arrays):
    with np.load(run / "calibration.npz") as f:
        a = {k: f[k] for k in f.files}
    for k, v in arrays.items():
        if v is None:
            a.pop(k)
        else:
            a[k] = v(a[k]) if callable(v) and k in a else v
    np.savez(run / "calibration.npz", **a)


def _tamper_json(run: Path, **fields):
    doc = json.loads((run / "calibration.json").read_text())
    for k, v in fields.items():
        if v is None:
            doc.pop(k)
        else:
            doc[k] = v
    (run / "calibration.json").write_text(json.dumps(doc))


def _nan_at(a, idx=(0, 0)):
    a = a.astype(float).copy()
    a[idx] = np.nan
    return a


def _indefinite(c):
    c = c.copy()
    c[0, 0, 1] = c[0, 1, 0] = 10 * np.sqrt(c[0, 0, 0] * c[0, 1, 1])
    return c


def _save_pickled(path: Path):
    with open(path, "wb") as f:                                # a file handle: np.save would append .npy
        np.savez(f, theta=np.array([{}], dtype=object))


_FAKE_NET = {"spec": {}, "fusion": "paper", "n_layers": 1, "passes": 2}
TAMPER = {
    "theta_nan": (lambda r: _tamper_npz(r, theta=_nan_at), "'theta'.*NaN"),
    "cov_inf": (lambda r: _tamper_npz(r, cov=lambda c: np.where(np.eye(c.shape[1], dtype=bool), np.inf, c)),
                "'cov'.*NaN/inf"),
    "cov_not_pd": (lambda r: _tamper_npz(r, cov=_indefinite), r"'cov' \(axis x\) is not positive definite"),
    "sigma_in_nan": (lambda r: _tamper_npz(r, sigma_in=_nan_at), "'sigma_in'"),
    "residual_sd_nan": (lambda r: _tamper_npz(r, residual_sd=lambda a: _nan_at(a, 1)), "'residual_sd'"),
    "theta_shape": (lambda r: _tamper_npz(r, theta=lambda a: a[:2]), r"'theta' has shape \(2, 8\)"),
    "theta_missing": (lambda r: _tamper_npz(r, theta=None), r"lacks arrays \['theta'\]"),
    "npz_random_bytes": (lambda r: (r / "calibration.npz").write_bytes(os.urandom(300)), "cannot be read"),
    "npz_pickled": (lambda r: _save_pickled(r / "calibration.npz"), "cannot be read"),
    "json_random_bytes": (lambda r: (r / "calibration.json").write_bytes(os.urandom(300)), "not valid JSON"),
    "json_no_model": (lambda r: _tamper_json(r, model=None), "lacks field 'model'"),
    "json_bad_model": (lambda r: _tamper_json(r, model={"terms": 3}), "description is damaged"),
    "likelihood": (lambda r: _tamper_json(r, likelihood="cauchy"), "'likelihood' = 'cauchy' is not known"),
    "level": (lambda r: _tamper_json(r, level=1.5), r"'level' = 1.5 must be a number in \(0, 1\)"),
    "domain_nan": (lambda r: _tamper_json(r, domain={"low": [0, 0, 0, float("nan")], "high": [1, 1, 1, 1]}),
                   "'domain.low'"),
    "network_null_with_weights": (lambda r: _tamper_npz(r, **{"network/layer0/w": np.ones((4, 3))}),
                                  "'network' is null but calibration.npz holds network weights"),
    "fusion": (lambda r: (_tamper_json(r, network={**_FAKE_NET, "fusion": "average"}),
                          _tamper_npz(r, **{"network/layer0/w": np.ones((4, 3))})), "'network.fusion' = 'average'"),
    "network_weights_nan": (lambda r: (_tamper_json(r, network=_FAKE_NET),
                                       _tamper_npz(r, **{"network/layer0/w": np.full((4, 3), np.nan),
                                                         "network/layer0/b": np.zeros(3)})),
                            "'network/layer0/w'.*NaN"),
}


@pytest.mark.parametrize("case", sorted(TAMPER))
def test_tampered_calibration_is_refused_naming_the_field(tmp_path, capsys, model, case):
    run = tmp_path / "run"
    shutil.copytree(model, run)
    tamper, match = TAMPER[case]
    tamper(run)
    with pytest.raises(ArtifactError, match=match):
        load(run)
    rec = _write(tmp_path / "rec.csv")
    rc = main(["apply", "--model", str(run), "--data", str(rec), "--out", str(tmp_path / "o.csv"), "--no-progress"])
    err = _err(capsys)
    assert rc == 2 and err.count("\n") == 1 and not (tmp_path / "o.csv").exists()


def test_untampered_calibration_loads(model):
    assert np.isfinite(load(model).theta).all()                # the control for the table above


# --------------------------------------------------------------------------- 7. NaN output is never valid


def test_nan_output_is_never_valid(model):
    import dataclasses
    cal = load(model)
    d = _recording(20)
    bad = dataclasses.replace(cal, theta=_nan_at(cal.theta, (1, 0)))   # bypasses load(): a NaN parameter on y
    pred = bad.predict(d)
    assert np.isnan(pred["calibrated"][:, 1]).all() and not pred["valid"].any()
    assert cal.predict(d)["valid"].all()


# --------------------------------------------------------------------------- 8, 9. CSV header and timestamps


def test_bom_in_header_is_stripped(tmp_path):
    d = _recording(50)
    p = _write(tmp_path / "plain.csv", d)
    q = tmp_path / "bom.csv"
    q.write_bytes(b"\xef\xbb\xbf" + p.read_bytes())
    np.testing.assert_allclose(load_csv(q).time, d.time, atol=1e-6)   # not the row index 0, 1, 2, ...
    assert not np.allclose(d.time, np.arange(d.n))


def test_duplicate_timestamps_found_when_not_adjacent():
    d = _recording(50)
    t = d.time.copy()
    t[30] = t[3]
    with pytest.raises(DataError, match=r"within run 1 at data row\(s\) 31 \(same time as data row\(s\) 4\)"):
        validate(CalibrationData(d.b_meas, d.temperature, d.b_ref, t, d.run))
    validate(CalibrationData(d.b_meas, d.temperature, d.b_ref, d.time[::-1].copy(), d.run))  # unsorted, distinct: fine


def test_unsorted_rows_are_refused_where_the_job_takes_them_in_time_order():
    """``bayesmag run`` accepted rows out of time order whatever the job: a time-block split then took scattered rows
    as a block (a random split in disguise), a thermal lag ran backwards. Now refused where something needs the
    order (the time-block split, a series model, an autocorrelation-aware covariance, the session model's AR(1));
    a random split of a plain model still accepts them."""
    from bayesmag._src.app.config import config_from_dict
    from bayesmag._src.app.job import build_model, time_order_reasons
    from bayesmag._src.core.data import check_time_order
    d = _recording(60)
    shuffled = CalibrationData(d.b_meas, d.temperature, d.b_ref, d.time[::-1].copy(), d.run)
    raw = lambda **k: config_from_dict({"data": {"source": "simulated"}, **k})  # noqa: E731
    for cfg in (raw(split={"kind": "time_blocks"}), raw(physics={"covariance": "ar1"}),
                raw(uq={"transfer": "hierarchical"}), raw(physics={"extra_terms": [{"name": "thermal_lag"}]})):
        reasons = time_order_reasons(cfg, build_model(cfg, d))
        with pytest.raises(DataError, match=r"not sorted within run .*Needed in time order by: the"):
            check_time_order(shuffled, reasons)
        check_time_order(d, reasons)                                       # sorted: fine
    plain = raw(split={"kind": "random"})
    check_time_order(shuffled, time_order_reasons(plain, build_model(plain, d)))


# --------------------------------------------------------------------------- 10. unidentifiable fits


@pytest.mark.parametrize("value", [0.0, 7.5])
def test_constant_field_axis_is_refused_naming_parameters(value):
    d = _recording(200)
    b = d.b_meas.copy()
    b[:, 1] = value
    with pytest.raises(DataError, match=r"cannot inform.*axis x, y, z: \[.*'S_y'.*\]"):
        fit_physics(CalibrationData(b, d.temperature, d.b_ref, d.time, d.run))


def test_nearly_collinear_but_identifiable_fit_is_kept():
    d = _recording(200)
    b = d.b_meas.copy()
    b[:, 1] = 7.5 + 1e-3 * np.random.default_rng(1).standard_normal(d.n)   # barely varying: poorly identified
    fit = fit_physics(CalibrationData(b, d.temperature, d.b_ref, d.time, d.run))
    assert (fit.std > 0).all() and np.isfinite(fit.std).all()
    J = np.column_stack([b, d.temperature, np.ones(d.n)])
    names, ratio = unidentifiable(J, ("a", "b", "c", "T", "1"))
    assert names == [] and RANK_RTOL < ratio < 1e-3


def test_batched_rank_check_agrees_with_unidentifiable_and_ignores_zeroed_rows():
    """fit_folds zeroes left-out rows and checks all folds with one batched SVD (rank_deficient): the
    verdict equals unidentifiable() on the kept rows alone, for a full-rank, a barely varying, a constant
    and a zero column."""
    from bayesmag._src.core.fit import rank_deficient
    d = _recording(200)
    rng = np.random.default_rng(3)
    keep = rng.random(d.n) < 0.7
    cases = []
    for col1 in (d.b_meas[:, 1], 7.5 + 1e-3 * rng.standard_normal(d.n), np.full(d.n, 7.5), np.zeros(d.n)):
        J = np.column_stack([d.b_meas[:, 0], col1, d.b_meas[:, 2], d.temperature, np.ones(d.n)])
        cases.append(J)
    batched = rank_deficient(np.stack([J * keep[:, None] for J in cases]))
    single = [bool(unidentifiable(J[keep], ("a", "b", "c", "T", "1"))[0]) for J in cases]
    assert batched.tolist() == single == [False, False, True, True]


@pytest.mark.realdata
def test_belsten_is_collinear_but_not_rank_deficient(belsten):
    from bayesmag import PhysicsModel, inputs_from_data
    J = np.asarray(PhysicsModel.paper().features(inputs_from_data(belsten)))
    names, ratio = unidentifiable(J, PhysicsModel.paper().param_names)
    assert names == [] and 5e-4 < ratio < 5e-3                 # measured 1.1e-3 at t0 = 0; threshold 1.5e-8
    fit_physics(belsten)                                       # not refused


# --------------------------------------------------------------------------- delimiters, apply units and columns


@pytest.mark.parametrize("delim", [";", "\t"])
def test_semicolon_and_tab_files_are_read(tmp_path, delim):
    d = _recording(30)
    p = _write(tmp_path / "a.csv", d)
    q = tmp_path / "b.csv"
    q.write_text(p.read_text().replace(",", delim))
    np.testing.assert_allclose(load_csv(q).b_meas, load_csv(p).b_meas)


def test_apply_column_mapping_and_units(tmp_path, model):
    d = _recording(40, seed=5)
    canon = _write(tmp_path / "canon.csv", d)
    other = tmp_path / "other.csv"
    rows = ["t;X;Y;Z;TK"] + [";".join(repr(float(v)) for v in (t, *(b * 1000), T + 273.15))
                             for t, b, T in zip(d.time, d.b_meas, d.temperature)]
    other.write_text("\n".join(rows) + "\n")
    assert main(["apply", "--model", str(model), "--data", str(canon), "--out", str(tmp_path / "a.csv"),
                 "--no-progress"]) == 0
    assert main(["apply", "--model", str(model), "--data", str(other), "--out", str(tmp_path / "b.csv"), "--no-progress",
                 "--columns", "time=t,bx_meas=X,by_meas=Y,bz_meas=Z,temperature=TK", "--field-unit", "nT",
                 "--temperature-unit", "K"]) == 0
    a = np.delete(np.loadtxt(tmp_path / "a.csv", delimiter=",", skiprows=1), 1, axis=1)   # all but 'run'
    b = np.delete(np.loadtxt(tmp_path / "b.csv", delimiter=",", skiprows=1), 1, axis=1)
    np.testing.assert_allclose(b, a, rtol=1e-7, atol=1e-9)      # CSV keeps 8 significant digits
    assert main(["apply", "--model", str(model), "--data", str(other), "--out", str(tmp_path / "c.csv")]) == 2


# --------------------------------------------------------------------------- the bad-input table


def _data_case(mutate):
    def make(tmp):
        d = _recording()
        b, t, ref, time = d.b_meas.copy(), d.temperature.copy(), d.b_ref.copy(), d.time.copy()
        mutate(b, t, ref, time)
        return _write(tmp / "rec.csv", d, b_meas=b, temperature=t, b_ref=ref, time=time)
    return make


def _text_case(text: str | bytes):
    def make(tmp):
        p = tmp / "rec.csv"
        (p.write_bytes if isinstance(text, bytes) else p.write_text)(text)
        return p
    return make


def _edit_text(edit):
    def make(tmp):
        p = _write(tmp / "rec.csv")
        p.write_text(edit(p.read_text()))
        return p
    return make


def _nan_row8(b, t, ref, time):
    b[7, 0] = np.nan


def _huge_row8(b, t, ref, time):
    b[7, 1] = 1e300


def _nano(b, t, ref, time):
    b *= 1000
    ref *= 1000


def _milli(b, t, ref, time):
    b /= 1000
    ref /= 1000


def _kelvin(b, t, ref, time):
    t += 273.15


def _dup_far(b, t, ref, time):
    time[30] = time[3]


def _dup_adjacent(b, t, ref, time):
    time[11] = time[10]


def _unsorted(b, t, ref, time):
    time[[10, 11]] = time[[11, 10]]


def _cell_abc(text):
    lines = text.splitlines()
    parts = lines[3].split(",")
    parts[3] = "abc"
    lines[3] = ",".join(parts)
    return "\n".join(lines) + "\n"


HEADER = "time,run,bx_meas,by_meas,bz_meas,temperature,bx_ref,by_ref,bz_ref"
# name -> (make data file, {command: regex on stderr}); a command missing from the dict accepts the input.
DATA_CASES = {
    "nan_value": (_data_case(_nan_row8), {"run": r"'bx_meas'.*row\(s\) 8", "discover": r"'bx_meas'.*row\(s\) 8"}),
    "1e300_value": (_data_case(_huge_row8), {c: r"'by_meas'.* 1e\+300 at data row\(s\) 8"
                                             for c in ("run", "apply", "discover")}),
    "field_in_nT": (_data_case(_nano), {c: "looks like nT" for c in ("run", "apply", "discover")}),
    "field_in_mT": (_data_case(_milli), {c: "looks like mT" for c in ("run", "discover")}),
    "kelvin": (_data_case(_kelvin), {c: "'temperature'.*kelvin" for c in ("run", "apply", "discover")}),
    "duplicate_times_far_apart": (_data_case(_dup_far), {"run": r"duplicated timestamps within run 1 at data row\(s\) 31",
                                                         "discover": r"not sorted within run 1: data row 31 "}),
    # discover accepted this (sorted, one stamp twice) until the fifth pass's found-not-fixed list was worked off
    "duplicate_times_adjacent": (_data_case(_dup_adjacent), {c: r"duplicated timestamps within run 1 at data row\(s\) 12"
                                                             for c in ("run", "discover")}),
    "rows_not_sorted": (_data_case(_unsorted), {"discover": r"not sorted within run 1: data row 12 "}),
    "missing_column": (_edit_text(lambda s: s.replace("bz_meas", "bz")),
                       {c: "no column 'bz_meas'" for c in ("run", "apply", "discover")}),
    "not_a_number": (_edit_text(_cell_abc), {c: r"data row 3, column 'by_meas' holds 'abc'"
                                             for c in ("run", "apply", "discover")}),
    "ambiguous_delimiter": (_text_case("a,b;c\n1,2;3\n"), {c: "cannot tell the delimiter: both comma and semicolon"
                                                         for c in ("run", "apply", "discover")}),
    "decimal_commas": (_text_case(HEADER.replace(",", ";") + "\n" + "0;1;1,5;2;3;20;1;2;3\n"),
                       {c: "Decimal commas" for c in ("run", "apply", "discover")}),
    "binary_file": (_text_case(bytes(range(256)) * 4), {c: "not a text file" for c in ("run", "apply", "discover")}),
    "empty_file": (_text_case(""), {c: "is empty" for c in ("run", "apply", "discover")}),
}
CONFIG_CASES = {          # --set overrides / config files for the commands that read a config
    "t0_nan": (["physics.t0=nan"], "'physics.t0' = nan must be finite"),
    "chunk_size_0": (["uq.chunk_size=0"], "'uq.chunk_size' = 0 must be at least 1"),
    "seed_negative": (["uq.seed=-1"], "'uq.seed' = -1 must be at least 0"),
    "n_blocks_0": (["split.n_blocks=0"], "'split.n_blocks' = 0 must be at least 1"),
    "unknown_key": (["uq.n_param=3"], "Unknown config key 'uq.n_param'"),
}


def _argv(cmd: str, tmp: Path, data: Path, model: Path) -> list[str]:
    out = tmp / "out"
    if cmd == "run":
        return ["run", str(_config(tmp, data)), "--out", str(out), "--no-progress"]
    if cmd == "apply":
        return ["apply", "--model", str(model), "--data", str(data), "--out", str(tmp / "out.csv"), "--no-progress"]
    return ["discover", "--data", str(data), "--out", str(out), "--no-figures"]


@pytest.mark.parametrize("cmd", ["run", "apply", "discover"])
@pytest.mark.parametrize("case", sorted(DATA_CASES))
def test_bad_data_table(tmp_path, capsys, model, monkeypatch, case, cmd):
    make, expect = DATA_CASES[case]
    data = make(tmp_path)
    if cmd not in expect:
        pytest.skip(f"{cmd} accepts {case} (covered elsewhere)")
    rc = main(_argv(cmd, tmp_path, data, model))
    err = _err(capsys)
    assert rc == 2, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "error:" in lines[0], err
    assert re.search(expect[cmd], lines[0]), lines[0]
    assert not (tmp_path / "out").exists() and not (tmp_path / "out.csv").exists()


@pytest.mark.parametrize("cmd", ["run", "discover"])
@pytest.mark.parametrize("case", sorted(CONFIG_CASES))
def test_bad_config_table(tmp_path, capsys, case, cmd):
    over, match = CONFIG_CASES[case]
    rec = _write(tmp_path / "rec.csv")
    cfg = _config(tmp_path, rec)
    argv = [cmd, str(cfg), "--out", str(tmp_path / "out")] + [a for o in over for a in ("--set", o)]
    assert main(argv) == 2
    err = _err(capsys)
    assert match in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("cmd", ["run", "discover"])
@pytest.mark.parametrize("kind", ["binary", "folder"])
def test_config_that_is_not_a_text_file(tmp_path, capsys, cmd, kind):
    cfg = tmp_path / "cfg.toml"
    if kind == "binary":
        cfg.write_bytes(bytes(range(256)))
    else:
        cfg.mkdir()
    assert main([cmd, str(cfg), "--out", str(tmp_path / "out")]) == 2
    assert ("not a text file" if kind == "binary" else "is a folder") in _err(capsys)


@pytest.mark.parametrize("cmd", ["run", "discover"])
def test_good_input_control(tmp_path, capsys, model, cmd):
    """The same commands on the untouched recording succeed: the table fails only for its defect."""
    data = _write(tmp_path / "rec.csv")
    assert main(_argv(cmd, tmp_path, data, model)) == 0
    assert marker_status(tmp_path / "out")["complete"]


def test_discover_refuses_foreign_out_before_searching(tmp_path, capsys, monkeypatch):
    import bayesmag._src.pipeline.discover as disc
    monkeypatch.setattr(disc, "discover", lambda *a, **k: (_ for _ in ()).throw(AssertionError("searched")))
    data = _write(tmp_path / "rec.csv")
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "notes.txt").write_text("mine")
    assert main(["discover", "--data", str(data), "--out", str(tmp_path / "out")]) == 2
    assert "did not write" in _err(capsys) and (tmp_path / "out" / "notes.txt").read_text() == "mine"


def test_apply_good_input_control(tmp_path, model):
    data = _write(tmp_path / "rec.csv")
    assert main(_argv("apply", tmp_path, data, model)) == 0
    out = np.loadtxt(tmp_path / "out.csv", delimiter=",", skiprows=1)
    assert out.shape[0] == 200 and (out[:, -1] == 1).all()
