"""Sessions as exchangeable groups: the hierarchical (per-run random effects) transfer model."""

from bayesmag._src.pipeline.sessions.hierarchical import (DEFAULT_EFFECTS, SessionPosterior, fit_laplace, fit_nuts,
                                                          fit_sessions, hierarchical_transfer, loro_elpd,
                                                          run_stats)

__all__ = ["DEFAULT_EFFECTS", "SessionPosterior", "fit_laplace", "fit_nuts", "fit_sessions", "hierarchical_transfer", "loro_elpd", "run_stats"]
