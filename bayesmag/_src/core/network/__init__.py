r"""Heteroscedastic residual network with Monte-Carlo DropConnect (Shetty & Marndi 2026, sec. 2.4).

One small MLP per field axis maps the standardised inputs :math:`x = (B_{meas}, T)` to the
raw head of a predictive family (:mod:`bayesmag.likelihoods`) for the physics residual
:math:`r = B_{ref} - \bar y_{phys}(x)`. Everything here is a pure function of pytrees:

* ``params`` is a tuple of :class:`Dense` layers (``w`` of shape ``(in, out)``, ``b`` of
  shape ``(out,)``), float32; :func:`init` makes them and :func:`apply` evaluates them;
* DropConnect (Wan et al. 2013) multiplies every weight *matrix* (not the biases, not the
  activations) by an independent Bernoulli(1 - p) mask scaled by ``1/(1-p)``, so the
  expected weights are the trained ones. One mask is drawn per minibatch step in training
  and one per forward pass at inference, shared by all rows of that pass (a pass is one
  draw of the weights from the approximate posterior; Mobiny et al. 2021).
  ``key=None`` gives the deterministic network with the expected weights;
* training (:func:`fit_residual_network`) is one jit-compiled program per axis, run in
  chunks of epochs (progress between them): the epoch loop is a :func:`jax.lax.while_loop`
  and the minibatch loop inside it a :func:`jax.lax.scan`; the axes run on threads over the
  cores there are (the same numbers for any count). Minibatches are reshuffled every epoch
  from a seeded key; a final short batch is padded with zero-weight rows.

Optional random Fourier input features (``fourier_features = m > 0``; not in the paper): the
standardised inputs ``z`` are extended to :math:`[z, \sin(2\pi zB), \cos(2\pi zB)]` with a fixed
``(n_in, m)`` matrix :math:`B \sim N(0, \sigma^2)` (``sigma = fourier_scale``) drawn from the
network seed (Tancik et al. 2020). A ReLU MLP on raw inputs learns smooth functions first
(spectral bias); the embedding lets it fit sharper structure in the residual. On a random row
split of an autocorrelated recording that sharper structure is mostly interpolation between
time neighbours, so it helps there far more than on held-out stretches of time
(``docs/hybrid.md``); it is off by default.

Loss (sec. 2.4), on the *standardised* residual :math:`\tilde r = (r - m_r)/s_r`:

.. math::  L(\phi) = \frac1N\sum_i \Big[-\log p(\tilde r_i \mid \mu_i, s_i)
           + \lambda\,(\log s_i^2)^2\Big],\qquad
           s_i^2 = \exp(\mathrm{clip}(h_{i,1}, lo, hi)) + \epsilon

with ``p`` the family density (Gaussian, Laplace or Student-t), ``lambda = log_scale_l2``,
``(lo, hi) = log_scale_clip`` and ``epsilon`` added to the squared scale. For the Gaussian
this is the paper's loss up to a factor 2 and a constant. Because the residual is scaled
to unit variance, ``log_scale_clip`` and the penalty act on the log of the scale relative to
the residual's training sd (the paper's raw-unit clip [-10, 3] uT^2 would put the x axis
residual variance, ~6e-4 uT^2, near the middle of the range too); inputs are standardised
by the fitting rows' mean and sd.

Early stopping (sec. 3.6): after every epoch the validation loss (the same regularised loss,
deterministic network) is compared with the best so far; an improvement of more than
``min_delta`` resets the patience counter, ``patience`` epochs without one stop training,
and the best weights are returned. A non-finite training or validation loss stops
training at once; the weights of the best finite epoch are kept and the epoch is
reported as ``TrainInfo.nan_epoch`` (-1 when none).

Monte-Carlo DropConnect inference (:func:`mc_predict`, sec. 2.4): for ``M`` passes with
independent masks, per row,

.. math::  \mu = \tfrac1M\sum_t \mu^{(t)},\quad
           \sigma^2_{alea,NN} = \tfrac1M\sum_t \mathrm{Var}^{(t)},\quad
           \sigma^2_{epi,NN} = \tfrac1{M-1}\sum_t (\mu^{(t)} - \mu)^2

where :math:`\mu^{(t)}` and :math:`\mathrm{Var}^{(t)}` are the family mean and variance of
pass ``t`` (Student-t: :math:`s^2\nu/(\nu-2)`; Laplace: :math:`2b^2`), mapped back to uT.

Deep ensemble x MC DropConnect (:class:`NetworkEnsemble`, e.g. the job's K cross-conformal fold
networks): the ``M`` passes are split over the ``K`` members (:func:`ensemble_passes`: ``M // K``
each, the first ``M mod K`` members one more, at least 2 each; member ``k`` draws its masks from
``seed + k``), so inference costs about one network's. The moments above are then taken over all ``M`` passes of
all members, exactly (:func:`pool_mc`): the epistemic variance is the sample variance of all
pass means, i.e. the within-member spread plus the spread between the members' means.

Size rule: a network whose parameter count per axis exceeds ``MAX_PARAMS_PER_ROW`` (10)
times the number of fitting rows (training rows minus the validation rows) is refused with
a ``ValueError`` naming ``width`` / ``hidden_layers`` (the job reports it as a config error): the
paper's 4 x 64 network (12.9k weights) needs at least 1.3k fitting rows. Fewer than
``MIN_VALIDATION_ROWS`` (20) validation rows make early stopping a coin toss and are refused
naming ``network.validation_fraction``.

References:
    Shetty & Marndi (2026). Metrology 6(3), 45, sections 2.4 and 3.6.
    Wan, L., Zeiler, M., Zhang, S., LeCun, Y. & Fergus, R. (2013). Regularization of neural
    networks using DropConnect. ICML.
    Tancik, M. et al. (2020). Fourier features let networks learn high frequency functions in
    low dimensional domains. NeurIPS.
    Mobiny, A. et al. (2021). DropConnect is effective in modeling uncertainty of Bayesian
    deep networks. Scientific Reports 11, 5458.

Modules, bottom to top: ``spec`` (:class:`NetworkSpec`, limits, activations), ``model`` (layers,
DropConnect, forward pass, Fourier features, head and loss), ``progress`` (training reports and
bars), ``train`` (the compiled epoch loop, threads, validation rows, :func:`fit_residual_network`),
``ensemble`` (:class:`NetworkEnsemble`), ``infer`` (:func:`mc_predict`, :func:`mc_samples`) and
``recalibration`` (:func:`recalibrate`). Every name is importable from this package.
"""

