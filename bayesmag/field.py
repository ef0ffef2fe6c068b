"""Field calibration: scalar-reference and Earth-field (constant magnitude) calibration with honest uncertainty.

See docs/field.md. The measurement models (:class:`Vector`, :class:`Scalar`, :class:`Constant`) are one
extension point; :func:`fit_field` fits the thermo-affine sensor model against any of them.

Example:
  >>> from bayesmag.simulate import simulate_field
  >>> c = simulate_field("dance", n=600, seed=0)
  >>> fit = fit_field(c.data.b_meas, c.data.temperature, c.f_ref, Scalar())
  >>> fit.model.param_names[:3]
  ('S_xx', 'S_xy', 'S_xz')
"""

from bayesmag._src.core.field import (INVARIANT_NAMES, FieldFit, FieldModel, FieldPrior, direction_coverage,
                                      field_target, fit_field, gauge_form, gaussian_scores, heading,
                                      heading_with_uncertainty, invariants)
from bayesmag._src.core.field_calibration import FieldCalibration
from bayesmag._src.core.measurement import MEASUREMENTS, Constant, MeasurementModel, Scalar, Vector, measurement_from_spec
from bayesmag._src.pipeline.field_stage import magnitude_transfer, run_field_stage

__all__ = ["MeasurementModel", "Vector", "Scalar", "Constant", "MEASUREMENTS", "measurement_from_spec",
           "FieldModel", "FieldPrior", "FieldFit", "fit_field", "field_target", "invariants", "INVARIANT_NAMES",
           "direction_coverage", "gauge_form", "heading", "heading_with_uncertainty", "gaussian_scores",
           "FieldCalibration", "magnitude_transfer", "run_field_stage"]
