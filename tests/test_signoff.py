"""What an engineer signs off on (issue 26): the certificate's identity, model, GUM rounding, transfer budget
and HTML rendering; field metrics (magnitude residual, heading error) against hand computations; the
figures that replace prediction-vs-reference plots; the NUTS trace's choice of parameters."""

import datetime
import hashlib
import json
import math
import re
from decimal import Decimal
from html.parser import HTMLParser

import numpy as np
import pytest
from scipy import stats

import bayesmag
from bayesmag._src.app.config import config_from_dict, to_toml
from bayesmag._src.app.report import (expanded_uncertainties, gum_format, gum_round, render_html,
                                      welch_satterthwaite)
from bayesmag._src.core import metrics as M


# --------------------------------------------------------------------------- GUM rounding (item 3)


@pytest.mark.parametrize("value, u, want", [
    (1.00213456, 4.90148e-05, ("1.002135", "0.000049")),
    (27.6234, 0.0123, ("27.623", "0.012")),
    (12.345, 0.996, ("12.3", "1.0")),                 # u rounds up to 1.0: the value follows to one decimal
    (-3.2e-05, 4.87e-07, ("-3.200e-05", "4.9e-07")),  # small numbers: scientific, same last decimal place
    (3.2475e-03, 9.7e-06, ("0.0032475", "0.0000097")),  # a thermal gain: fixed, as its neighbours in the table
    (123456.7, 12.3, ("123457", "12")),
    (0.00001, 0.02, ("0.000", "0.020")),              # no "-0.000"
    (2.5, 0.0, ("2.5", "0")),                         # no uncertainty: value to 6 significant figures
])
def test_gum_round_examples(value, u, want):
    assert gum_round(value, u) == want


@pytest.mark.parametrize("seed", range(5))
def test_gum_round_two_significant_figures_and_value_to_the_same_place(seed):
    r = np.random.default_rng(seed)
    for _ in range(200):
        u = 10 ** r.uniform(-9, 4) * r.uniform(1, 9.99)
        value = r.normal() * 10 ** r.uniform(-6, 5)
        vs, us = gum_round(value, u)
        place = math.floor(math.log10(u)) - 1                     # the decimal place of u's 2nd significant figure
        if round(u / 10.0**place) >= 100:                          # 9.96 -> 10: one place to the left
            place += 1
        step = 10.0**place
        nu_, nv = float(us) / step, float(vs) / step
        assert 10 <= round(nu_) <= 99 and abs(nu_ - round(nu_)) < 1e-6        # u: two significant figures ...
        assert abs(nv - round(nv)) < 1e-6 * max(1.0, abs(nv))                 # ... the value to the same place
        assert abs(float(us) - u) <= 0.5 * step * (1 + 1e-9)
        assert abs(float(vs) - value) <= 0.5 * step * (1 + 1e-9) + 1e-12 * abs(value)
    assert gum_format(1.00213456, 4.90148e-05, "uT") == "1.002135 ± 0.000049 uT"


# --------------------------------------------------------------------------- certificate of a run (items 1, 2, 4-6)


def _raw(tmp_path, **cert):
    from bayesmag._src.core.data import write_csv
    from bayesmag._src.core.simulate import simulate_from_config
    data = simulate_from_config({"design": "campaign", "n": 900, "seed": 2, "noise_sd": 0.05})
    path = tmp_path / "rec.csv"
    write_csv(data, path)
    return {"data": {"path": str(path)}, "split": {"kind": "time_blocks", "test_fraction": 0.2},
            "uq": {"method": "analytic"}, "physics": {"t0": "mean"}, "certificate": cert,
            "output": {"figures": True, "progress": False}}


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("signoff")
    raw = _raw(tmp, dut="Acme AMR-3 s/n 0042", reference="Fluxgate FG-1 s/n 7, cert. 2025-17")
    res = bayesmag.run_job(config_from_dict(raw), tmp / "run")
    return tmp / "run", raw, res


def test_certificate_identity(run):
    out, raw, res = run
    m = json.loads((out / "metrics.json").read_text())
    rec = m["certificate"]
    digest = hashlib.sha256(open(raw["data"]["path"], "rb").read()).hexdigest()
    assert rec["data_sha256"] == digest
    cid = hashlib.sha256((to_toml(res["config"].to_dict()) + digest).encode()).hexdigest()[:16]
    assert rec["calibration_id"] == cid and re.fullmatch(r"[0-9a-f]{16}", cid)
    when = datetime.datetime.fromisoformat(rec["date_utc"])
    assert when.utcoffset() == datetime.timedelta(0)
    assert abs((datetime.datetime.now(datetime.timezone.utc) - when).total_seconds()) < 3600
    text = (out / "report.md").read_text()
    for item in (f"| calibration ID | {cid} |", f"| bayesmag version | {bayesmag.__version__} |",
                 "| device under test | Acme AMR-3 s/n 0042 |",
                 "| reference instrument | Fluxgate FG-1 s/n 7, cert. 2025-17 |", f"`{digest}`"):
        assert item in text, item


