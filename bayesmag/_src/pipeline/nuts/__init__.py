r"""Full-Bayesian cross-check of the physics posterior with NumPyro NUTS.

The Levenberg-Marquardt fit (:func:`~bayesmag.fit_physics`) reports the Laplace
approximation :math:`\theta_i \sim \mathcal N(\hat\theta_i, \hat\Sigma_i)` of each output
axis :math:`i` (Shetty & Marndi 2026, sec. 2.2-2.3). This module samples the posterior the
approximation stands for, with the No-U-Turn Sampler (Hoffman & Gelman 2014) of NumPyro,
and says per axis whether the approximation is adequate.

**Model** (one axis; the three axes are independent, as in the row-wise LM fit):

.. math::

   y_k &\sim \mathcal D\big(f(x_k; \theta),\ \sigma\big), \quad k = 1..n, \\
   \theta_j &\sim \mathcal N(\hat\theta_j,\ (c\, \hat s_j)^2) \text{ independently}, \quad c = 100, \\
   \sigma &\sim \mathrm{HalfNormal}(\mathrm{sd}(y)), \qquad
   \nu \sim \mathrm{Gamma}(2, 0.1) \ \text{(Student-t only)},

with :math:`f` = :meth:`PhysicsModel.predict` -- the very function the LM fit minimises,
extra terms and input transforms included -- and :math:`\mathcal D` a family of the
likelihood registry (:mod:`bayesmag.likelihoods`: Normal by default, Laplace, Student-t, or
a user family; its ``to_numpyro`` distribution), :math:`\hat s_j` the LM standard error.
A family's shape fields (Student-t :math:`\nu`) are learned with the family's prior
(``ShapeParam.prior``) unless ``priors`` fixes them.

**Priors.** Centred at the LM estimate with 100 LM standard errors: weakly informative by
construction for every parameter whatever its units (a gain near 1, a thermal coefficient
near 1e-3 /C, an offset in uT). The prior adds :math:`10^{-4}` of the data precision in
each coordinate, so it moves posterior means and sds by less than about 1e-4 of an LM sd;
it exists to make the posterior proper, not to inform it. It uses the data twice (an
empirical-Bayes centre), which is harmless at this width and documented. Overrides go in
``[nuts] priors`` (:func:`parse_priors`): ``scale`` (the 100), a parameter name with an
absolute sd (``"Ks_x" = 0.1``, all axes) or ``{mean = ..., sd = ...}``, per-axis tables
(``y = {Ks_x = 0.1}``), ``sigma`` (HalfNormal scale of the noise, uT) and a shape field of
the family, e.g. ``df`` (fixes the Student-t degrees of freedom instead of learning them).

**Parametrisation.** With :math:`T_0 = 0` the S-Ks and O-Ko pairs are correlated beyond
:math:`|\rho| > 0.999` (the posterior is a needle), which makes NUTS on the raw parameters
take thousands of leapfrog steps per draw. We sample the whitened coordinates

.. math::  \theta = \hat\theta + L z, \qquad L L^T = \hat\Sigma_{\mathrm{white}}, \qquad
           \sigma = \hat\sigma \exp(u / \sqrt{2n}),

with the priors above written on :math:`\theta` and :math:`\sigma` (the map is linear with
a constant Jacobian for :math:`\theta`; the :math:`\sigma` Jacobian is added), so the
posterior is exactly the same; only the geometry NUTS sees changes. We chose whitening over
``dense_mass=True`` because the LM fit already delivers the covariance: the target is
near-isotropic from the first warm-up iteration, whereas a dense mass matrix has to be
learned from early warm-up draws that mix badly in a condition-number-1e12 posterior. A
diagonal mass matrix is still adapted on top. ``parametrisation="scaled"`` (per-parameter
standardisation only) with ``dense_mass=True`` is available for comparison
(``benchmarks/bench_nuts.py --parametrisation scaled --dense-mass``).

**Cross-check.** Per parameter, :math:`(\bar\theta_\mathrm{NUTS} - \hat\theta)/\hat s`
and :math:`\mathrm{sd}_\mathrm{NUTS}/\hat s`, the largest correlation differences and the
eigenvalues of the NUTS covariance in whitened coordinates (all 1 when the Laplace
approximation is exact). For the linear Gaussian model the exact posterior is a
multivariate t with :math:`n-p` degrees of freedom, so the expected sd ratio is
:math:`\sqrt{(n-p)/(n-p-2)} \approx 1`; deviations beyond :data:`MEAN_DIFF_TOL` and
:data:`SD_RATIO_RANGE` mean the Laplace approximation (or the sampler) is wrong there.

The reference is the *white* LM covariance :math:`s^2 (J^T J)^{-1}` because it is the
Laplace approximation of this independent-error posterior; if the fit was made with
``covariance="ar1"``/``"newey_west"`` the cross-check also reports the sd ratio against
that covariance (NUTS with independent errors is then expected to be narrower).

References:
    Hoffman, M. D. & Gelman, A. (2014). The No-U-Turn Sampler. JMLR 15, 1593-1623.
    Vehtari, A., Gelman, A., Simpson, D., Carpenter, B. & Bürkner, P.-C. (2021).
    Rank-normalization, folding, and localization: an improved R-hat. Bayesian Analysis 16(2).
    Vehtari, A., Gelman, A. & Gabry, J. (2017). Practical Bayesian model evaluation using
    leave-one-out cross-validation and WAIC. Statistics and Computing 27, 1413-1432.
    Juárez, M. A. & Steel, M. F. J. (2010). Model-based clustering of non-Gaussian panel
    data based on skew-t distributions. JBES 28(1) (the Gamma(2, 0.1) prior on nu).
    Shetty & Marndi (2026). Hybrid physics + heteroscedastic-network magnetometer calibration.

Modules (one concept each; ``constants`` at the bottom): ``priors``, ``model`` (the numpyro
model and its whitening), ``sampler``, ``idata`` (ArviZ InferenceData and summary),
``crosscheck``, ``result``, ``run`` (:func:`run_nuts`) and ``compare`` (LOO). Files and figures are
the application layer's (``bayesmag._src.app.nuts_outputs``, ``nuts_plots``), as is the job's
``[nuts]`` check (``bayesmag._src.app.nuts_stage``).
"""

