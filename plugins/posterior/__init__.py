"""Posterior blocks of Bayesian 3DGS, each module holding its block and the pure, batched math it uses.

Modules: niw (NIWBlock; Eq. 1-3 and samples for Eq. 4), noise (NoiseBlock; inverse-gamma sigma^2), dp
(DPBlock; stick-breaking Eq. 5 and activity gate), opacity and color (their shared math, approximate
opacity/colour refinements, lives in :mod:`b3dgs.appearance`). The math is re-exported here; numerical guards are
counted in :mod:`b3dgs.numerics`.
"""

from b3dgs.appearance import (
    SH_C0,
    color_posterior_mean,
    color_posterior_var,
    dc_var_to_rgb_var,
    logit_normal_moments,
    opacity_beta_moment_match,
    opacity_fisher_var,
    opacity_to_logit,
    rgb_var_to_dc_var,
)
from b3dgs.dp import (
    activity_posterior,
    cavi_stick_update,
    dp_posterior,
    expected_log_pi,
    expected_pi,
    prune_threshold,
    stick_order,
)
from .niw import (
    expected_cov,
    mean_variance,
    niw_batch_stats,
    niw_update,
    position_variance,
    posterior_mean_params,
    prior_scale_for_expected_cov,
    safe_cholesky,
    sample_niw,
)
from .noise import ig_mean, ig_mode, ig_sample, ig_update, ig_update_ema, ig_var

__all__ = ["SH_C0", "activity_posterior", "cavi_stick_update", "color_posterior_mean", "color_posterior_var",
           "dc_var_to_rgb_var", "dp_posterior", "expected_cov", "expected_log_pi", "expected_pi", "ig_mean", "ig_mode",
           "ig_sample", "ig_update", "ig_update_ema", "ig_var", "logit_normal_moments", "mean_variance",
           "niw_batch_stats", "niw_update", "opacity_beta_moment_match", "opacity_fisher_var", "opacity_to_logit",
           "position_variance", "posterior_mean_params", "prior_scale_for_expected_cov", "prune_threshold",
           "rgb_var_to_dc_var", "safe_cholesky", "sample_niw", "stick_order"]