def test_calibration_id_depends_on_config_and_data(tmp_path):
    from bayesmag._src.app.report import certificate_record
    raw = _raw(tmp_path, dut="a")
    data = bayesmag.load_csv(raw["data"]["path"])
    a = certificate_record(config_from_dict(raw), data)["calibration_id"]
    assert certificate_record(config_from_dict(raw), data)["calibration_id"] == a          # reproducible
    assert certificate_record(config_from_dict({**raw, "certificate": {"dut": "b"}}), data)["calibration_id"] != a


@pytest.mark.parametrize("cert, match", [({"dut": "two\nlines"}, "certificate.dut"),
                                         ({"reference": 3}, "certificate.reference"),
                                         ({"serial": "x"}, "certificate.serial"),
                                         ({"operator": "x" * 201}, "certificate.operator")])
def test_certificate_keys_are_validated_at_load(cert, match):
    with pytest.raises(bayesmag.ConfigError, match=match):
        config_from_dict({"data": {"source": "simulated"}, "certificate": cert})


def test_model_section_states_t0_and_s_o_with_u(run):
    out, _, _ = run
    params = json.loads((out / "params.json").read_text())
    text = (out / "report.md").read_text()
    t0 = params["model"]["terms"][0]["t0"]
    assert f"**T0 = {t0:.6g} C**" in text and "B_cal = (S + Ks (T - T0)) B_meas + O + Ko (T - T0)" in text
    rows = {ln.split("|")[1].strip(): [c.strip() for c in ln.strip().strip("|").split("|")[1:]]
            for ln in text.split("| S (1) |")[1].split("\n\n")[0].splitlines()[2:]}
    for i, a in enumerate("xyz"):
        for j, b in enumerate("xyz"):
            v, u = params["axes"][a]["values"][f"S_{b}"], params["axes"][a]["std"][f"S_{b}"]
            vs, us = rows[a][j].split(" ± ")
            assert float(us) == pytest.approx(u, rel=0.05) and len(us.lstrip("0.").replace(".", "")) == 2
            assert float(vs) == pytest.approx(v, abs=0.51 * 10 ** Decimal(us).as_tuple().exponent)
    o = params["axes"]["y"]["values"]["O"]
    assert f"| y | {gum_format(o, params['axes']['y']['std']['O'])} |" in text
    assert not re.search(r"\d\.\d{5,}e-0\d \|", text)              # no six-figure uncertainties anywhere


def test_transfer_term_gives_same_and_new_session_U():
    m = {"uq": {"level": 0.95, "mean_aleatoric": dict.fromkeys("xyz", 0.06), "residual_term": dict.fromkeys("xyz", 0.02),
                "mean_epistemic": dict.fromkeys("xyz", 0.01), "sigma_in_sd": {"bx": 0.05}, "sigma_in_source": "auto"},
         "split": {"n_train": 500}, "transfer": {"method": "leave_one_run_out", "sd": {"x": 0.05, "y": 0.0, "z": 0.1}}}
    params = {"n_rows": 500, "model": {"param_names": list("abcdefgh")}}
    ex = expanded_uncertainties(m, params)
    same = math.sqrt(0.06**2 + 0.02**2 + 0.01**2)
    nu_noise = 0.37 / (1 + 2 * (4 / 9 + 1 / 36)) * (500 - 2)      # report.MAD_EFFICIENCY x SECOND_DIFFERENCE_EFFICIENCY
    nu = welch_satterthwaite([0.06, 0.02, 0.01], [nu_noise, 492, 492])
    assert ex["same_session"]["x"]["U"] == pytest.approx(stats.t.ppf(0.975, nu) * same, rel=1e-12)
    for a, tau in (("x", 0.05), ("y", 0.0), ("z", 0.1)):
        uc = math.sqrt(same**2 + tau**2)
        nu_new = welch_satterthwaite([0.06, 0.02, 0.01, tau], [nu_noise, 492, 492, math.inf])
        assert ex["new_session"][a]["U"] == pytest.approx(stats.t.ppf(0.975, nu_new) * uc, rel=1e-12)
    assert ex["new_session"]["y"]["U"] == pytest.approx(ex["same_session"]["y"]["U"], rel=1e-12)


