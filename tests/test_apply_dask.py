"""bayesmag apply on Dask (app/apply_dask.py): a 2-worker local cluster on a small dataset equals the in-process
apply row for row; bad input is one line naming the partition, the file and the row; nothing is overwritten."""

import numpy as np
import pandas as pd
import pytest

pytest.importorskip("dask")
pytest.importorskip("distributed")
pytest.importorskip("pyarrow")

from bayesmag._src.app.apply import apply_calibration  # noqa: E402
from bayesmag._src.app.apply_dask import OUTPUT_COLUMNS, apply_dask, list_pieces  # noqa: E402
from bayesmag._src.app.cli import main  # noqa: E402
from bayesmag._src.core.data import DataError  # noqa: E402
from bayesmag._src.core.frames import to_frame  # noqa: E402


@pytest.fixture(scope="module")
def cal_dir(tmp_path_factory):
    """A calibration (physics, transfer sd) fitted on one simulated recording, saved as `bayesmag run` saves it."""
    from bayesmag._src.app.artifact import save_calibration
    from bayesmag._src.core.domain import Domain
    from bayesmag._src.core.fit import fit_physics
    from bayesmag._src.core.physics import PhysicsModel
    from bayesmag._src.core.physics_uq import estimate_input_noise
    from bayesmag._src.core.predictor import Predictor, UQOptions
    from bayesmag._src.core.simulate import simulate
    d = simulate(2000, design="campaign", seed=11, noise_sd=0.05)
    fit = fit_physics(d, PhysicsModel.paper(t0=25.0))
    pred = Predictor(fit=fit, sigma_in=estimate_input_noise(d), residual_sd=np.full(3, 0.01),
                     transfer_sd=np.full(3, 0.02), domain=Domain.from_data(d), uq=UQOptions(method="analytic"))
    out = tmp_path_factory.mktemp("cal")
    save_calibration(out, pred, config={}, level=0.95)
    return out


@pytest.fixture(scope="module")
def archive(tmp_path_factory):
    """3 Parquet files of 3 row groups each and the same rows as 3 CSV files and as one CSV."""
    from bayesmag._src.core.simulate import simulate
    root = tmp_path_factory.mktemp("archive")
    df = to_frame(simulate(2400, design="campaign", seed=12, noise_sd=0.05))
    (root / "pq").mkdir()
    (root / "csv").mkdir()
    for k in range(3):
        part = df.iloc[k * 800:(k + 1) * 800]
        part.to_parquet(root / "pq" / f"day{k}.parquet", row_group_size=300, index=False)
        part.to_csv(root / "csv" / f"day{k}.csv", index=False)
    df.to_csv(root / "all.csv", index=False)
    return root


@pytest.fixture(scope="module")
def cluster():
    import dask
    from distributed import LocalCluster
    with dask.config.set({"distributed.worker.memory.target": False, "distributed.worker.memory.spill": False,
                          "distributed.worker.memory.pause": False}):
        with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                          memory_limit="2GB") as c:
            yield c.scheduler_address


@pytest.fixture(scope="module")
def in_process(cal_dir, archive):
    apply_calibration(cal_dir, archive / "all.csv", archive / "ref.csv")
    return pd.read_csv(archive / "ref.csv")


@pytest.mark.parametrize("source, blocksize", [("pq", 0), ("csv/*.csv", 9000)])
@pytest.mark.extended
def test_dask_apply_equals_in_process_apply(cal_dir, archive, cluster, in_process, tmp_path, source, blocksize):
    kw = {"blocksize": blocksize} if blocksize else {}
    s = apply_dask(cal_dir, str(archive / source), tmp_path / "out", scheduler=cluster, **kw)
    n_parts = len(list_pieces(str(archive / source), **kw))
    assert n_parts >= 9 and s["n_partitions"] == n_parts
    assert s["n_rows"] == s["n_rows_in"] == 2400 and s["n_valid"] == 2400
    out = pd.read_parquet(tmp_path / "out")                       # the parts, read back in input order
    assert list(out.columns) == list(in_process.columns)         # same columns as the CSV of the in-process apply
    assert {c.split("_", 1)[1] for c in out.columns if c[:2] in ("x_", "y_", "z_")} <= set(OUTPUT_COLUMNS)
    for c in in_process.columns:
        np.testing.assert_allclose(out[c].to_numpy(float), in_process[c].to_numpy(float), rtol=1e-7, atol=1e-6,
                                   err_msg=c)
    assert s["metrics"]["coverage"]["x"] > 0.9


