"""The hybrid stage's networks train while the physics stage finishes (pipeline/prefetch.py): the same networks as
trained after it, the training stopped on an error, and not used where the stage trains fold networks."""

from __future__ import annotations

import threading
import time

import jax
import numpy as np
import pytest

import bayesmag
from bayesmag._src.pipeline import prefetch, stages
from bayesmag._src.pipeline.calibrate import calibrate
from bayesmag._src.pipeline.settings import CalibrationSettings, NetworkSettings, UQSettings

FAST = {"n_params": 40, "n_qmc": 64, "seed": 2}


@pytest.fixture(scope="module")
def split():
    d = bayesmag.simulate.simulate(500, design="campaign", seed=5)
    return d.subset(np.arange(400)), d.subset(np.arange(400, 500))


def _settings(**net):
    kw = dict(hidden_layers=1, width=8, max_epochs=30, patience=5, batch_size=32, mc_passes=8,
              interval_calibration="none", likelihoods=("gaussian", "laplace"))
    return CalibrationSettings(uq=UQSettings(**FAST), network=NetworkSettings(**{**kw, **net}))


def _leaves(run):
    return [np.asarray(x) for name in run.hybrid.networks for x in jax.tree.leaves(run.hybrid.networks[name].params)]


@pytest.mark.extended
def test_networks_trained_during_the_physics_stage_are_the_ones_trained_after_it(split, monkeypatch):
    """Bit-identical weights, predictions and training records with the prefetch on and off (same programs)."""
    train, test = split
    started = []
    real = prefetch.start_training
    monkeypatch.setattr(prefetch, "start_training", lambda *a, **k: started.append(1) or real(*a, **k))
    with_prefetch = calibrate(train, _settings(), test=test)
    assert started, "the plain hybrid stage should train in the background"
    monkeypatch.setattr(prefetch, "start_training", lambda *a, **k: None)
    without = calibrate(train, _settings(), test=test)
    for a, b in zip(_leaves(with_prefetch), _leaves(without)):
        np.testing.assert_array_equal(a, b)
    for name in ("gaussian", "laplace"):
        np.testing.assert_array_equal(with_prefetch.hybrid.predictions[name].mean, without.hybrid.predictions[name].mean)
        np.testing.assert_array_equal(with_prefetch.hybrid.predictions[name].total,
                                      without.hybrid.predictions[name].total)
        np.testing.assert_array_equal(with_prefetch.hybrid.networks[name].info.val_loss,
                                      without.hybrid.networks[name].info.val_loss)
    assert with_prefetch.timings["network_train"] > 0


def test_an_error_after_the_fit_stops_the_background_training(split, monkeypatch):
    """The physics stage fails after the training started: calibrate raises that error and no training thread is
    left running (it stops at its next chunk of epochs)."""
    train, test = split
    trainings = []
    real = prefetch.start_training

    def spy(*a, **k):
        t = real(*a, **k)
        trainings.append(t)
        return t

    monkeypatch.setattr(prefetch, "start_training", spy)
    real_part = stages.Predictor.physics_part

    def boom(self, *a, **k):
        time.sleep(0.2)                       # the training is under way
        raise RuntimeError("physics uncertainty failed")

    monkeypatch.setattr(stages.Predictor, "physics_part", boom)
    with pytest.raises(RuntimeError, match="physics uncertainty failed"):
        calibrate(train, _settings(max_epochs=100_000, patience=100_000), test=test)
    monkeypatch.setattr(stages.Predictor, "physics_part", real_part)
    assert trainings and trainings[0] is not None
    assert not any(t.name == "bayesmag-prefetch" and t.is_alive() for t in threading.enumerate())


@pytest.mark.parametrize("net, transfer_networks, asked",
                         [({"interval_calibration": "conformal", "conformal_folds": 2}, "none", True),
                          pytest.param({}, "by_run_folds", False, marks=pytest.mark.slow)])
def test_fold_networks_are_not_prefetched(split, monkeypatch, net, transfer_networks, asked):
    """Cross-conformal and by-run fold networks train together on one pool after the physics stage, as before:
    no background training (the conformal stage is asked and declines; the by-run option is not asked)."""
    import dataclasses

    train, test = split
    got = []
    real = prefetch.start_training
    monkeypatch.setattr(prefetch, "start_training", lambda *a, **k: got.append(real(*a, **k)) or got[-1])
    s = _settings(likelihoods=("gaussian",), **net)
    s = dataclasses.replace(s, uq=dataclasses.replace(s.uq, transfer_networks=transfer_networks))
    run = calibrate(train, s, test=test)
    assert run.hybrid is not None
    assert got == ([None] if asked else [])


def test_on_physics_hears_the_physics_stage_before_the_hybrid_stage_and_changes_nothing(split, monkeypatch):
    """``calibrate(on_physics=)`` (the command line queues the physics figures there, drawn while the networks
    train): called once, with the run's own physics stage, before the hybrid stage starts; a callback that runs
    JAX work of its own (as the figures' columns do) leaves the run bit-identical."""
    train, test = split
    order = []
    real = stages.run_hybrid_stage
    monkeypatch.setattr(stages, "run_hybrid_stage", lambda *a, **k: order.append("hybrid") or real(*a, **k))
    heard = []

    def on_physics(ps):
        order.append("physics")
        heard.append(ps)
        np.asarray(ps.prediction.interval(0.95)[0])      # JAX work on this thread while the networks train

    run = calibrate(train, _settings(), test=test, on_physics=on_physics)
    assert order == ["physics", "hybrid"] and heard[0] is run.physics
    plain = calibrate(train, _settings(), test=test)
    for a, b in zip(_leaves(run), _leaves(plain)):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(run.prediction.total, plain.prediction.total)