def test_report_budget_states_which_U_applies(run):
    out, _, _ = run
    text = (out / "report.md").read_text()
    m = json.loads((out / "metrics.json").read_text())
    row = next(ln for ln in text.splitlines() if ln.startswith("| transfer (between sessions"))
    assert [c.strip() for c in row.strip("|").split("|")][3:6] == [f"{m['transfer']['sd'][a]:.2g}" for a in "xyz"]
    assert "U same session" in text and "U new session" in text and "in the field" in text


@pytest.mark.parametrize("transfer, reason", [
    ({"method": "off", "sd": dict.fromkeys("xyz", 0.0)}, '[uq] transfer = "off"'),
    ({"method": "largest_offset_change", "sd": dict.fromkeys("xyz", 0.0)}, "one training run"),
    (None, "no transfer estimate")])
def test_no_new_session_U_without_a_transfer_term(run, transfer, reason):
    from bayesmag._src.app.report import transfer_missing, uncertainty_budget
    out, _, _ = run
    m = json.loads((out / "metrics.json").read_text())
    params = json.loads((out / "params.json").read_text())
    m2 = {**m, "transfer": transfer}
    assert reason in transfer_missing(m2) and transfer_missing(m) is None
    ex = expanded_uncertainties(m2, params)
    assert ex["new_session_missing"] == transfer_missing(m2)
    text = "\n".join(uncertainty_budget(m2, params))
    # not the same-session U relabelled: no new-session numbers, and the reason why
    assert "U = k u_c, new session" not in text and "**No U for a new session**" in text and reason in text
    assert "| **expanded uncertainty U, new session** | | | not stated | not stated | not stated |" in text
    same = "\n".join(uncertainty_budget(m, params))                   # with the term: both U, as before
    assert "U = k u_c, new session" in same and "No U for a new session" not in same
    # two runs give a (rough) nonzero run-to-run change: stated, not missing
    assert transfer_missing({"transfer": {"method": "largest_offset_change", "sd": {"x": 0.1, "y": 0, "z": 0}}}) is None


def test_exports_state_no_new_session_U_without_a_transfer_term(run, tmp_path):
    import shutil
    from bayesmag._src.app.export import export_run
    out, _, _ = run
    folder = tmp_path / "run"
    shutil.copytree(out, folder)
    m = json.loads((folder / "metrics.json").read_text())
    m["transfer"] = {**m["transfer"], "method": "off", "sd": dict.fromkeys("xyz", 0.0)}
    (folder / "metrics.json").write_text(json.dumps(m))
    path, _ = export_run(folder, "json", tmp_path / "cal.json")
    doc = json.loads(path.read_text())["expanded_uncertainty"]
    assert doc["new_session"] is None and "not estimated" in doc["applies"] and set(doc["same_session"]) == set("xyz")
    path, _ = export_run(folder, "c-header", tmp_path / "cal.h")
    header = path.read_text()
    assert "BAYESMAG_U_SAME_SESSION[3] = {" in header and "BAYESMAG_U_NEW_SESSION[3] =" not in header
    assert "/* No BAYESMAG_U_NEW_SESSION:" in header
    path, _ = export_run(out, "json", tmp_path / "with.json")                  # the run itself has the term
    assert set(json.loads(path.read_text())["expanded_uncertainty"]["new_session"]) == set("xyz")


class _Checker(HTMLParser):
    VOID = {"meta", "img", "br", "hr"}

    def __init__(self):
        super().__init__()
        self.stack, self.tags, self.imgs, self.cells = [], [], [], 0

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)
        if tag == "img":
            self.imgs.append(dict(attrs)["src"])
        if tag in ("td", "th"):
            self.cells += 1
        if tag not in self.VOID:
            self.stack.append(tag)

    def handle_endtag(self, tag):
        assert self.stack and self.stack.pop() == tag, f"unbalanced </{tag}>"


def test_report_html_has_the_same_content_and_embedded_figures(run):
    import base64
    out, _, _ = run
    md = (out / "report.md").read_text()
    page = (out / "report.html").read_text()
    chk = _Checker()
    chk.feed(page)
    assert chk.stack == []                                                   # every element closed
    figs = sorted(p.name for p in out.glob("*.png"))
    assert len(chk.imgs) == len(figs) >= 6
    for src, name in zip(chk.imgs, figs):
        assert src.startswith("data:image/png;base64,")
        assert base64.b64decode(src.split(",", 1)[1]) == (out / name).read_bytes()
    md_cells = sum(len(ln.strip().strip("|").split("|")) for ln in md.splitlines()
                   if ln.startswith("|") and not re.fullmatch(r"\|[-|: ]+\|?", ln.strip()))
    assert chk.cells == md_cells
    assert chk.tags.count("h2") == md.count("\n## ")
    for phrase in ("Uncertainty budget", "Acme AMR-3 s/n 0042", "U new session"):
        assert phrase in page
    assert "<script" not in page