@pytest.mark.parametrize("fmt", ["parquet", "csv"])
@pytest.mark.extended
def test_rate_flags_at_partition_boundaries_equal_the_whole_file(cal_dir, cluster, tmp_path, fmt):
    """Field spikes make the neighbours' rates out of domain; with many partitions, rows at the boundaries still get
    the whole-file apply's flags (each partition is predicted with the file rows just before and after it)."""
    from bayesmag._src.core.simulate import simulate
    df = to_frame(simulate(1200, design="campaign", seed=13, noise_sd=0.05))
    spikes = np.random.default_rng(0).choice(1200, 100, replace=False)
    df.loc[spikes, "bx_meas"] += 250.0
    df.to_csv(tmp_path / "all.csv", index=False)
    (tmp_path / "in").mkdir()
    if fmt == "parquet":
        df.to_parquet(tmp_path / "in" / "a.parquet", row_group_size=37, index=False)
        s = apply_dask(cal_dir, str(tmp_path / "in"), tmp_path / "out", scheduler=cluster)
    else:
        df.to_csv(tmp_path / "in" / "a.csv", index=False)
        s = apply_dask(cal_dir, str(tmp_path / "in" / "*.csv"), tmp_path / "out", scheduler=cluster, blocksize=2500)
    assert s["n_partitions"] > 30
    apply_calibration(cal_dir, tmp_path / "all.csv", tmp_path / "ref.csv")
    ref, out = pd.read_csv(tmp_path / "ref.csv"), pd.read_parquet(tmp_path / "out")
    rate_bits = (ref["in_domain_reason"].to_numpy() & 12) != 0
    assert rate_bits.sum() > 50                                   # the spikes do raise rate flags
    np.testing.assert_array_equal(out["in_domain_reason"], ref["in_domain_reason"])
    np.testing.assert_array_equal(out["in_domain"], ref["in_domain"].astype(bool))


