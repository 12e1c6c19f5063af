"""Native posterior uncertainty calibrated on held-out calibration views (``data.calib_every``).

Both regimes draw u_p exactly as ``uq=native`` (paper Eq. 4) and only rescale the predictive variance
with scalars fitted on ``scene.calib`` -- training views held out of training, never test views -- so
the pixel ranking of every view is that of u_p, unchanged by the calibration. A run without calibration
views is refused with the fix (``data.calib_every=16``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from b3dgs.errors import B3dgsError
from b3dgs.uq.calibration import calibration_views, conformal_scale, fit_scale_and_level
from b3dgs.uq.native import NativeRegime
from b3dgs.uq.regime import Predictive


@dataclass
class _CalibratedNative(NativeRegime):
    seed: int = 0  # the calibration views' posterior draws use their own generator, seeded with this

    def _calibration_data(self):
        """Per calibration view: u_p (H·W,) and the residuals gt − render (H·W, 3), float64 numpy."""
        cams = calibration_views(self.scene, self.regime_name)
        gen = torch.Generator().manual_seed(int(self.seed))
        us, rs = [], []
        for cam in cams:
            mean, u = self.spread(cam, gen)
            us.append(u.detach().double().cpu().numpy().reshape(-1))
            rs.append((cam.image.double() - mean.detach().double().cpu()).numpy().reshape(-1, 3))
        self.fit_info["calib_views"] = [c.name for c in cams]
        return np.concatenate(us), np.concatenate(rs)


@dataclass
class NativeCalibratedUQ(_CalibratedNative):
    """var_p = s·u_p + a with (a, s) the Gaussian maximum-likelihood fit on the calibration views'
    residuals (:func:`b3dgs.uq.calibration.fit_scale_and_level`): ``s`` scales the epistemic part, ``a``
    replaces the training plug-in σ̂² by the held-out residual level. ``fit_scale=false`` fits ``a``
    alone (s = 1). s > 0, so the pixel ranking (AUSE, Spearman ρ) is that of u_p."""

    regime_name = "native_calibrated"
    fit_scale: bool = True  # False: fit the aleatoric level a alone (s = 1)

    def fit(self, models, scene):
        super().fit(models, scene)
        u, r = self._calibration_data()
        fit = fit_scale_and_level(u, (r ** 2).sum(-1), channels=3, fit_scale=self.fit_scale)
        self.a, self.s = float(fit["a"]), float(fit["s"])
        self.fit_info.update({f"fit_{k}": v for k, v in fit.items()})
        self.fit_info.update(a=self.a, s=self.s, aleatoric_ratio=self.a / self.sigma2 if self.sigma2 > 0 else None)

    @torch.no_grad()
    def predict(self, camera, generator=None):
        mean, u = self.spread(camera, generator)
        epi = self.s * u
        return Predictive(mean=mean, var=epi + self.a, epistemic=epi, aleatoric=self.a)


@dataclass
class NativeConformalUQ(_CalibratedNative):
    """Split-conformal intervals around the native prediction. Score of a calibration (pixel, channel):
    t = |gt − render| / √(u_p + σ̂²), σ̂² the training plug-in (a normaliser fixed before the calibration
    data are seen); q = the ⌈(n+1)·level⌉-th smallest of the n scores; var_p = (q / z_level)²·(u_p + σ̂²),
    so the reported Gaussian interval at ``level`` is exactly ±q·√(u_p + σ̂²).

    Guarantee: if the calibration scores and a test score are exchangeable, that interval covers the
    test residual with probability ≥ ``level`` (marginally, over calibration and test draws). Here the
    calibration views are a fixed every-n-th subset and pixels of one view are dependent, so this is
    the guarantee of the idealised exchangeable setting; the test views measure the realised coverage.
    Only the ``level`` interval carries it: the other levels of the reliability curve (ECE) are the
    same variance read as Gaussian. One scalar, so the ranking is that of u_p."""

    regime_name = "native_conformal"
    level: float = 0.95

    def validate(self, **kwargs):
        super().validate(**kwargs)
        if not 0 < self.level < 1:
            raise B3dgsError(f"uq.native_conformal.level must be in (0, 1), got {self.level}",
                             fix="pass uq.native_conformal.level strictly between 0 and 1, e.g. 0.95")

    def fit(self, models, scene):
        super().fit(models, scene)
        u, r = self._calibration_data()
        sd = np.broadcast_to(np.sqrt(u + self.sigma2)[:, None], r.shape)
        ar = np.abs(r)
        # as in the metrics: 0/0 -> 0 (inside any interval), x/0 -> inf (outside every interval)
        scores = np.where(sd > 0, ar / np.where(sd > 0, sd, 1.0), np.where(ar > 0, np.inf, 0.0)).reshape(-1)
        conf = conformal_scale(scores, self.level)
        if not np.isfinite(conf["q"]):
            raise B3dgsError(f"uq=native_conformal: the {conf['rank']}-th smallest of the {conf['n']} calibration "
                             "scores is infinite (residuals where u_p + σ̂² = 0: a run without the plug-in σ̂², "
                             "posterior.niw.plugin_noise=false, or too few calibration pixels)",
                             fix="train with posterior.niw.plugin_noise=true, or hold out more calibration views "
                                 "(a smaller data.calib_every, e.g. 8)")
        self.k = float(conf["multiplier"])
        self.fit_info.update({f"conformal_{k}": v for k, v in conf.items()})

    @torch.no_grad()
    def predict(self, camera, generator=None):
        mean, u = self.spread(camera, generator)
        return Predictive(mean=mean, var=self.k * (u + self.sigma2), epistemic=self.k * u,
                          aleatoric=self.k * self.sigma2)
