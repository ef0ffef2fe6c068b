"""The one Predictor: composition rules in closed form, purity, conformal interval scale, the one scorer."""

import dataclasses

import numpy as np
import pytest
import scipy.stats

import bayesmag
from bayesmag import PhysicsUQ, metrics
from bayesmag._src.core.likelihoods import Gaussian
from bayesmag._src.core.predictor import Components, Predictor, UQOptions, compose
from bayesmag._src.pipeline.conformal import conformal_quantile, conformal_ratios, conformal_scale
from helpers import uq_parts

Z95 = scipy.stats.norm.ppf(0.975)



def test_physics_only_adds_residual_scale_and_transfer_for_new_sessions_only():
    phys, _ = uq_parts(n=40)
    r, tau, k = np.array([0.01, 0.02, 0.03]), np.array([0.1, 0.2, 0.3]), np.array([1.5, 1.0, 2.0])
    new = np.arange(40) % 2 == 0
    p = compose(phys, residual_sd=r, transfer_sd=tau, scale=k, new_session=new)
    within = phys.aleatoric**2 + r**2 + phys.epistemic**2
    want = k**2 * within + np.where(new[:, None], tau**2, 0.0)
    np.testing.assert_allclose(p.total**2, want, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(p.dist.variance), want, rtol=1e-12)
    np.testing.assert_array_equal(p.transfer[~new], 0.0)
    np.testing.assert_array_equal(p.transfer[new], np.broadcast_to(tau, (new.sum(), 3)))
    lo, hi = p.interval(0.95)
    np.testing.assert_allclose(hi - p.mean, Z95 * np.sqrt(want), rtol=1e-10)
    # no transfer, no scale: the part is absent and the total is the within-session one
    q = compose(phys, residual_sd=r)
    assert q.transfer is None
    np.testing.assert_allclose(q.total**2, within, rtol=1e-12)


@pytest.mark.parametrize("fusion", ["moment_match", "paper"])
def test_hybrid_transfer_enters_in_quadrature(fusion):
    phys, nn = uq_parts(1, n=40)
    tau = np.array([0.05, 0.0, 0.4])
    p = compose(phys, nn, residual_sd=np.ones(3), fusion=fusion, family="laplace", transfer_sd=tau)
    var = nn.aleatoric**2 + nn.epistemic**2 + phys.epistemic**2 + (phys.aleatoric**2 if fusion == "paper" else 0)
    np.testing.assert_allclose(np.asarray(p.dist.variance), var + tau**2, rtol=1e-12)  # residual not added
    assert type(p.dist).name == ("gaussian" if fusion == "paper" else "laplace")
    np.testing.assert_allclose(p.mean, phys.mean + nn.mean, rtol=1e-14)


def test_predict_is_pure_and_matches_its_parts():
    d = bayesmag.simulate.simulate(400, design="iid", seed=0, noise_sd=0.05)
    fit = bayesmag.fit_physics(d)
    pr = Predictor(fit=fit, sigma_in=np.diag([0.05**2] * 3 + [1e-6]), residual_sd=np.full(3, 0.01),
                   transfer_sd=np.array([0.1, 0.2, 0.3]), uq=UQOptions(method="analytic"))
    a, b = pr.predict(d), pr.predict(d)
    np.testing.assert_array_equal(a.mean, b.mean)
    np.testing.assert_array_equal(a.total, b.total)
    c = pr.compose(Components(pr.physics_part(d)), new_session=True)
    np.testing.assert_array_equal(a.total, c.total)
    same = pr.predict(d, new_session=False)
    assert np.all(same.total < a.total) and np.all(same.transfer == 0)
    with pytest.raises(ValueError, match=r"fusion 'rss'.*\['moment_match', 'paper'\]"):
        dataclasses.replace(pr, fusion="rss")


