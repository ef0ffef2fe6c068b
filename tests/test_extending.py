"""Issue #12: a new catalogue term and a new likelihood family, each defined here and nowhere
else, run through fit, discover, NUTS and a saved calibration (docs/extending.md)."""

import csv
import dataclasses
import warnings
from typing import ClassVar

import jax.numpy as jnp
import numpy as np
import pytest

import bayesmag as bm
from bayesmag._src.core import catalogue as C
from bayesmag._src.core import likelihoods as _lik
from bayesmag._src.core.catalogue import Entry, Setting
from bayesmag._src.app.config import config_from_dict
from bayesmag._src.core.catalogue import make_extra
from bayesmag._src.core.physics import EXTRA_TERMS, PhysicsModel, Term
from helpers import Logistic, affine_data


# ---------------------------------------------------------------- the toy term (docs/extending.md)
@dataclasses.dataclass(frozen=True)
class AbsField(Term, Entry):
    r"""Rectified field: :math:`\sum_j a_j |B_j|` (``a`` dimensionless)."""

    name: ClassVar[str] = "toy_abs_field"
    degree: ClassVar[None] = None                      # |B| is not a polynomial
    temperature_centred: ClassVar[bool] = True         # no temperature at all: one program for every T0
    explanation: ClassVar[str] = "A toy: the reading responds to the magnitude of one field component."

    def param_names(self):
        return ("a_x", "a_y", "a_z")

    def features(self, inputs):
        return jnp.abs(inputs.b)

    @classmethod
    def grid(cls, ctx, c):                             # one option per input component
        return [Setting(cls(), cols=(j,)) for j in range(3)]

    def describe(self, cols):
        return "reading gains " + " + ".join(f"|B{'xyz'[j]}|" for j in (cols or range(3))) + " terms"

    def depends_on(self, cols):
        return "B" + "xyz"[(cols or (0,))[0]]


# ---------------------------------------------------------------- the toy family (logistic)
@dataclasses.dataclass(frozen=True)
class ToyLogistic(Logistic):
    """Logistic(loc, scale) (tests/helpers.py), under a test-only name."""

    name = "toy_logistic"


# registered (bayesmag.register_likelihood, as bayesmag.register_term for the term) only while these tests run
@pytest.fixture(autouse=True, scope="module")
def _registered():
    C.register(AbsField)
    _lik.register(ToyLogistic)
    yield
    C.unregister("toy_abs_field")
    _lik.unregister("toy_logistic")


def test_registered_everywhere():
    assert C.CATALOGUE["toy_abs_field"] is AbsField and EXTRA_TERMS["toy_abs_field"] is AbsField
    assert _lik.get_likelihood("toy_logistic") is ToyLogistic
    assert type(make_extra("toy_abs_field")) is AbsField
    with pytest.raises(ValueError, match="already registered"):
        C.register(AbsField)
    with pytest.raises(TypeError, match="dataclass subclassing Entry"):
        C.register(PhysicsModel)
    with pytest.raises(ValueError, match="not registered"):
        C.unregister("no_such_term")


def test_unregister_removes_the_term_everywhere():
    assert C.unregister("toy_abs_field") is AbsField
    try:
        assert "toy_abs_field" not in C.CATALOGUE and "toy_abs_field" not in EXTRA_TERMS
        with pytest.raises(ValueError, match="not known"):
            make_extra("toy_abs_field")
    finally:
        C.register(AbsField)


#: Planted toy coefficient; the fit must recover it within 5 standard errors (SE ~1e-4 here).
A_TRUE = 0.05


def _toy_data(n, seed, noise):
    data, _ = affine_data(n, seed=seed, noise=noise)
    y = data.b_ref.copy()
    y[:, 2] += A_TRUE * np.abs(data.b_meas[:, 0])               # truth: the z output gains a |Bx|
    return bm.CalibrationData(data.b_meas, data.temperature, y, data.time)


def test_fit_recovers_the_toy_coefficient():
    data = _toy_data(3000, seed=4, noise=0.05)
    model = PhysicsModel.paper(extra=(make_extra("toy_abs_field"),))
    fit = bm.fit_physics(data, model)
    i = model.param_names.index("a_x")
    se = np.sqrt(fit.cov[:, i, i])
    assert se[2] < 1e-3 and abs(fit.theta[2, i] - A_TRUE) < 5 * se[2]
    assert np.all(np.abs(fit.theta[:2, i]) < 5 * se[:2])        # no |Bx| on x and y