def test_report_command_rewrites_both_renderings(run, capsys):
    from bayesmag._src.app.cli import main
    out, _, _ = run
    md, page = (out / "report.md").read_text(), (out / "report.html").read_text()
    (out / "report.md").unlink()
    (out / "report.html").unlink()
    assert main(["report", str(out)]) == 0
    # the same certificate from the run's files (its date is the run's, not the rewrite's), figures embedded
    assert (out / "report.md").read_text() == md and (out / "report.html").read_text() == page
    printed = capsys.readouterr().out
    assert "report.md" in printed and "report.html" in printed


def test_render_html_escapes_and_handles_missing_figures(tmp_path):
    page = render_html("# T\n\na <b> & `x<y`\n\n![f.png](f.png)\n", tmp_path)
    assert "a &lt;b&gt; &amp; <code>x&lt;y</code>" in page and "[figure f.png not found]" in page


def test_one_t0_recommendation(belsten):
    fit = bayesmag.fit_physics(belsten)
    note = next(n for n in fit.design_notes if "only in run(s) [6]" in n)
    assert '[physics] t0 = "mean"' in note and not re.search(r"t0 = \d", note)
    # with t0 already the training mean, the note does not tell the user to set it (it did)
    centred = bayesmag.fit_physics(belsten, bayesmag.PhysicsModel.paper(t0=float(np.mean(belsten.temperature))))
    note = next(n for n in centred.design_notes if "only in run(s) [6]" in n)
    assert "t0 =" not in note and note.endswith("Separating Ks_j needs temperature varied while field axis j is swept.")


# --------------------------------------------------------------------------- field metrics (item 12)


def test_heading_error_by_hand():
    # reference headings 0, 90, 200 and 330 degrees (x forward, y right: B = H (cos psi, -sin psi, .))
    psi = np.array([0.0, 90.0, 200.0, 330.0])
    H = 20.0
    ref = np.column_stack([H * np.cos(np.radians(psi)), -H * np.sin(np.radians(psi)), np.full(4, 40.0)])
    # calibrated headings off by +1.5, -2, +3 (wraps through 0 / 360 at 330 + 3 = 333: no wrap) and -179.5
    err = np.array([1.5, -2.0, 3.0, -179.5])
    p2 = psi + err
    cal = np.column_stack([H * np.cos(np.radians(p2)), -H * np.sin(np.radians(p2)), np.full(4, 40.0)])
    np.testing.assert_allclose(M.heading_deg(ref), psi, atol=1e-12)
    np.testing.assert_allclose(M.heading_error_deg(cal, ref), err, atol=1e-9)
    # wrap across north: 359 vs 1 degree is -2 / +2, not 358
    a = np.array([[np.cos(np.radians(359)), -np.sin(np.radians(359)), 0.0]]) * H
    b = np.array([[np.cos(np.radians(1)), -np.sin(np.radians(1)), 0.0]]) * H
    assert M.heading_error_deg(a, b)[0] == pytest.approx(-2.0) and M.heading_error_deg(b, a)[0] == pytest.approx(2.0)


def test_field_metrics_by_hand():
    r = np.random.default_rng(3)
    ref = r.uniform(-40, 40, (300, 3))
    ref[:10, :2] = 1.0                                     # horizontal 1.4 uT: no heading
    cal = ref * 1.01                                       # |B| off by 1 %, heading exact
    run = np.repeat([4, 7, 9], 100)
    f = M.field_metrics(cal, ref, run)
    dm = 0.01 * np.sqrt((ref**2).sum(1))
    assert f["magnitude"]["rms"] == pytest.approx(np.sqrt(np.mean(dm**2)), rel=1e-12)
    assert f["magnitude"]["mean"] == pytest.approx(dm.mean(), rel=1e-12)
    assert f["magnitude"]["per_run"]["7"]["max_abs"] == pytest.approx(dm[100:200].max(), rel=1e-12)
    weak = np.sqrt(ref[:, 0] ** 2 + ref[:, 1] ** 2) < 5.0
    assert weak[:10].all() and f["heading"]["max_abs"] < 1e-9 and f["heading"]["n_excluded"] == weak.sum()
    assert f["heading"]["n_rows"] == 300 - weak.sum() and f["heading"]["per_run"]["4"]["n_rows"] == 100 - weak[:100].sum()
    # rotate run 9 by 2 degrees about z: its heading error is -2 (the field turns the other way)
    c, s = np.cos(np.radians(2)), np.sin(np.radians(2))
    rot = ref.copy()
    rot[200:, :2] = ref[200:, :2] @ np.array([[c, s], [-s, c]]).T
    g = M.field_metrics(rot, ref, run)
    assert g["heading"]["per_run"]["9"]["rms"] == pytest.approx(2.0, rel=1e-9)
    assert g["heading"]["per_run"]["4"]["rms"] < 1e-9 and g["magnitude"]["max_abs"] < 1e-9


