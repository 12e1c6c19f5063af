"""Uncertainty quantification metrics (:mod:`b3dgs.uq.metrics`) and plots (:mod:`b3dgs.uq.plots`).

Only the metrics are imported here; import :mod:`b3dgs.uq.plots` explicitly (it pulls in matplotlib).
"""
from b3dgs.uq.metrics import (
    ause,
    calibration,
    coverage,
    evaluate_view,
    gaussian_nll,
    per_pixel_errors,
    sparsification,
    spearman_rho,
    summarize,
    to_jsonable,
)

__all__ = ["ause", "calibration", "coverage", "evaluate_view", "gaussian_nll", "per_pixel_errors", "sparsification",
           "spearman_rho", "summarize", "to_jsonable"]
