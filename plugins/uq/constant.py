"""Constant-variance baseline: the plug-in σ̂² at every pixel, no posterior and no samples."""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Optional

import torch

from b3dgs.errors import B3dgsError
from b3dgs.uq.calibration import training_mse
from b3dgs.uq.regime import Predictive, UQRegime


@dataclass
class ConstantUQ(UQRegime):
    """var_p = σ̂² for every pixel of every view, where σ̂² is the model's training-residual MSE: the mean
    over the training views' pixels and RGB values of (render − image)², computed in ``fit`` from the
    model's own renders of ``scene.train`` (``max_train_views`` of them, spread evenly, when set). It
    needs no posterior, so it applies to any model, standard included, and it is the reference that
    shows what a posterior adds beyond a constant: the aleatoric term of ``uq=native`` is the same kind
    of plug-in (NIW's EMA of the training residual MSE). The prediction is the point-estimate render;
    the epistemic part is identically 0 (``has_epistemic`` False), so every pixel ranks the same and its
    AUSE is that of a random order with ties."""

    has_epistemic: ClassVar[bool] = False
    samples: ClassVar[int] = 0  # no Monte-Carlo draws (not a setting: nothing to sample)
    max_train_views: Optional[int] = None  # training views rendered for σ̂² (None: all)

    def validate(self, **kwargs):
        if self.max_train_views is not None and self.max_train_views < 1:
            raise B3dgsError(f"uq.constant.max_train_views must be >= 1 or null, got {self.max_train_views}",
                             fix="pass uq.constant.max_train_views as a positive count, or null for every training "
                                 "view")

    def fit(self, models, scene):
        super().fit(models, scene)
        from b3dgs.data.scene import select_evenly

        cams = list(scene.train)
        cams = [cams[i] for i in select_evenly(len(cams), self.max_train_views)]
        self.sigma2 = training_mse(self.models[0], cams)
        self.fit_info.update(sigma2=self.sigma2, sigma2_source="training-residual MSE of the renders",
                             sigma2_views=len(cams))

    @torch.no_grad()
    def predict(self, camera, generator=None):
        mean = self.models[0].render_eval(camera)
        zero = torch.zeros(mean.shape[:2], dtype=mean.dtype, device=mean.device)
        return Predictive(mean=mean, var=zero + self.sigma2, epistemic=zero, aleatoric=self.sigma2)
