"""``bayesmag config list`` and ``bayesmag config show NAME``: the packaged configs, and every key of
one with its value, default, unit and one-line meaning (:data:`KEY_DOCS`; a test checks that
every key of :class:`~bayesmag._src.app.config.Config` has an entry)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

__all__ = ["KEY_DOCS", "config_keys", "list_configs", "show_config"]

#: ``"section.key"`` -> (unit, one-line meaning); unit "" for dimensionless settings.
KEY_DOCS: dict[str, tuple[str, str]] = {
    "name": ("", "name of the job (the default output folder is runs/<config file name>)"),
    "data.source": ("", 'named dataset ("belsten2023") or "simulated"; give this or data.path'),
    "data.path": ("", "CSV file: time,run,bx_meas,by_meas,bz_meas,temperature[,bx_ref,by_ref,bz_ref]"),
    "data.temperature_unit": ("", "unit of the temperature column: C or K"),
    "data.time_unit": ("", "unit of the time column: s, ms, us, min or h (converted to seconds; loggers often "
                           "stamp ms or us since boot)"),
    "data.field_unit": ("", "declared unit of the field columns: uT | nT | mT | G (converted to uT and trusted); "
                            "unset: uT, checked (nT, mT and gauss refused)"),
    "data.columns": ("", "map canonical column names to the file's, e.g. {time = \"t\", bx_meas = \"X\"}"),
    "data.simulate": ("", "simulator settings with source = \"simulated\" (design, n, seed, noise_sd, effects)"),
    "split.kind": ("", "test rows: random | by_run | time_blocks (contiguous blocks per run) | none"),
    "split.test_fraction": ("", "share of rows held out for testing"),
    "split.seed": ("", "seed of the split"),
    "split.test_runs": ("", "runs held out with kind = \"by_run\""),
    "split.n_blocks": ("", "held-out blocks per run with kind = \"time_blocks\""),
    "physics.t0": ("C", 'reference temperature T0 of the model, or "mean" (the training mean; recommended)'),
    "physics.temperature_terms": ("", "fit the thermal terms Ks and Ko"),
    "physics.extra_terms": ("", "further physics terms from the discovery catalogue, by name"),
    "physics.covariance": ("", "parameter covariance: white | ar1 | newey_west (autocorrelated residuals)"),
    "uq.method": ("", "physics uncertainty: psqmc (paper) | mc | analytic (exact for linear models)"),
    "uq.n_params": ("", "Np: parameter draws of PS-QMC"),
    "uq.n_qmc": ("", "Nq: Sobol points of the input noise per parameter draw"),
    "uq.sigma_in": ("uT, C", '"auto" (estimated), sd of [Bx, By, Bz, T], or a 4x4 covariance of the input noise'),
    "uq.level": ("", "level of the central intervals and of the certificate's U"),
    "uq.seed": ("", "seed of the uncertainty draws"),
    "uq.chunk_size": ("rows", "rows per compiled chunk of the uncertainty computation"),
    "uq.residual_term": ("", "add the fit's unexplained residual variance (false: the paper's total)"),
    "uq.transfer": ("", 'between-session sd for new recordings: "loro" (leave one run out) | "hierarchical" '
                        '(random-effects model, Laplace; docs/sessions.md) | "hierarchical_nuts" | "off"; a field '
                        'calibration ([measurement] kind scalar/constant): "loro" (on the magnitude) | "off"'),
    "uq.transfer_likelihood": ("", 'likelihood of the hierarchical transfer model: "gaussian" | "student_t" (every '
                                   'run jointly multivariate t: heavy-tailed sessions) | "laplace" (every run jointly '
                                   'multivariate Laplace; docs/sessions.md)'),
    "uq.transfer_uninformed": ("", 'hierarchical transfer: parameters fewer than 3 runs sweep change between sessions '
                                   'as much as the learned ones ("pooled"), by their prior ("prior") or not at all '
                                   '("fixed"); docs/sessions.md'),
    "uq.transfer_check": ("", 'hierarchical transfer: an axis whose session-model spread is more than 2x leave-one-'
                               'run-out\'s (and the residual sd) failed its check: "loro" uses leave-one-run-out\'s '
                               'sd there, "warn" keeps the model\'s and warns (the hybrid\'s out-of-fold session model, '
                               'transfer_networks = "by_run_folds", is only warned about; docs/sessions.md)'),
    "uq.transfer_df": ("", 'degrees of freedom of the Student-t transfer likelihood (> 2), or "learned": a posterior '
                           'on a grid 2.5-50 and the Gaussian limit (docs/sessions.md)'),
    "uq.transfer_networks": ("", '"none" | "by_run_folds": the hybrid transfer part adds the residual network\'s own '
                                 'new-session error, from fold networks that never saw a run; with the hierarchical '
                                 'transfer the session model is refitted on their residuals (docs/sessions.md)'),
    "uq.reference_sd": ("uT", "standard uncertainty of the reference magnetometer (one value or per axis)"),
    "network.enabled": ("", "train the residual network (hybrid stage)"),
    "network.likelihoods": ("", "likelihood families, one network each (the first is the primary)"),
    "network.hidden_layers": ("", "hidden layers of the MLP"),
    "network.width": ("", "units per hidden layer"),
    "network.activation": ("", "activation function"),
    "network.dropconnect": ("", "DropConnect probability (training and MC passes)"),
    "network.learning_rate": ("", "Adam learning rate"),
    "network.batch_size": ("rows", "minibatch size"),
    "network.max_epochs": ("", "most training epochs"),
    "network.patience": ("epochs", "early stopping: epochs without improvement"),
    "network.min_delta": ("", "early stopping: smallest improvement of the validation loss"),
    "network.validation_fraction": ("", "share of the training rows used for early stopping"),
    "network.log_scale_clip": ("", "clip of the log squared scale of the standardised residual [low, high]"),
    "network.log_scale_l2": ("", "L2 penalty on the log scale head"),
    "network.epsilon": ("", "floor added to the predicted variance"),
    "network.student_t_df": ("", 'degrees of freedom of the Student-t likelihood (> 2), or "learn"'),
    "network.mc_passes": ("", "MC-DropConnect passes at prediction"),
    "network.lr_plateau_factor": ("", "learning-rate factor on a plateau (1 = off)"),
    "network.lr_plateau_patience": ("epochs", "plateau length before the learning rate is reduced"),
    "network.lr_min_factor": ("", "smallest learning rate as a factor of learning_rate"),
    "network.fourier_features": ("", "random Fourier features of the inputs (0 = none; not in the paper)"),
    "network.fourier_scale": ("", "sd of the Fourier frequencies per standardised input unit"),
    "network.validation": ("", 'early-stopping rows: "time_blocks" (one block per run) | "random" (paper)'),
    "network.recalibrate": ("", "fit a variance factor per axis on the validation rows"),
    "network.seed": ("", "seed of the network initialisation, batches and MC passes"),
    "network.interval_calibration": ("", '"conformal": scale the intervals (conformal scale c) | "none"'),
    "network.conformal_folds": ("", "most cross-conformal time-block folds (one network each)"),
    "network.fusion": ("", "how the network's and the physics uncertainty combine: moment_match | paper"),
    "nuts.enabled": ("", "run the NUTS cross-check of the physics posterior"),
    "nuts.chains": ("", "Markov chains"),
    "nuts.warmup": ("draws", "warm-up draws per chain"),
    "nuts.draws": ("draws", "kept draws per chain"),
    "nuts.target_accept": ("", "target acceptance probability of NUTS"),
    "nuts.chain_method": ("", "vectorized | parallel | sequential"),
    "nuts.likelihood": ("", "observation model, a family of bayesmag.likelihoods"),
    "nuts.priors": ("", "priors by parameter name (see docs/nuts.md)"),
    "nuts.seed": ("", "seed of the sampler"),
    "discover": ("", "settings of bayesmag discover (see docs/discovery.md)"),
    "study.sizes": ("rows", "simulated data set sizes of bayesmag study"),
    "study.per_size": ("", "[network] overrides per size"),
    "output.figures": ("", "draw the PNG figures"),
    "output.progress": ("", "progress bars (off anyway when the output is not a terminal)"),
    "output.compile_cache": ("", 'JAX persistent compilation cache in the user cache folder: "auto" (on from the command line, the caller\'s setting from Python), true, false'),
    "measurement.kind": ("", 'what the reference gives: "vector" (reference magnetometer) | "scalar" (a magnitude per '
                         'row) | "constant" (one field magnitude for the recording); docs/field.md'),
    "measurement.field": ("uT", 'constant: the site field magnitude (e.g. from IGRF/WMM), or "free"'),
    "measurement.scalar_column": ("", 'scalar with data.path: the CSV column holding the reference magnitude per row '
                                  '(uT); "" = the magnitude of bx_ref, by_ref, bz_ref'),
    "measurement.reference_sd": ("uT", "scalar: the reference magnitude's own noise sd (0: negligible); docs/field.md"),
    "measurement.temperature_terms": ("", 'thermal terms in the field fit: true | false | "auto" (on when the '
                                      'training temperature spans >= 1 C)'),
    "measurement.covariance": ("", 'field fit parameter covariance: "white" | "ar1" (autocorrelated residuals)'),
    "measurement.min_magnitude": ("uT", "drop rows whose reference magnitude is below this (a scalar sensor's range)"),
    "measurement.interval_calibration": ("", 'magnitude intervals: "conformal" (scaled to cover on time-block folds '
                                         'of the training rows) | "none" (the Laplace predictive as it is)'),
    "measurement.conformal_folds": ("", "most cross-conformal folds of the field fit (one refit each)"),
    "measurement.heading_check": ("", "simulated campaigns: report the heading error on the level test rows"),
    "measurement.compare_vector": ("", "with a vector reference in the data: compare the scalar fit's invariants"),
    "measurement.exports": ("", "firmware exports written by a field run (json, c-header, magcal, px4, ardupilot)"),
    "measurement.simulate": ("", 'data.source = "field_simulated": the simulate_field arguments (motion, seed, ...)'),
    "certificate.dut": ("", "device under test on the certificate: make, model, serial number"),
    "certificate.reference": ("", "reference instrument on the certificate: make, model, serial, its certificate"),
    "certificate.operator": ("", "who ran the calibration (optional)"),
}


def config_keys(cfg) -> list[tuple[str, object]]:
    """``("section.key", value)`` of every key of a :class:`Config`, in declaration order."""
    out = []
    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        if dataclasses.is_dataclass(v):
            internal = getattr(type(v), "internal", ())
            out += [(f"{f.name}.{g.name}", getattr(v, g.name)) for g in dataclasses.fields(v) if g.name not in internal]
        else:
            out.append((f.name, v))
    return out


def _describe(path: Path, limit: int = 160) -> str:
    """The first sentence of a config file's leading comment (its description), at most ``limit`` characters."""
    words = []
    for line in path.read_text(encoding="utf-8").splitlines():
        if not line.startswith("#"):
            break
        words += line.lstrip("#").split()
    text = " ".join(words)
    end = text.find(". ")
    text = text[:end + 1] if end >= 0 else text
    return text if len(text) <= limit else text[:limit - 3].rsplit(" ", 1)[0] + "..."