def test_field_metrics_in_metrics_json_and_report(run):
    out, _, _ = run
    m = json.loads((out / "metrics.json").read_text())
    rows = list(__import__("csv").DictReader(open(out / "predictions.csv")))
    ref = np.array([[float(r[f"{a}_reference"]) for a in "xyz"] for r in rows])
    pred = np.array([[float(r[f"{a}_predicted"]) for a in "xyz"] for r in rows])
    runs = np.array([int(r["run"]) for r in rows])
    h = np.degrees(np.arctan2(-pred[:, 1], pred[:, 0]) - np.arctan2(-ref[:, 1], ref[:, 0]))
    h = (h + 180) % 360 - 180
    keep = np.hypot(ref[:, 0], ref[:, 1]) >= 5.0
    assert m["field"]["physics"]["heading"]["rms"] == pytest.approx(np.sqrt(np.mean(h[keep] ** 2)), rel=1e-5)
    dm = np.linalg.norm(pred, axis=1) - np.linalg.norm(ref, axis=1)
    assert m["field"]["physics"]["magnitude"]["rms"] == pytest.approx(np.sqrt(np.mean(dm**2)), rel=1e-5)
    assert set(m["field"]["physics"]["heading"]["per_run"]) == {str(r) for r in np.unique(runs)}
    assert m["field"]["raw"]["heading"]["rms"] > 10 * m["field"]["physics"]["heading"]["rms"]
    text = (out / "report.md").read_text()
    assert "## Field metrics (test rows)" in text
    assert f"| physics | {m['field']['physics']['magnitude']['mean']:+.3g} |" in text


# --------------------------------------------------------------------------- figures (items 13-15)


def test_residual_interval_figure_counts_coverage(tmp_path, monkeypatch):
    import matplotlib.pyplot as plt
    from bayesmag._src.app import plots
    saved = []
    monkeypatch.setattr(plt.Figure, "savefig", lambda self, *a, **k: saved.append(self))
    monkeypatch.setattr(plt, "close", lambda fig=None: None)
    r = np.random.default_rng(0)
    ref = r.uniform(-50, 50, (1000, 3))
    pred = ref + 0.03 * r.standard_normal((1000, 3))
    half = np.array([0.0588, 0.03, 0.1])                    # x: 1.96 sd (95 %), y: 1 sd (68 %), z: 3.33 sd
    cov = plots.residual_interval_figure(tmp_path / "c.png", ref, pred, pred - half, pred + half, max_points=200)
    by_hand = [np.mean(np.abs(pred[:, a] - ref[:, a]) <= half[a]) for a in range(3)]
    assert cov == pytest.approx(np.mean(by_hand))
    fig = saved[0]
    for a, ax in enumerate(fig.axes):
        assert f"{by_hand[a]:.1%} covered" in ax.get_title()
        assert ax.get_ylabel() == f"calibrated - reference B{'xyz'[a]} (uT)"
        lim = ax.get_ylim()
        assert lim[1] - lim[0] < 1.0                        # error axes, not +-50 uT field axes


def test_time_figure_shows_train_and_test_from_the_run_start():
    from bayesmag._src.app import plots
    t = np.arange(40) * 0.5
    run = np.repeat([1, 2], 20)
    test_rows = np.r_[10:14, 30:34]                          # test blocks in the middle of each run
    train_rows = np.setdiff1d(np.arange(40), test_rows)
    res = np.zeros((40, 3))
    fig = plots.residuals_vs_time(t[test_rows], run[test_rows], res[test_rows], np.ones((8, 3)),
                                  train=(t[train_rows], run[train_rows], res[train_rows]))
    ax = fig.axes[1]                                         # run 2, x axis: run 2 starts at t = 10 s (a train row)
    xs = np.concatenate([c.get_offsets()[:, 0] for c in ax.collections if len(c.get_offsets())])
    assert xs.min() == pytest.approx(0.0) and xs.max() == pytest.approx(9.5)
    assert sum(len(c.get_offsets()) for c in ax.collections if c.get_label() == "train rows") == 16