from bayesmag._src.pipeline.nuts.compare import compare_models, loo
from bayesmag._src.pipeline.nuts.constants import (
    CHAIN_METHODS,
    DEFAULT_PRIOR_SCALE,
    EBFMI_MIN,
    ESS_MIN,
    INIT_RADIUS,
    MEAN_DIFF_TOL,
    MIN_CHAINS,
    MIN_DRAWS,
    PARAMETRISATIONS,
    RHAT_MAX,
    SD_RATIO_RANGE,
    NutsWarning,
)
from bayesmag._src.pipeline.nuts.crosscheck import crosscheck
from bayesmag._src.pipeline.nuts.idata import JOINT_STATS, build_idata, summary_frame
from bayesmag._src.pipeline.nuts.model import NutsProblem, build_problem, nuts_model
from bayesmag._src.pipeline.nuts.priors import NutsPriors, parse_priors
from bayesmag._src.pipeline.nuts.result import NutsResult
from bayesmag._src.pipeline.nuts.run import run_nuts
from bayesmag._src.pipeline.nuts.sampler import NutsDraws, check_settings, sample_nuts

__all__ = [
    "NutsPriors", "parse_priors", "NutsProblem", "build_problem", "nuts_model", "NutsDraws", "sample_nuts",
    "NutsResult", "run_nuts", "crosscheck", "loo", "compare_models", "build_idata",
    "summary_frame", "check_settings", "NutsWarning", "CHAIN_METHODS", "PARAMETRISATIONS", "JOINT_STATS",
    "RHAT_MAX", "ESS_MIN", "MEAN_DIFF_TOL", "SD_RATIO_RANGE", "MIN_DRAWS", "MIN_CHAINS", "DEFAULT_PRIOR_SCALE",
    "INIT_RADIUS", "EBFMI_MIN",
]