def test_bad_csv_value_names_partition_file_and_row(cal_dir, archive, cluster, tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    df = pd.read_csv(archive / "csv" / "day0.csv").astype(object)
    df.loc[637, "by_meas"] = "12..5"
    df.to_csv(src / "a.csv", index=False)
    with pytest.raises(DataError) as e:
        apply_dask(cal_dir, str(src / "*.csv"), tmp_path / "out", scheduler=cluster, blocksize=20_000)
    msg = str(e.value)
    assert "partition " in msg and "a.csv" in msg and "'by_meas'" in msg and "'12..5'" in msg and "\n" not in msg
    assert "data row 638 of the file" in msg
    assert not (tmp_path / "out").exists()                       # nothing half-written


def test_absurd_parquet_value_names_row(cal_dir, archive, cluster, tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    df = pd.read_parquet(archive / "pq" / "day1.parquet")
    df.loc[df.index[450], "temperature"] = 1e9
    df.to_parquet(src / "b.parquet", row_group_size=300, index=False)
    with pytest.raises(DataError) as e:
        apply_dask(cal_dir, str(src), tmp_path / "out", scheduler=cluster)
    msg = str(e.value)
    assert "partition 1: " in msg and "b.parquet (row group 1)" in msg and "its row 1 is data row 301 of the file" in msg
    assert "row(s) 151" in msg and "temperature" in msg and "1e+09" in msg


def test_each_apply_scatters_the_calibration_under_its_own_key(cal_dir, archive, cluster, tmp_path, monkeypatch):
    """Back-to-back applies of one calibration on one running cluster (as these tests do) must not share the scattered
    key: the first client's release of a content-hashed key can reach the scheduler after the second client's scatter
    of the same key, and the data is forgotten (dask/distributed#8576) -- the intermittent failure of this file."""
    import distributed
    keys = []
    scatter = distributed.Client.scatter

    def spy(self, data, *a, **kw):
        fut = scatter(self, data, *a, **kw)
        keys.append(fut.key)
        return fut
    monkeypatch.setattr(distributed.Client, "scatter", spy)
    for k in range(3):
        s = apply_dask(cal_dir, str(archive / "pq"), tmp_path / f"out{k}", scheduler=cluster)
        assert s["n_rows"] == 2400
    assert len(keys) == 3 and len(set(keys)) == 3


@pytest.mark.parametrize("where", ["input", "model", "file"])
def test_nothing_overwritten(cal_dir, archive, tmp_path, where):
    out = {"input": archive / "pq", "model": cal_dir / "sub", "file": tmp_path / "x.parquet"}[where]
    with pytest.raises(DataError, match="--out"):
        apply_dask(cal_dir, str(archive / "pq"), out)


def test_cli_routes_archives_to_dask(cal_dir, archive, cluster, tmp_path, capsys):
    """`bayesmag apply` on a folder runs on Dask (here the test cluster); its errors are one line, exit status 2."""
    rc = main(["apply", "--model", str(cal_dir), "--data", str(archive / "pq"), "--out", str(tmp_path / "o"),
               "--no-progress", "--scheduler", cluster])
    out = capsys.readouterr()
    assert rc == 0 and "2400 of 2400 rows in 9 partitions" in out.out
    assert len(pd.read_parquet(tmp_path / "o")) == 2400
    assert main(["apply", "--model", str(cal_dir), "--data", str(tmp_path / "nothing*.csv"), "--out",
                 str(tmp_path / "o2")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("bayesmag: error: --data") and len(err.splitlines()) == 1


def test_cli_dask_progress_only_on_a_terminal(cal_dir, archive, cluster, tmp_path, capsys):
    """Without --no-progress, Dask's text progress bar (carriage returns) is still off when output is not a
    terminal (issue 26 item 18: logs stay free of carriage-return noise)."""
    rc = main(["apply", "--model", str(cal_dir), "--data", str(archive / "pq"), "--out", str(tmp_path / "o"),
               "--scheduler", cluster])
    out = capsys.readouterr()
    assert rc == 0 and "2400 of 2400 rows" in out.out
    assert "\r" not in out.out and "\r" not in out.err


@pytest.mark.slow
def test_cli_default_local_cluster(cal_dir, archive, tmp_path, capsys):
    """Without --scheduler, a local cluster of --workers processes is started and closed (slow: process start-up)."""
    rc = main(["apply", "--model", str(cal_dir), "--data", str(archive / "csv" / "*.csv"), "--out",
               str(tmp_path / "o"), "--no-progress", "--workers", "2", "--blocksize-mb", "0.02"])
    assert rc == 0 and "2400 of 2400 rows" in capsys.readouterr().out


def _job(tmp_path, data, extra):
    """A calibration with one catalogue term ``extra`` fitted on ``data``, saved as `bayesmag run` saves it."""
    from bayesmag._src.app.artifact import save_calibration
    from bayesmag._src.core.catalogue import make_extra
    from bayesmag._src.core.domain import Domain
    from bayesmag._src.core.fit import fit_physics
    from bayesmag._src.core.physics import PhysicsModel
    from bayesmag._src.core.physics_uq import estimate_input_noise
    from bayesmag._src.core.predictor import Predictor, UQOptions
    t0 = float(np.mean(data.temperature))
    fit = fit_physics(data, PhysicsModel.paper(t0=t0, extra=(make_extra(extra, t0=t0),)))
    pred = Predictor(fit=fit, sigma_in=estimate_input_noise(data), residual_sd=np.full(3, 0.01),
                     transfer_sd=np.full(3, 0.02), domain=Domain.from_data(data), uq=UQOptions(method="psqmc"))
    (tmp_path / "cal").mkdir()
    save_calibration(tmp_path / "cal", pred, config={}, level=0.95)
    return tmp_path / "cal"


@pytest.fixture(scope="module")
def hysteresis_cal(tmp_path_factory):
    import bayesmag
    train = bayesmag.simulate.simulate(1200, design="campaign", seed=1, noise_sd=0.05)
    return _job(tmp_path_factory.mktemp("hyst"), train, {"name": "hysteresis", "axis": "x", "threshold": 20.0})


@pytest.mark.parametrize("case", ["hysteresis", "thermal_lag"])
@pytest.mark.extended
def test_rows_that_depend_on_neighbours_equal_the_whole_file(cluster, tmp_path, hysteresis_cal, case):
    """A hysteresis state (set by earlier rows) and a thermal lag (remembering about 45 tau of rows on each side)
    span partitions: each partition is predicted with the neighbouring partitions these need, so 100-row (250 for
    the lag, whose 45 tau reach past the file) row groups give the whole-file apply's numbers (to 1e-9). Before,
    every partition restarted both as at a run start (the lag: up to 0.6 uT apart at the boundaries)."""
    import bayesmag
    from bayesmag._src.app.artifact import load
    if case == "hysteresis":
        new = bayesmag.simulate.simulate(2400, design="campaign", seed=5, noise_sd=0.05)
        cal_dir = hysteresis_cal
    else:
        from chamber_campaigns import campaign
        train, _ = campaign("lag_first_order", seed=2, n=3000)
        new, _ = campaign("lag_first_order", seed=3, n=3000)
        cal_dir = _job(tmp_path, train, {"name": "thermal_lag", "tau0": 60.0})
    model = load(cal_dir).model
    assert model.has_history if case == "hysteresis" else model.transforms
    df = to_frame(new)
    (tmp_path / "in").mkdir()
    df.to_parquet(tmp_path / "in" / "a.parquet", row_group_size=100 if case == "hysteresis" else 250, index=False)
    kw = {"method": "psqmc", "n_params": 40, "n_qmc": 64}
    s = apply_dask(cal_dir, str(tmp_path / "in"), tmp_path / "out", scheduler=cluster, **kw)
    assert s["n_partitions"] >= 12 and not [w for w in s["warnings"] if "hysteresis" in w]
    ref, out = load(cal_dir).predict(new, **kw), pd.read_parquet(tmp_path / "out")
    for k in ("calibrated", "total", "lower", "upper"):
        got = out[[f"{ax}_{k}" for ax in "xyz"]].to_numpy(float)
        np.testing.assert_allclose(got, ref[k], rtol=1e-9, atol=1e-12, err_msg=k)
    np.testing.assert_array_equal(out["in_domain"], ref["in_domain"])


def test_an_unset_hysteresis_state_is_a_warning(hysteresis_cal, tmp_path, monkeypatch):
    """Where no earlier partition within reach sets the state (the field never crosses the threshold), the partition
    is calibrated with the state of the partitions read, and the summary says so; a partition whose file start is
    within reach needs no warning."""
    import bayesmag
    from bayesmag._src.app import apply_dask as A
    from bayesmag._src.app.artifact import load
    monkeypatch.setattr(A, "MAX_HISTORY_PIECES", 3)
    d = bayesmag.simulate.simulate(600, design="campaign", seed=5, noise_sd=0.05)
    df = to_frame(d)
    df["bx_meas"] = 5.0 * np.sin(np.arange(600) / 20.0)          # never beyond the 20 uT threshold
    df["run"] = 0                                                 # one run: no run start sets it either
    df.to_parquet(tmp_path / "a.parquet", row_group_size=50, index=False)
    pieces = A.list_pieces(str(tmp_path / "a.parquet"))
    cal = load(hysteresis_cal)
    opts = dict(columns=None, temperature_unit="C", field_unit="uT", level=0.95, method="auto", n_params=40,
                n_qmc=64, chunk_size=50_000, columns_out=["calibrated", "total", "lower", "upper"])
    far = A.calibrate_piece(pieces[10], 10, cal, opts, str(tmp_path), A._Pieces(pieces))
    near = A.calibrate_piece(pieces[2], 2, cal, opts, str(tmp_path), A._Pieces(pieces))
    assert "partition 10: the hysteresis state at its first row is not set by the 3 partitions" in far["warnings"][0]
    assert near["warnings"][0] == ""


@pytest.mark.extended
def test_a_hierarchical_calibration_keeps_its_row_wise_transfer_column(cluster, tmp_path):
    """The hierarchical session model's transfer sd depends on the row: the archive apply writes it as the
    in-process apply does (before, its columns were chosen from the saved constant transfer sd, which such a
    calibration has not, and x/y/z_transfer were missing); values as Calibration.predict's (1e-12)."""
    import bayesmag
    from bayesmag._src.app.artifact import load
    from bayesmag._src.app.config import config_from_dict
    raw = {"data": {"source": "simulated", "simulate": {"design": "campaign", "n": 1200, "seed": 1, "noise_sd": 0.05}},
           "split": {"kind": "time_blocks", "test_fraction": 0.2},
           "uq": {"method": "analytic", "transfer": "hierarchical"},
           "output": {"figures": False, "progress": False}}
    bayesmag.run_job(config_from_dict(raw), tmp_path / "cal")
    cal = load(tmp_path / "cal")
    assert cal.sessions is not None and cal.transfer_sd is None
    new = bayesmag.simulate.simulate(900, design="campaign", seed=6, noise_sd=0.05)
    (tmp_path / "in").mkdir()
    to_frame(new).to_parquet(tmp_path / "in" / "a.parquet", row_group_size=200, index=False)
    apply_dask(tmp_path / "cal", str(tmp_path / "in"), tmp_path / "out", scheduler=cluster)
    out, ref = pd.read_parquet(tmp_path / "out"), cal.predict(new)
    got = out[[f"{ax}_transfer" for ax in "xyz"]].to_numpy(float)
    assert np.ptp(ref["transfer"], axis=0).max() > 0                 # row-dependent
    np.testing.assert_allclose(got, ref["transfer"], rtol=1e-12, atol=1e-15)


def test_a_near_zero_field_partition_is_not_refused_but_an_all_small_file_is(cal_dir, cluster, tmp_path):
    """Fourth safety pass: the mT test ran per partition, so a file whose first row group is a near-zero-field run
    was refused ("looks like mT") though the in-process apply accepts it; now it runs on the whole recording, and a
    file small in every partition is still refused, with nothing written."""
    from bayesmag._src.core.simulate import simulate
    df = to_frame(simulate(600, design="campaign", seed=14, noise_sd=0.05))
    quiet = df.iloc[:200].copy()
    quiet[["bx_meas", "by_meas", "bz_meas"]] = quiet[["bx_meas", "by_meas", "bz_meas"]] * 0.001   # near zero field
    quiet[["bx_ref", "by_ref", "bz_ref"]] = quiet[["bx_ref", "by_ref", "bz_ref"]] * 0.001
    mixed = pd.concat([quiet, df.iloc[200:]], ignore_index=True)
    (tmp_path / "in").mkdir()
    mixed.to_parquet(tmp_path / "in" / "a.parquet", row_group_size=100, index=False)
    apply_calibration(cal_dir, tmp_path / "in" / "a.parquet", tmp_path / "ref.csv")        # accepted in process
    s = apply_dask(cal_dir, str(tmp_path / "in"), tmp_path / "out", scheduler=cluster)
    assert s["n_rows"] == 600 and s["n_partitions"] == 6
    (tmp_path / "in2").mkdir()
    quiet.to_parquet(tmp_path / "in2" / "b.parquet", row_group_size=100, index=False)
    with pytest.raises(DataError, match="every partition.*mT"):
        apply_dask(cal_dir, str(tmp_path / "in2"), tmp_path / "out2", scheduler=cluster)
    assert not (tmp_path / "out2").exists()


@pytest.mark.parametrize("fmt", ["parquet", "csv"])
def test_rows_not_calibrated_are_named_by_file_and_row(cal_dir, archive, cluster, tmp_path, fmt):
    """Blank (NaN) readings in later partitions of the second of two files: the warning names each row as the
    in-process apply does ("data row N", the header not counted), by file (it gave only a count)."""
    src = tmp_path / "in"
    src.mkdir()
    bad = [5, 377, 640]
    for k in (0, 1):
        df = pd.read_csv(archive / "csv" / f"day{k}.csv")
        if k == 1:
            df.loc[bad, "bz_meas"] = np.nan
        if fmt == "parquet":
            df.to_parquet(src / f"d{k}.parquet", row_group_size=300, index=False)
        else:
            df.to_csv(src / f"d{k}.csv", index=False)
    kw = {} if fmt == "parquet" else {"blocksize": 20_000}
    s = apply_dask(cal_dir, str(src if fmt == "parquet" else src / "*.csv"), tmp_path / "out", scheduler=cluster, **kw)
    assert s["n_partitions"] >= 4
    msg = next(w for w in s["warnings"] if "not calibrated" in w)
    ext = "parquet" if fmt == "parquet" else "csv"
    assert msg.startswith("3 row(s)")
    for r in bad:
        assert f"d1.{ext} data row {r + 1}" in msg, msg
    assert "d0." not in msg
    out = pd.read_parquet(tmp_path / "out")
    assert np.flatnonzero(~out["valid"].to_numpy()).tolist() == [800 + r for r in bad]


def test_a_declared_unit_that_misreads_some_files_is_said(cal_dir, archive, cluster, tmp_path):
    """Sixth outside pass: `--field-unit nT` on a file in uT gave calibrated values 1000x too small, every row
    marked in domain, exit 0 and no word (in process and in an archive of uT and nT files). The declared unit is
    still trusted (a shielded recording is genuinely weak), but the files it makes 50x off the training field are
    named."""
    s = apply_calibration(cal_dir, archive / "csv" / "day0.csv", tmp_path / "one.csv", field_unit="nT")
    assert any("read as 'nT' as declared" in w and "Check the declared field unit" in w for w in s["warnings"])
    (tmp_path / "mixed").mkdir()
    pd.read_parquet(archive / "pq" / "day0.parquet").to_parquet(tmp_path / "mixed" / "a.parquet", index=False)
    nt = pd.read_parquet(archive / "pq" / "day1.parquet")
    cols = ["bx_meas", "by_meas", "bz_meas", "bx_ref", "by_ref", "bz_ref"]
    nt[cols] = nt[cols] * 1000.0
    nt.to_parquet(tmp_path / "mixed" / "b.parquet", index=False)
    s = apply_dask(cal_dir, str(tmp_path / "mixed"), tmp_path / "out", scheduler=cluster, field_unit="nT")
    odd = [w for w in s["warnings"] if "declared --field-unit nT" in w]
    assert len(odd) == 1 and "a.parquet" in odd[0] and "b.parquet" not in odd[0]


def _session_pids(sid: int) -> list[int]:
    """Live processes of session ``sid`` (zombies not counted)."""
    import os
    pids = []
    for p in os.listdir("/proc"):
        if not p.isdigit():
            continue
        try:
            fields = open(f"/proc/{p}/stat").read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[3]) == sid and fields[0] != "Z":           # fields: state ppid pgrp session ...
            pids.append(int(p))
    return pids


def _workers(pid: int) -> list[int]:
    """The multiprocessing children of ``pid`` (a local cluster's worker processes)."""
    return [k for k in _session_pids(pid) if "spawn_main" in open(f"/proc/{k}/cmdline").read()]


@pytest.mark.extended
@pytest.mark.skipif(not __import__("pathlib").Path("/proc").is_dir(), reason="reads /proc")
def test_ctrl_c_of_a_local_cluster_apply_is_one_line_and_leaves_nothing(cal_dir, tmp_path):
    """Seventh outside pass: Ctrl-C of `bayesmag apply` on a local cluster printed the workers' KeyboardInterrupt
    tracebacks and the scheduler's 'Task exception was never retrieved' (36-80 lines) before the one line. The
    terminal's SIGINT to the whole process group, sent once the workers are computing: the one line, exit status
    130, no output folder, staging folder or lock, and no process of the command left (10-20 s: a cluster start)."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from bayesmag._src.core.simulate import simulate
    logs = tmp_path / "logs"
    logs.mkdir()
    df = to_frame(simulate(2400, design="campaign", seed=12, noise_sd=0.05))
    for k in range(16):
        df.to_csv(logs / f"day{k:02d}.csv", index=False)
    out = tmp_path / "out"
    env = {**os.environ, "MPLBACKEND": "Agg", "JAX_PLATFORMS": "cpu"}
    p = subprocess.Popen([sys.executable, "-m", "bayesmag", "apply", "--model", str(cal_dir), "--data",
                          str(logs / "*.csv"), "--out", str(out), "--workers", "2", "--uq", "psqmc", "--n-params",
                          "200", "--n-qmc", "512", "--no-progress"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True, env=env)
    try:
        deadline = time.monotonic() + 60
        while len(_workers(p.pid)) < 2 and p.poll() is None:      # the cluster's workers are starting
            assert time.monotonic() < deadline, "no worker process within 60 s"
            time.sleep(0.05)
        time.sleep(1.0)                                          # importing, or computing: both printed tracebacks
        assert p.poll() is None, p.communicate()[1].decode()
        t0 = time.monotonic()
        os.killpg(p.pid, signal.SIGINT)                          # what a terminal's Ctrl-C does
        _, stderr = p.communicate(timeout=30)
        took = time.monotonic() - t0
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    err = stderr.decode()
    assert p.returncode == 130, err
    assert err.splitlines() == ["bayesmag: interrupted by SIGINT; stopped without leaving a partial result."], err
    assert took < 2.0, took
    assert sorted(x.name for x in tmp_path.iterdir()) == ["logs"]       # no out/, staging folder or lock
    time.sleep(0.5)
    assert _session_pids(p.pid) == []                                   # no worker, nanny or tracker left


def test_the_dataset_carries_its_unit_file(cal_dir, archive, cluster, tmp_path):
    """The Dask apply's folder holds the in-process apply's unit file (`_bayesmag_apply.json`: a Parquet reader skips
    it), swapped in with the parts and listed in the folder's marker; pandas reads the dataset as before."""
    import json

    from bayesmag._src.app.outdir import MARKER
    s = apply_dask(cal_dir, str(archive / "pq"), tmp_path / "out", scheduler=cluster)
    side = tmp_path / "out" / "_bayesmag_apply.json"
    assert s["units_file"] == str(side)
    doc = json.loads(side.read_text())
    df = pd.read_parquet(tmp_path / "out")
    assert list(doc["units"]) == list(df.columns) and doc["units"]["x_total"] == "uT" and doc["units"]["time"] == "s"
    assert doc["rows"] == len(df) == 2400 and len(doc["files"]) == s["n_partitions"]
    assert sum(f["rows"] for f in doc["files"].values()) == 2400 and doc["calibration"]["kind"] == "vector"
    assert "_bayesmag_apply.json" in json.loads((tmp_path / "out" / MARKER).read_text())["files"]
    # seventh outside pass: the family of the intervals and the declared conversions; a folder has no one sha256
    assert doc["intervals"]["family"] == "gaussian" and doc["conversions"]["field_unit"] is None
    assert "data_sha256" not in doc and "not one file" in doc["data_sha256_not_recorded"]


def test_a_reference_in_another_unit_and_the_domain_reasons_are_said(cal_dir, archive, cluster, tmp_path):
    """As the in-process apply (seventh outside pass): with --field-unit nT, nT readings beside a uT reference are
    calibrated but not scored (the archive's metrics were the uT reference against the nT readings, no word), and the
    out-of-domain warning counts each reason."""
    (tmp_path / "mixed").mkdir()
    df = pd.read_parquet(archive / "pq" / "day0.parquet")
    df[["bx_meas", "by_meas", "bz_meas"]] *= 1000.0
    df.loc[:39, "temperature"] = 90.0                            # 40 rows far above the training temperatures
    df.to_parquet(tmp_path / "mixed" / "a.parquet", index=False)
    s = apply_dask(cal_dir, str(tmp_path / "mixed"), tmp_path / "out", scheduler=cluster, field_unit="nT")
    ref = [w for w in s["warnings"] if "reference columns" in w]
    assert "metrics" not in s and len(ref) == 1 and "calibrated values are unaffected" in ref[0], s["warnings"]
    dom = [w for w in s["warnings"] if "outside the calibration's training domain" in w]
    assert len(dom) == 1 and s["outside_domain_by_reason"]["temperature"] >= 40, s
    assert f"temperature {s['outside_domain_by_reason']['temperature']} (" in dom[0], dom