def test_conformal_scale_recovers_a_known_misscale():
    """Predicted sd half the truth: the factor is ~2 and the scaled intervals cover the level."""
    rng = np.random.default_rng(3)
    n = 4000
    y = rng.normal(0.0, 2.0, (n, 3))
    unit = PhysicsUQ(np.zeros((n, 3)), np.ones((n, 3)), np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3)))
    k = conformal_scale(y, compose(unit), 0.95)
    np.testing.assert_allclose(k, 2.0, rtol=0.05)        # sampling sd of the 95% quantile ~1.5% at n = 4000
    lo, hi = compose(unit, scale=k).interval(0.95)
    cov = metrics.coverage(y, lo, hi)
    assert np.all(cov >= 0.95) and np.all(cov <= 0.955)   # split conformal: at least the level, ceil((n+1)0.95)/n
    with pytest.raises(ValueError, match="at least 20"):
        conformal_scale(y[:10], compose(PhysicsUQ(*(np.ones((10, 3)),) * 5)), 0.95)
    # cross-conformal: scores of several folds pooled, one quantile (the job's scale over its time-block folds)
    half = PhysicsUQ(np.zeros((n // 2, 3)), np.ones((n // 2, 3)), *(np.zeros((n // 2, 3)),) * 3)
    pooled = conformal_quantile(np.concatenate([conformal_ratios(y[:n // 2], compose(half), 0.95),
                                                conformal_ratios(y[n // 2:], compose(half), 0.95)]), 0.95)
    np.testing.assert_array_equal(pooled, k)


def test_score_is_the_one_scorer():
    rng = np.random.default_rng(0)
    n = 300
    d = Gaussian(rng.normal(size=(n, 3)), rng.uniform(0.5, 1.5, (n, 3)))
    y = rng.normal(size=(n, 3))
    s = metrics.score(y, d, 0.9)
    assert tuple(s) == ("rmse", "mae", "coverage", "nll", "crps", "mean_width")
    lo, hi = d.interval(0.9)
    np.testing.assert_allclose(s["coverage"], metrics.coverage(y, lo, hi))
    np.testing.assert_allclose(s["mean_width"], np.mean(2 * scipy.stats.norm.ppf(0.95) * np.asarray(d.scale), 0),
                               rtol=1e-10)
    per = metrics.score_per_axis(y, d, 0.9)
    summ = metrics.summarize(y, d, 0.9)
    for a in "xyz":
        assert per["mean_width"][a] == summ[a]["width"] and per["nll"][a] == summ[a]["nll"]


def _small_nets(k: int, likelihood: str = "gaussian"):
    """``k`` small trained residual networks on one synthetic problem, differing in rows and seed (fold networks)."""
    from bayesmag._src.core.network import NetworkSpec, fit_residual_network

    rng = np.random.default_rng(0)
    x = rng.normal(size=(300, 4))
    r = np.column_stack([np.sin(x[:, 0]), 0.5 * x[:, 1] * x[:, 3], np.cos(x[:, 2])]) + 0.1 * rng.normal(size=(300, 3))
    spec = NetworkSpec(hidden_layers=1, width=8, batch_size=64, max_epochs=3, patience=2, dropconnect=0.2,
                       likelihood=likelihood)
    return [fit_residual_network(np.delete(x, np.s_[30 * j:30 * j + 30], 0), np.delete(r, np.s_[30 * j:30 * j + 30], 0),
                                 spec, seed=j) for j in range(k)], x[:50]


@pytest.mark.parametrize("passes", [9, 12])
@pytest.mark.extended
def test_ensemble_pools_every_pass_exactly(passes):
    """Deep ensemble x MC DropConnect: the pooled moments are those of all raw passes of all members together."""
    from bayesmag._src.core.network import NetworkEnsemble, ensemble_passes, mc_predict, mc_samples

    nets, x = _small_nets(3)
    counts = ensemble_passes(passes, 3)
    assert sum(counts) == passes and counts == ((3, 3, 3) if passes == 9 else (4, 4, 4))
    assert ensemble_passes(101, 5) == (21, 20, 20, 20, 20) and ensemble_passes(100, 5) == (20,) * 5
    assert ensemble_passes(5, 3) == (2, 2, 2)                  # at least 2 each (a sample variance needs 2)
    raw = [mc_samples(n, x, passes=c, seed=7 + k) for k, (n, c) in enumerate(zip(nets, counts))]
    # mc_samples are mc_predict's passes: its moments from them, member by member
    for n, c, (mu, var), k in zip(nets, counts, raw, range(3)):
        one = mc_predict(n, x, passes=c, seed=7 + k)
        np.testing.assert_allclose(one.mean, mu.mean(0), rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(one.epistemic, mu.std(0, ddof=1), rtol=1e-4, atol=1e-7)
        np.testing.assert_allclose(one.aleatoric, np.sqrt(var.mean(0)), rtol=1e-5)
    means, variances = np.concatenate([m for m, _ in raw]), np.concatenate([v for _, v in raw])   # (M, n, 3)
    pooled = mc_predict(NetworkEnsemble(tuple(nets)), x, passes=passes, seed=7)
    np.testing.assert_allclose(pooled.mean, means.mean(0), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(pooled.aleatoric**2, variances.mean(0), rtol=1e-5)
    np.testing.assert_allclose(pooled.epistemic**2, means.var(0, ddof=1), rtol=1e-4, atol=1e-10)
    # the between-member spread counts: larger than the mean within-member variance alone
    within = np.mean([m.var(0, ddof=1) for m, _ in raw], axis=0)
    assert np.mean(pooled.epistemic**2) > np.mean(within)
    # one member is the network itself
    single = mc_predict(NetworkEnsemble((nets[0],)), x, passes=passes, seed=7)
    plain = mc_predict(nets[0], x, passes=passes, seed=7)
    for f in ("mean", "aleatoric", "epistemic"):
        np.testing.assert_allclose(getattr(single, f), getattr(plain, f), rtol=1e-12)


def test_ensemble_predictor_pools_student_t_shape_and_chunks():
    """A Predictor with an ensemble: family and shape from the members, chunked rows as one call."""
    from bayesmag._src.core import predictor as P
    from bayesmag._src.core.network import NetworkEnsemble, mc_predict

    nets, x = _small_nets(2, "student_t")
    ens = NetworkEnsemble(tuple(nets))
    pooled = mc_predict(ens, x, passes=10, seed=1)
    parts = [mc_predict(n, x, passes=5, seed=1 + k) for k, n in enumerate(nets)]
    np.testing.assert_allclose(pooled.shape["df"], 0.5 * (parts[0].shape["df"] + parts[1].shape["df"]), rtol=1e-12)
    phys, _ = uq_parts(n=50)
    pr = Predictor(fit=None, sigma_in=np.zeros((4, 4)), residual_sd=np.zeros(3), network=ens, passes=10, network_seed=1)
    assert pr.family == "student_t"
    data = bayesmag.CalibrationData(x[:, :3], x[:, 3], None, np.arange(50.0), np.zeros(50, int))
    whole = pr.network_part(data)
    old = P.NN_CHUNK
    try:
        P.NN_CHUNK = 16
        chunked = pr.network_part(data)
    finally:
        P.NN_CHUNK = old
    np.testing.assert_allclose(chunked.mean, whole.mean, rtol=1e-6)
    np.testing.assert_allclose(chunked.epistemic, whole.epistemic, rtol=1e-5)
    p = pr.compose(Components(phys, whole))
    assert p.family == "student_t" and np.all(np.isfinite(p.total))


@pytest.mark.extended
def test_a_prediction_knows_its_calibrations_level(tmp_path):
    """Seventh outside pass (found in the fifth): ``Prediction.interval`` needed its level, so
    ``run.predictor.predict(rows).interval()`` raised TypeError and ``interval(95)`` gave NaN bounds without a word.
    The level lives in the settings (``[uq] level``) and the saved calibration; every Predictor keeps it and every
    Prediction it makes carries it; an explicit level still wins; one outside (0, 1) is refused, naming it."""
    import warnings
    d = bayesmag.simulate.simulate(400, design="campaign", seed=0, noise_sd=0.05)
    settings = bayesmag.CalibrationSettings(uq=bayesmag.UQSettings(level=0.9, method="analytic"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        run = bayesmag.calibrate(d.subset(np.arange(320)), settings, test=d.subset(np.arange(320, 400)))
    pred = run.predictor.predict(d)
    assert run.predictor.level == pred.level == run.prediction.level == 0.9
    lo, hi = pred.interval()
    np.testing.assert_array_equal(lo, pred.interval(0.9)[0])
    np.testing.assert_allclose(hi - pred.mean, scipy.stats.norm.ppf(0.95) * pred.total, rtol=1e-10)
    assert np.all(pred.interval(0.99)[1] > hi)                        # the explicit argument still works
    for bad in (95, 0.0, 1.0, True, "0.95"):
        with pytest.raises(ValueError, match=rf"level\) = {bad!r} must be a number in \(0, 1\)"):
            pred.interval(bad)
    with pytest.raises(ValueError, match=r"use 0\.95"):
        pred.interval(95)
    with pytest.raises(ValueError, match=r"Predictor\.level = 95"):
        dataclasses.replace(run.predictor, level=95)

    with warnings.catch_warnings():                                    # saved and loaded: the calibration's level
        warnings.simplefilter("ignore")
        cal = bayesmag.Calibrator({"uq": {"level": 0.8, "method": "analytic"}}).fit(d)
        out = cal.predict(d)
    loaded = cal.calibration_.predictor().predict(d)
    assert loaded.level == 0.8
    np.testing.assert_allclose(loaded.interval()[0], out["lower"], rtol=1e-12)