@pytest.mark.extended
def test_discover_names_the_toy_term_on_its_channel():
    """The toy distortion planted on the y reading of a campaign: discover finds it (only through
    the registry) on channel y, input Bx, with its coefficient."""
    d = bm.simulate.simulate(3000, design="campaign", seed=0, noise_sd=0.05)
    b = d.b_meas.copy()
    b[:, 1] += 0.03 * np.abs(b[:, 0])                           # the y reading gains 0.03 |Bx|
    d = bm.CalibrationData(b, d.temperature, d.b_ref, d.time, d.run, d.source)
    r = bm.discover(d, figures=False)
    toy = [f for f in r.findings if f["effect"] == "toy_abs_field"]
    assert len(toy) == 1, [(f["effect"], f["channel"]) for f in r.findings]
    f = toy[0]
    assert f["frame"] == "sensor" and f["channel"] == "y" and list(f["parameters"]) == ["a_x"]
    p = f["parameters"]["a_x"]
    assert abs(p["value"] - 0.03) < 5 * p["se"], p            # the sensor-frame coefficient is the planted one
    assert f["config"]["name"] == "toy_abs_field" and f["explanation"] == AbsField.explanation


@pytest.mark.extended
def test_nuts_with_the_toy_family_and_term():
    """NUTS (2 chains x 200 draws) with the toy family as observation model and the toy term in the
    mean function: converged, and the posterior of the toy coefficient covers the truth (4 sd)."""
    from bayesmag._src.pipeline.nuts import NutsWarning
    data = _toy_data(400, seed=1, noise=0.2)
    fit = bm.fit_physics(data, PhysicsModel.paper(extra=(AbsField(),)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NutsWarning)            # R-hat/ESS targets are for 4 x 1000 draws
        res = bm.run_nuts(data, fit, chains=2, warmup=200, draws=200, likelihood="toy_logistic", axes=("z",),
                          seed=0)
    assert res.settings["likelihood"] == "toy_logistic"
    c = res.crosscheck["z"]
    assert c["divergences"] == 0 and c["max_rhat"] < 1.05, c
    a = res.idata.posterior.theta.sel(axis="z", parameter="a_x").values
    assert abs(a.mean() - A_TRUE) < 4 * a.std(), (a.mean(), a.std())


@pytest.mark.extended
def test_a_job_with_the_toy_term_and_family_round_trips(tmp_path):
    """``[physics] extra_terms = ["toy_abs_field"]`` with the toy family as the network likelihood:
    the saved calibration rebuilds the term by name and reproduces the run's predictions."""
    sim = {"design": "campaign", "n": 1200, "seed": 1, "noise_sd": 0.05}
    cfg = config_from_dict({
        "data": {"source": "simulated", "simulate": sim},
        "split": {"kind": "time_blocks", "test_fraction": 0.2},
        "uq": {"n_params": 16, "n_qmc": 16, "seed": 3, "method": "psqmc"},
        "physics": {"t0": "mean", "extra_terms": ["toy_abs_field"]},
        "network": {"enabled": True, "likelihoods": ["toy_logistic"], "hidden_layers": 1, "width": 8,
                    "batch_size": 128, "max_epochs": 4, "mc_passes": 4, "seed": 2},
        "output": {"figures": False, "progress": False},
    })
    out = tmp_path / "run"
    res = bm.run_job(cfg, out)
    cal = bm.load(out)
    assert [t.name for t in cal.physics_fit().model.terms] == ["thermo_affine", "toy_abs_field"]
    assert cal.likelihood == "toy_logistic"
    test = res["data"].subset(res["split"].test)
    pred = cal.predict(test, method="psqmc", n_params=16, n_qmc=16, seed=3, new_session=False)
    rows = list(csv.DictReader(open(out / "predictions.csv")))
    for a, ax in enumerate("xyz"):
        for col, key in (("hybrid_predicted", "calibrated"), ("hybrid_total", "total"), ("hybrid_upper", "upper")):
            np.testing.assert_allclose(pred[key][:, a], [float(r[f"{ax}_{col}"]) for r in rows], rtol=1e-6,
                                       atol=1e-9)                # the CSV keeps 8 digits


def test_a_term_whose_features_miss_a_parameter_is_named_when_the_model_is_built():
    """Sixth outside pass: a term with 2 feature columns for 3 parameter names registered, and the job failed
    inside JAX ("dot_general requires contracting dimensions to have the same shape"), naming no term."""

    @dataclasses.dataclass(frozen=True)
    class TwoColumns(AbsField):
        name: ClassVar[str] = "toy_two_columns"

        def features(self, inputs):
            return jnp.abs(inputs.b[..., :2])

    with pytest.raises(ValueError, match=r"'toy_two_columns' \(TwoColumns\): features gives 2 column\(s\) for its 3 "
                                         r"parameter\(s\) \['a_x', 'a_y', 'a_z'\]"):
        PhysicsModel.paper(t0=25.0, extra=(TwoColumns(),))
    PhysicsModel.paper(t0=25.0, extra=(AbsField(),))        # the right one builds
