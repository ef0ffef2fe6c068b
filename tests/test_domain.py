"""The training domain's rate checks on recordings whose stamps repeat (core/domain.py)."""

import numpy as np
import pytest

from bayesmag._src.core.data import CalibrationData
from bayesmag._src.core.domain import Domain, rates, repeated_stamps


def _recording(speed, n=400, dt=0.25, seed=0):
    """A 4 Hz recording whose field turns at ``speed`` (rad/s) for rows 150-250 and slowly elsewhere."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * dt
    w = np.where((np.arange(n) >= 150) & (np.arange(n) < 250), speed, 0.2)
    phase = np.cumsum(w) * dt
    b = 40 * np.column_stack([np.cos(phase), np.sin(phase), 0.3 * np.ones(n)]) + rng.normal(0, 0.02, (n, 3))
    temp = 22 + 0.01 * t
    return CalibrationData(b, temp, None, time=t, run=np.zeros(n, int))


def test_whole_second_stamps_are_checked_as_the_real_4hz_times():
    """Sixth outside pass: `apply` on Belsten run 4 with its file's whole-second stamps flagged 68 field_rate rows
    where the run flagged 106: rows at equal times were skipped, so the step across a second boundary was read as a
    change over 1 s instead of 0.25 s (rates up to 4x too low). Now the stamps are spread as the loader spreads
    them: the same flags as the true times (up to the rows next to a fast turn's start and end)."""
    train = _recording(0.4)
    dom = Domain.from_data(train)
    new = _recording(1.2, seed=1)                          # turns 3x faster than training in rows 150-250
    whole = CalibrationData(new.b_meas, new.temperature, None, time=np.floor(new.time), run=new.run)
    assert repeated_stamps(whole) == 300 and repeated_stamps(new) == 0
    true_flags = dom.outside(new)[:, 4:7].any(axis=1)
    got = dom.outside(whole)[:, 4:7].any(axis=1)
    assert true_flags.sum() >= 90                          # the fast turn is flagged on the true times
    assert np.sum(got != true_flags) <= 4                  # spread stamps: the same rows, up to the edges
    np.testing.assert_allclose(rates(whole)[160:240], rates(new)[160:240], rtol=0.05)
    note = dom.step_note(whole)
    assert note is not None and note.startswith("300 of 400 rows share their timestamp")
    assert dom.step_note(new) is None


@pytest.mark.parametrize("stamps", [[0, 0, 1, 1, 2, 2], [0, 1, 2, 3, 4, 5]])
def test_repeated_stamps_counts_within_runs(stamps):
    d = CalibrationData(np.ones((6, 3)) * 40, np.full(6, 20.0), None, time=np.array(stamps, float),
                        run=np.array([0, 0, 0, 1, 1, 1]))
    want = 2 if stamps[0] == stamps[1] else 0         # one in each run ([0, 0, 1] and [1, 2, 2])
    assert repeated_stamps(d) == want


def test_the_budget_averages_over_the_in_domain_test_rows():
    """Sixth outside pass: a leave-run-out certificate's U averaged the parts over every test row, 395 of 584 of
    them extrapolated (Belsten run 4), while it states U inside the domain only: 0.091 against 0.047 uT on x."""
    from bayesmag._src.core.domain import budget_row_mask, budget_rows_note
    out = np.array([[False, False], [True, False], [False, True], [False, False]])
    np.testing.assert_array_equal(budget_row_mask(out), [True, False, False, True])
    assert budget_rows_note(out) == "2 in-domain test rows of 4"
    none = np.ones((3, 2), bool)
    np.testing.assert_array_equal(budget_row_mask(none), [True, True, True])     # none inside: all, said so
    assert budget_rows_note(none) == "all 3 test rows (none in domain)"
    assert budget_rows_note(np.zeros((5, 2), bool)) == "all 5 test rows (all in domain)"


def test_predict_warns_of_repeated_stamps_as_apply_does():
    """Python's predict raised only the out-of-domain warning where apply also printed the repeated-stamps note."""
    import warnings

    import bayesmag
    from bayesmag import CalibrationWarning
    d = bayesmag.simulate.simulate(900, design="campaign", seed=0, noise_sd=0.05)
    cal = bayesmag.Calibrator().fit(d).calibration_
    new = bayesmag.simulate.simulate(300, design="campaign", seed=7, noise_sd=0.05)
    whole = CalibrationData(new.b_meas, new.temperature, None, time=np.floor(new.time), run=new.run)
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always", CalibrationWarning)
        cal.predict(whole)
    assert any("share their timestamp" in str(w.message) for w in got)


def test_the_out_of_domain_warning_counts_each_reason(tmp_path):
    """Seventh outside pass: apply's "N rows lie outside the calibration's training domain" named no reason, so the
    user could not tell what to fix (a wider field range, a temperature span, slower turns). Now it counts the rows
    of each reason, as the file's in_domain_reason bits do (a row outside for two reasons counts under both); so
    does Calibration.predict's warning."""
    import warnings

    import bayesmag
    from bayesmag import CalibrationWarning, write_csv
    from bayesmag._src.app.apply import apply_calibration
    from bayesmag._src.app.artifact import out_of_domain_counts, out_of_domain_note, save_calibration
    from bayesmag._src.core.fit import fit_physics
    from bayesmag._src.core.physics import PhysicsModel
    from bayesmag._src.core.physics_uq import estimate_input_noise
    from bayesmag._src.core.predictor import Predictor, UQOptions

    assert out_of_domain_counts(["field_range", "temperature;field_rate", "temperature"]) == {
        "field_range": 1, "temperature": 2, "field_rate": 1}
    assert "(in_domain=false; temperature 2 (" in out_of_domain_note(2, 9, ["temperature"] * 2)
    d = bayesmag.simulate.simulate(600, design="campaign", seed=3, noise_sd=0.05)
    fit = fit_physics(d, PhysicsModel.paper(t0=25.0))
    pred = Predictor(fit=fit, sigma_in=estimate_input_noise(d), residual_sd=np.full(3, 0.01),
                     transfer_sd=np.full(3, 0.02), domain=Domain.from_data(d), uq=UQOptions(method="analytic"))
    (tmp_path / "cal").mkdir()
    save_calibration(tmp_path / "cal", pred, config={}, level=0.95)
    new = bayesmag.simulate.simulate(200, design="campaign", seed=4, noise_sd=0.05)
    hot = np.asarray(new.temperature).copy()
    hot[:30] = float(np.max(d.temperature)) + 20.0                # 30 rows far above the training temperatures
    rec = CalibrationData(new.b_meas, hot, None, time=new.time, run=new.run)
    write_csv(rec, tmp_path / "new.csv")
    s = apply_calibration(tmp_path / "cal", tmp_path / "new.csv", tmp_path / "o.csv")
    w = [x for x in s["warnings"] if "outside the calibration's training domain" in x]
    assert len(w) == 1 and f"{s['n_outside_domain']} of 200 rows" in w[0], s["warnings"]
    n_temp = sum(v for k, v in s["outside_domain_by_reason"].items() if "temperature" in k.split(";"))
    assert n_temp >= 30 and f"temperature {n_temp} (the temperature outside the training span)" in w[0], w[0]
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always", CalibrationWarning)
        bayesmag.load(tmp_path / "cal").predict(rec)
    assert any(f"temperature {n_temp} (" in str(g.message) for g in got)