from bayesmag._src.core.network.spec import DTYPE, MAX_PARAMS_PER_ROW, MIN_VALIDATION_ROWS, VALIDATION_KINDS, FOURIER_STREAM, ACTIVATIONS, shape_settings, count_params, LEARN, NetworkSpec  # noqa: F401
from bayesmag._src.core.network.model import Dense, Params, init, DROP_TAIL, max_drops, keep_masks, drop_connect, apply, fourier_frequencies, embed, head_distribution, regularized_nll  # noqa: F401
from bayesmag._src.core.network.progress import TrainProgress, progress_bar, merged_reporter, merge_progress  # noqa: F401
from bayesmag._src.core.network.train import TrainInfo, TrainState, _Trainer, _trainer, build_trainer, TRAIN_CHUNK_EPOCHS, SCAN_UNROLL, _init_axes, _train_chunk, _axis_keys, _train_axes, training_threads, _train_parallel, Standardizer, ResidualNetwork, validation_rows, check_network_size, start_residual_network, fit_residual_network  # noqa: F401
from bayesmag._src.core.network.ensemble import NetworkEnsemble, ensemble_passes  # noqa: F401
from bayesmag._src.core.network.infer import MCPrediction, _mc_raw, _mc_passes, _mc_axes, pool_mc, mc_predict, mc_samples  # noqa: F401
from bayesmag._src.core.network.recalibration import RECALIBRATION_GRID, recalibrate  # noqa: F401

__all__ = ["Dense", "NetworkSpec", "Standardizer", "TrainInfo", "ResidualNetwork", "MCPrediction",
           "ACTIVATIONS", "MAX_PARAMS_PER_ROW", "MIN_VALIDATION_ROWS", "init", "apply", "drop_connect", "keep_masks", "max_drops",
           "count_params", "fourier_frequencies", "embed", "head_distribution", "regularized_nll", "build_trainer",
           "validation_rows", "TrainProgress", "TRAIN_CHUNK_EPOCHS", "progress_bar", "merge_progress", "merged_reporter", "LEARN", "shape_settings",
           "check_network_size", "start_residual_network", "fit_residual_network", "mc_predict", "mc_samples", "recalibrate", "VALIDATION_KINDS",
           "NetworkEnsemble", "ensemble_passes", "pool_mc"]