@pytest.fixture
def saved_figures(monkeypatch):
    """The figures a plotting function saves, kept open instead of written."""
    import matplotlib.pyplot as plt
    saved = []
    monkeypatch.setattr(plt.Figure, "savefig", lambda self, *a, **k: saved.append(self))
    monkeypatch.setattr(plt, "close", lambda fig=None: None)
    return saved


def test_physics_calibration_curve_matches_the_metric(tmp_path, saved_figures):
    from bayesmag._src.app import plots
    from bayesmag.likelihoods import Gaussian
    saved = saved_figures
    r = np.random.default_rng(1)
    y = 1.3 * r.standard_normal((500, 3))
    dist = Gaussian(np.zeros((500, 3)), np.ones((500, 3)))   # too narrow: under-covers
    plots.calibration_curve_figure(tmp_path / "c.png", {"physics": M.pit(dist, y)})
    nominal, observed = M.calibration_curve(dist, y)
    line = saved[0].axes[2].lines[1]
    np.testing.assert_allclose(line.get_xdata(), nominal)
    np.testing.assert_allclose(line.get_ydata(), observed[:, 2])


def test_physics_pit_figure_is_the_histogram_of_the_predictive_cdf(tmp_path, saved_figures):
    from bayesmag._src.app import plots
    from bayesmag.likelihoods import Gaussian
    saved = saved_figures
    r = np.random.default_rng(2)
    y = 1.3 * r.standard_normal((800, 3))
    u = M.pit(Gaussian(np.zeros((800, 3)), np.ones((800, 3))), y)
    np.testing.assert_allclose(u, stats.norm.cdf(y), atol=1e-12)           # PIT = F(y), scipy's normal cdf
    plots.pit_figure(tmp_path / "p.png", {"physics": u})
    for a, ax in enumerate(saved[0].axes):
        heights = np.array([p.get_height() for p in ax.patches])
        want, _ = np.histogram(stats.norm.cdf(y[:, a]), bins=10, range=(0, 1), density=True)
        np.testing.assert_allclose(heights, want, rtol=1e-12)
        assert heights[0] > 1.3 and heights[-1] > 1.3 and heights[4] < 0.8     # too narrow: U-shaped


def test_job_draws_the_physics_calibration_and_pit(run):
    out, _, _ = run
    for f in ("calibration.png", "physics_calibration.png", "physics_pit.png", "physics_residuals_vs_time.png"):
        assert (out / f).stat().st_size > 10_000, f


# --------------------------------------------------------------------------- NUTS (item 16)


def test_trace_shows_the_worst_r_hat_parameters():
    import pandas as pd
    from bayesmag._src.app.nuts_plots import trace_parameters
    df = pd.DataFrame({"axis": list("xxxyyy") + ["x"], "parameter": ["S_x", "S_y", "O", "S_x", "Ko", "O", "sigma"],
                       "r_hat": [1.001, 1.09, 1.002, 1.03, 1.002, 1.2, 1.5],
                       "ess_bulk": [100.0, 900.0, 50.0, 800.0, 60.0, 700.0, 10.0],
                       "lm_sd": [1.0] * 6 + [np.nan]})
    top = trace_parameters(df, 3)
    # by R-hat, not by ESS (the lowest-ESS O/x and Ko/y are not the ones that make a verdict inconclusive);
    # the noise scale (no LM sd) is drawn separately
    assert list(zip(top.axis, top.parameter)) == [("y", "O"), ("x", "S_y"), ("y", "S_x")]
    tie = trace_parameters(df.assign(r_hat=1.0), 2)                       # ties: the lowest bulk ESS first
    assert list(tie.parameter) == ["O", "Ko"]


@pytest.mark.slow                      # ~35 s (NUTS compile); the job test in test_nuts.py checks the same quickly
def test_nuts_stage_warnings_once_and_not_as_python_warnings(tmp_path):
    import warnings
    from bayesmag._src.app.nuts_stage import check_nuts_config, run_nuts_stage
    from bayesmag._src.core.simulate import simulate_from_config
    train = simulate_from_config({"design": "campaign", "n": 120, "seed": 5, "noise_sd": 0.05})
    fit = bayesmag.fit_physics(train)
    cfg = config_from_dict({"data": {"source": "simulated"},
                            "nuts": {"enabled": True, "chains": 1, "warmup": 30, "draws": 30}})
    priors = check_nuts_config(cfg, fit.param_names)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = run_nuts_stage(cfg, fit, train, priors)
    assert [str(w.message) for w in caught if issubclass(w.category, (UserWarning, RuntimeWarning))] == []
    assert len(res.warnings) >= 1 and len(set(res.warnings)) == len(res.warnings)
    assert any("chain" in w for w in res.warnings)                       # one chain: R-hat cannot be judged


