"""PPU-style residual head: a small CNN on a frozen checkpoint's renders predicts per-pixel error
(after Galappaththige et al. 2026, predictive photometric uncertainty)."""
from __future__ import annotations

import logging
from dataclasses import dataclass

import torch
from torch import nn

from b3dgs.uq.regime import Predictive, UQRegime

log = logging.getLogger(__name__)


def render_features(module, camera) -> torch.Tensor:
    """(1, 7, H, W): rendered RGB, alpha, depth / its median, and RGB gradient magnitudes (x, y)."""
    with torch.no_grad():
        out = module.render_camera(camera)
        rgb = out.rgb.clamp(0, 1)
        depth = out.depth * (out.alpha > 0.5)
        med = depth[depth > 0].median() if bool((depth > 0).any()) else torch.ones((), device=depth.device)
        gx = torch.zeros_like(rgb[..., 0])
        gy = torch.zeros_like(rgb[..., 0])
        gx[:, 1:] = (rgb[:, 1:] - rgb[:, :-1]).abs().mean(-1)
        gy[1:, :] = (rgb[1:] - rgb[:-1]).abs().mean(-1)
        feats = torch.stack([rgb[..., 0], rgb[..., 1], rgb[..., 2], out.alpha, depth / med.clamp_min(1e-6), gx, gy])
    return feats.unsqueeze(0), rgb


class ResidualHead(nn.Module):
    """Three 3x3 convolutions (7 -> width -> width -> 1) predicting log σ² per pixel."""

    def __init__(self, width: int = 16):
        super().__init__()
        self.net = nn.Sequential(
            nn.Conv2d(7, width, 3, padding=1), nn.ReLU(),
            nn.Conv2d(width, width, 3, padding=2, dilation=2), nn.ReLU(),
            nn.Conv2d(width, 1, 3, padding=1),
        )
        nn.init.constant_(self.net[-1].bias, -6.0)

    def forward(self, x):
        return self.net(x)[:, 0]


@dataclass
class PPUHead(UQRegime):
    """Trains a residual head on the frozen checkpoint's training views with the Gaussian NLL of the
    per-channel residuals (one variance per pixel); the backbone is never updated.
    var = exp(head) + ``var_floor``: the floor keeps the NLL bounded below where a residual is exactly 0
    (e.g. a black background rendered black), which otherwise drives the head to -inf and the loss to NaN."""

    steps: int = 300
    lr: float = 5e-3
    width: int = 16
    seed: int = 0
    var_floor: float = 1e-8

    def fit(self, models, scene):
        super().fit(models, scene)
        m = self.models[0]
        g = torch.Generator().manual_seed(int(self.seed))
        torch.manual_seed(int(self.seed))
        self.head = ResidualHead(self.width).to(m.device)
        data = []
        for cam in scene.train:
            feats, rgb = render_features(m, cam)
            data.append((feats, (rgb - m.device_camera(cam).image).square().permute(2, 0, 1)))  # (3, H, W)
        opt = torch.optim.Adam(self.head.parameters(), lr=self.lr)
        loss = torch.full((), float("nan"), device=m.device)
        for it in range(self.steps):
            feats, r2 = data[int(torch.randint(len(data), (1,), generator=g))]
            v = torch.exp(self.head(feats)[0]) + self.var_floor
            loss = 0.5 * (torch.log(v) + r2 / v).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        self.final_loss = float(loss.detach())
        self.head.eval()

    @torch.no_grad()
    def predict(self, camera, generator=None):
        m = self.models[0]
        feats, rgb = render_features(m, camera)
        var = torch.exp(self.head(feats)[0]) + self.var_floor
        return Predictive(mean=rgb, var=var, epistemic=var, aleatoric=0.0)