def list_configs(folder: Path) -> str:
    """One line per packaged config: name and description."""
    files = sorted(Path(folder).glob("*.toml"))
    width = max((len(p.stem) for p in files), default=0)
    return "\n".join(f"{p.stem:<{width}}  {_describe(p)}" for p in files) + "\n"


def _fmt(v) -> str:
    from bayesmag._src.app.config import _toml_value
    if v is None:
        return "(unset)"
    try:
        return _toml_value(v)
    except TypeError:
        return repr(v)


def show_config(path: Path) -> str:
    """Every key of the config at ``path``: value, default (``*`` marks a change), unit and meaning."""
    from bayesmag._src.app.config import Config, load_config
    cfg = load_config(path)
    defaults = dict(config_keys(Config()))
    rows = [(k, _fmt(v), _fmt(defaults.get(k)), *KEY_DOCS.get(k, ("", ""))) for k, v in config_keys(cfg)]
    wk, wv = max(len(r[0]) for r in rows), min(max(len(r[1]) for r in rows), 28)
    lines = [f"{path.stem}: {_describe(path)}", "", f"{'key':<{wk}}  {'value':<{wv}}  default / unit / meaning",
             "(* = differs from the default)"]
    for k, v, d, unit, meaning in rows:
        mark = " " if v == d else "*"
        lines.append(f"{k:<{wk}} {mark}{v:<{wv}}  default {d}" + (f" [{unit}]" if unit else "") + f"; {meaning}")
    return "\n".join(lines) + "\n"