# --------------------------------------------------------------------------- finding your way (items 17, 18)


def test_every_config_key_has_a_unit_and_meaning():
    from bayesmag._src.app.config import Config
    from bayesmag._src.app.config_docs import KEY_DOCS, config_keys
    keys = [k for k, _ in config_keys(Config())]
    assert sorted(keys) == sorted(KEY_DOCS)                       # none missing, none stale
    assert all(meaning for _, meaning in KEY_DOCS.values())


def test_config_list_and_show(capsys):
    from pathlib import Path
    from bayesmag._src.app.cli import main, packaged_configs_dir
    assert main(["config", "list"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert [ln.split()[0] for ln in out] == sorted(p.stem for p in Path(packaged_configs_dir()).glob("*.toml"))
    assert main(["config", "show", "quickstart"]) == 0
    text = capsys.readouterr().out
    line = next(ln for ln in text.splitlines() if ln.startswith("split.kind "))
    assert '*"time_blocks"' in line and 'default "random"' in line              # changed from the default
    assert next(ln for ln in text.splitlines() if ln.startswith("uq.seed ")).split()[1] == "0"   # unchanged, no *
    assert "[C]" in next(ln for ln in text.splitlines() if ln.startswith("physics.t0 "))
    assert main(["config", "show", "no_such_config"]) == 2


def test_every_subcommand_help_has_a_description():
    from bayesmag._src.app.cli import build_parser
    sub = next(a for a in build_parser()._actions if a.__class__.__name__ == "_SubParsersAction")
    assert set(sub.choices) >= {"run", "apply", "study", "report", "export", "discover", "data", "config"}
    for name, sp in sub.choices.items():
        assert sp.description and len(sp.description) > 30, name
        assert sp.description.split()[0] in sp.format_help(), name
    # discover parses its own options: `bayesmag discover --help` prints that parser's description
    from bayesmag._src.app.discover_cli import build_parser as discover_parser
    assert len(discover_parser().description) > 60


def test_progress_bars_only_on_a_terminal(tmp_path, capsys, monkeypatch):
    import sys
    from bayesmag._src.app.cli import main
    cfg = tmp_path / "c.toml"
    cfg.write_text('[data]\nsource = "simulated"\n[data.simulate]\ndesign = "campaign"\nn = 600\nseed = 1\n'
                   '[split]\nkind = "time_blocks"\ntest_fraction = 0.2\n[physics]\nt0 = "mean"\n'
                   '[uq]\nmethod = "analytic"\ntransfer = "off"\n[output]\nfigures = false\n')
    from bayesmag._src.app import job
    real = job.run_job
    seen, results = [], []

    def recording_run_job(*a, progress=None, **k):
        seen.append(progress)
        results.append(real(*a, progress=progress, **k))
        return results[-1]

    monkeypatch.setattr(job, "run_job", recording_run_job)
    assert main(["run", str(cfg), "--out", str(tmp_path / "a")]) == 0    # one real run, stderr not a terminal
    out, err = capsys.readouterr()
    assert "\r" not in err and "physics UQ" not in err and seen == [False]
    f = results[0]["metrics"]["field"]["physics"]                        # item 12 on the command's summary too
    assert (f"  physics: heading error RMS {f['heading']['rms']:.3g} deg (max {f['heading']['max_abs']:.3g}), "
            f"|B| residual RMS {f['magnitude']['rms']:.3g} uT") in out
    # a job from Python, [output] progress = true (the default), stderr captured: no bars either
    from bayesmag._src.app.config import load_config
    assert load_config(cfg).output.progress is True
    real(load_config(cfg), tmp_path / "py")
    err = capsys.readouterr().err
    assert "\r" not in err and "physics UQ" not in err
    # on a terminal the job is left to [output] progress (default on: bars drawn), unless --no-progress;
    # the wiring only (a third job would take as long again): the job returns the first run's result
    monkeypatch.setattr(job, "run_job", lambda *a, progress=None, **k: seen.append(progress) or results[0])
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True, raising=False)
    assert main(["run", str(cfg), "--out", str(tmp_path / "b")]) == 0
    assert main(["run", str(cfg), "--out", str(tmp_path / "d"), "--no-progress"]) == 0
    assert seen == [False, None, False]


# --------------------------------------------------------------------------- the walkthrough notebook (item 19)


def test_notebook_walkthrough_runs_on_the_real_recordings(belsten, tmp_path, monkeypatch, capsys):
    """examples/signoff_notebook.py (jupytext percent format) end to end: pandas load, job and Calibrator fit
    (the same parameters), certificate numbers and figures, PX4 export; its rows are the loader's rows."""
    import runpy
    from pathlib import Path
    monkeypatch.setenv("BAYESMAG_EXAMPLE_OUT", str(tmp_path / "nb"))
    ns = runpy.run_path(str(Path(__file__).parents[1] / "examples" / "signoff_notebook.py"), run_name="notebook")
    df = ns["df"]
    np.testing.assert_allclose(df[["bx_meas", "by_meas", "bz_meas"]].to_numpy(), belsten.b_meas)
    np.testing.assert_array_equal(df["run"].to_numpy(), belsten.run)                 # same campaigns as load_belsten
    np.testing.assert_allclose(df["time"].to_numpy(), belsten.time, atol=1e-9)
    run_dir = ns["run_dir"]
    assert (run_dir / "report.html").exists() and (run_dir / "calibration.params").exists()
    assert "Honeywell HMC1053" in (run_dir / "report.md").read_text()
    out = capsys.readouterr().out
    assert "U new_session" in out and "heading error RMS" in out and "CAL_MAG0_XOFF" in out
    assert all(ns["m"]["physics"]["rmse"][a] < 0.1 for a in "xyz")
    # the Calibrator (no files) fits the job's calibration: same rows held out, same parameters and scores
    assert ns["largest"] < 1e-12 and len(ns["cal"].params_) == 24
    for a in "xyz":
        assert ns["cal"].metrics_["physics"]["rmse"][a] == pytest.approx(ns["m"]["physics"]["rmse"][a], rel=1e-9)


@pytest.mark.filterwarnings("ignore:Residual network:bayesmag.CalibrationWarning")
@pytest.mark.extended
def test_a_hybrid_runs_certificate_states_the_U_of_the_predictor_apply_uses(tmp_path):
    """Sixth outside pass: on a hybrid run the certificate's U was the physics model's (y: 0.91 uT same session)
    while `apply` delivers the hybrid's intervals (half-width 0.22 uT). Now U same / new session are the hybrid
    predictor's -- checked against its own intervals in predictions.csv (Gaussian: half-width 1.96 x total; the
    budget's root-mean-square parts against the rows' mean: within 15 %) -- and the physics model alone, what the
    firmware exports hold, keeps its own U (the exports state that one)."""
    import pandas as pd

    from bayesmag._src.app.config import load_config
    from bayesmag._src.app.export import run_uncertainty

    cfg = load_config("quickstart", ['data.simulate.n=2400', 'network.max_epochs=40', 'network.mc_passes=20',
                                     'uq.n_params=100', 'uq.n_qmc=128', 'output.figures=false',
                                     'output.progress=false'])
    out = tmp_path / "qs"
    bayesmag.run_job(cfg, out)
    m = json.loads((out / "metrics.json").read_text())
    params = json.loads((out / "params.json").read_text())
    ex = expanded_uncertainties(m, params)
    assert ex["source"] == ex["new_session_source"] == "hybrid"
    pred = pd.read_csv(out / "predictions.csv")
    assert (pred["y_hybrid_family"] == "gaussian").all()       # the file says whose hybrid columns these are
    z = stats.norm.ppf(0.975)
    for a in "xyz":
        half = z * pred[f"{a}_hybrid_total"].to_numpy()
        assert ex["same_session"][a]["U"] == pytest.approx(half.mean(), rel=0.15)
        tau = m["transfer"]["sd"][a]
        new_half = z * np.sqrt(pred[f"{a}_hybrid_total"].to_numpy() ** 2 + tau**2)
        assert ex["new_session"][a]["U"] == pytest.approx(new_half.mean(), rel=0.15)
    # the y axis, where the physics misses the quadratic: its U is far above the hybrid's
    assert ex["physics"]["same_session"]["y"]["U"] > 2 * ex["same_session"]["y"]["U"]
    exported = run_uncertainty(out)
    assert exported["source"] == "physics" and "physics" not in exported
    for a in "xyz":
        assert exported["same_session"][a]["U"] == pytest.approx(ex["physics"]["same_session"][a]["U"], rel=1e-12)
    text = (out / "report.md").read_text()
    row = next(ln for ln in text.splitlines() if ln.startswith("| **expanded uncertainty U = k u_c, same session"))
    assert [float(c) for c in row.strip("|").split("|")[3:6]] == pytest.approx(
        [ex["same_session"][a]["U"] for a in "xyz"], rel=0.05)             # two significant figures
    assert "physics model alone" in text and "This run saved the hybrid predictor" in text
