"""Simulated magnetometer with known parameters: seeded designs and named distortion effects.

See :mod:`bayesmag._src.core.simulate` for the model (the inverse of the paper's thermo-affine
calibration, section 4.1) and the effect catalogue (:data:`EFFECTS`).
"""

from bayesmag._src.core.simulate import (
    EFFECTS,
    Conditions,
    Effect,
    TrueParams,
    draw_campaign,
    draw_iid,
    get_effect,
    simulate,
    simulate_from_config,
)
from bayesmag._src.core.field_sim import FieldCampaign, FieldTruth, MOTIONS, simulate_field, simulate_field_sessions

__all__ = [
    "TrueParams",
    "Conditions",
    "simulate",
    "simulate_from_config",
    "draw_iid",
    "draw_campaign",
    "Effect",
    "get_effect",
    "EFFECTS",
    "simulate_field",
    "simulate_field_sessions",
    "FieldCampaign",
    "FieldTruth",
    "MOTIONS",
]
