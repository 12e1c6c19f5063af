"""NIW geometry posterior over each Gaussian's mean and covariance (paper Eq. 1-3)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Optional

import torch
from torch import Tensor

from b3dgs.plugin import PosteriorBlock
from b3dgs.posterior import niw as niwm
from b3dgs.posterior.guards import guard
from b3dgs.render.projection import covariance_3d

D = 3


@dataclass
class NIWBlock(PosteriorBlock):
    """NIW(m_n, κ_n, ν_n, S_n) over (μ_k, Σ_k) for every Gaussian k, updated in closed form (Eq. 2-3).

    Prior: m0 = the Gaussian's centre at birth, κ0, ν0 = D + 2, S0 = Σ_birth (ν0 - D - 1) so that
    E[Σ] under the prior is the covariance at birth.

    Renderer-derived summaries (the paper's online path):
    - N̂_k: EMA over training steps of o_k √(∏_d E[Σ_k]_dd) for the Gaussians visible in the step's
      view, normalised so that the per-step values sum to the view's effective pixel count
      (Σ_p α_p) times the number of training views; N̂ therefore sums to about the effective pixel
      count of all training views;
    - x̄_k: the current centre; C_k = 0.
    The posterior is recomputed from the prior and these summaries every ``update_every`` steps
    (Eq. 2-3 are a function of the summaries, so this is exact for the online path).

    Children of a clone or split: the prior is re-centred at the child's birth (m0 = its centre,
    S0 from its covariance) and the child inherits half its parent's N̂ (the parent's support is
    shared by the two), so a child is neither maximally uncertain nor over-confident.

    Posterior samples (``sample``) replace exactly two rendering parameters:
    - the centre: μ^(s) ~ N(m_n, Σ^(s)/κ_n);
    - the covariance (``cov_mode="relative"``, default): Σ_render^(s) = L_k W^(s) L_kᵀ where
      L_k L_kᵀ is the rendered (point-estimate) covariance and W^(s) = E[Σ]^{-1/2} Σ^(s) E[Σ]^{-1/2}
      is the IW draw whitened by its mean (its spread depends on ν_n only); ``"absolute"`` renders
      Σ^(s) itself, ``"none"`` keeps the rendered covariance.
    Opacity and colour are untouched. The posterior mean (μ = m_n, W = I) renders the point estimate
    up to the κ0/(κ0+N̂) pull towards m0.

    ``plugin_noise``: track the plug-in residual MSE σ̂² (EMA) and offer it as the aleatoric
    variance, as in the paper's NIW rows; turn it off when a NoiseBlock supplies E[σ²].

    ``count_scale`` (c, default 1 = the paper): the posterior refresh uses c·N̂_k in place of N̂_k in
    Eq. 2-3 (the stored summary ``state["N"]`` is unchanged). Because N̂ is normalised to the effective
    pixel count it is large, and the posterior concentrates as E[Σ] ≈ S0/(c N̂), Var[μ] ≈ S0/(c N̂)²
    while c N̂ ≫ ν0; c < 1 widens the posterior (Var[μ] ∝ 1/c²) and pulls m_n towards m0 by
    κ0/(κ0 + c N̂). A trained run's posterior can be re-evaluated at another c without retraining: set
    ``count_scale`` on the loaded block (every use of the posterior refreshes it from the summaries).
    """

    needs_residuals: ClassVar[bool] = True  # reads info["sq_err_sum"]
    changes_training: ClassVar[bool] = False  # it reads summaries; splats, optimizers, gradients untouched

    kappa0: float = 0.01
    nu0: float = 5.0
    ema: float = 0.99
    update_every: int = 100
    t_niw: Optional[int] = None  # None: 0 (active from the start)
    cov_mode: str = "relative"
    plugin_noise: bool = True
    mse_ema: float = 0.99
    sampler_backend: str = "auto"  # posterior draws: "cpu" (C++, one pass), "torch" (reference) or "auto"
    count_scale: float = 1.0  # c in N̂ <- c·N̂ at the posterior refresh (Eq. 2-3); 1 = the paper

    def check_sanity(self, max_steps: int = 0, **kw) -> None:
        if self.kappa0 <= 0:
            raise ValueError("posterior.niw.kappa0 must be > 0")
        if self.nu0 <= D + 1:
            raise ValueError(f"posterior.niw.nu0 must be > D + 1 = {D + 1} for a proper prior with finite E[Σ]")
        if not 0 <= self.ema < 1:
            raise ValueError("posterior.niw.ema must be in [0, 1)")
        if self.update_every < 1:
            raise ValueError("posterior.niw.update_every must be >= 1")
        if self.cov_mode not in ("relative", "absolute", "none"):
            raise ValueError("posterior.niw.cov_mode must be relative | absolute | none")
        if self.sampler_backend not in ("auto", "cpu", "torch"):
            raise ValueError("posterior.niw.sampler_backend must be auto | cpu | torch")
        if not (isinstance(self.count_scale, (int, float)) and 0 < float(self.count_scale) < float("inf")):
            raise ValueError(f"posterior.niw.count_scale must be a finite number > 0, got {self.count_scale}")

    # ------------------------------------------------------------------ state
    def _prior_for(self, splats, rows: Optional[Tensor] = None):
        means = splats["means"].detach()
        cov = covariance_3d(splats["quats"].detach(), splats["scales"].detach())
        if rows is not None:
            means, cov = means[rows], cov[rows]
        nu0 = torch.full((means.shape[0],), float(self.nu0), dtype=torch.float64, device=means.device)
        return means.double(), niwm.prior_scale_for_expected_cov(cov.double(), nu0)

    def initialize_state(self, *, splats, scene, info):
        m0, S0 = self._prior_for(splats)
        n, dev = m0.shape[0], m0.device
        st = {
            "m0": m0, "S0": S0, "N": torch.zeros(n, dtype=torch.float64, device=dev),
            "ediag": torch.diagonal(S0, dim1=-2, dim2=-1) / (self.nu0 - D - 1),
            "mse": torch.tensor(0.0, dtype=torch.float64, device=dev),
            "mse_n": torch.tensor(0.0, dtype=torch.float64, device=dev),
            "n_views": torch.tensor(float(len(scene.train)) if scene is not None else 1.0, device=dev),
        }
        self._refresh(st, splats)
        return st

    def _t_niw(self, info) -> int:
        return int(self.t_niw) if self.t_niw is not None else 0

    # ------------------------------------------------------------------ updates
    @torch.no_grad()
    def step_post_backward(self, *, splats, optimizers, state, step, info):
        # tensor arithmetic only (no host synchronisation per step on a GPU)
        if self.plugin_noise:
            mse = info["sq_err_sum"].double() / max(int(info["num_values"]), 1)
            state["mse"] = self.mse_ema * state["mse"] + (1 - self.mse_ema) * mse
            state["mse_n"] = self.mse_ema * state["mse_n"] + (1 - self.mse_ema)
        if step < self._t_niw(info):
            return
        vis = info["per_gaussian"]["radii"][0] > 0
        o = torch.sigmoid(splats["opacities"].detach()).double() * vis
        raw = o * torch.sqrt(torch.clamp(state["ediag"].prod(-1), min=0.0))
        total = raw.sum()
        eff_pixels = info["render"].alpha.detach().sum().double()
        ok = (total > 0) & (eff_pixels > 0)
        target = raw * torch.where(ok, eff_pixels * self.train_views(state, info) / torch.where(ok, total, 1.0), 0.0)
        keep = torch.where(vis.any(), self.ema, 1.0)  # no visible Gaussian: the counts stay as they are
        state["N"].mul_(keep).add_((1 - keep) * target)
        if step % self.update_every == 0:
            self._refresh(state, splats)

    @torch.no_grad()
    def _refresh(self, state, splats) -> None:
        """Eq. 2-3 with N̂ ← count_scale·N̂, x̄ = current centre and C = 0."""
        xbar = splats["means"].detach().double()
        n = xbar.shape[0]
        dev = xbar.device
        k0 = torch.full((n,), float(self.kappa0), dtype=torch.float64, device=dev)
        nu0 = torch.full((n,), float(self.nu0), dtype=torch.float64, device=dev)
        C = torch.zeros(n, D, D, dtype=torch.float64, device=dev)
        m_n, k_n, nu_n, S_n = niwm.niw_update(state["m0"], k0, nu0, state["S0"],
                                                 state["N"] * float(self.count_scale), xbar, C)
        state["m_n"], state["kappa_n"], state["nu_n"], state["S_n"] = m_n, k_n, nu_n, S_n
        state["ediag"] = torch.diagonal(niwm.expected_cov(S_n, nu_n), dim1=-2, dim2=-1).clone()

    @torch.no_grad()
    def on_topology(self, *, splats, optimizers, state, step, info):
        fresh = info["fresh"]
        if not bool(fresh.any()):
            return
        rows = torch.nonzero(fresh, as_tuple=False).flatten()
        m0, S0 = self._prior_for(splats, rows)
        state["m0"][rows] = m0
        state["S0"][rows] = S0
        state["N"][rows] = 0.5 * state["N"][rows]
        # the posterior (m_n, S_n, ...) of new rows is refreshed at the next scheduled update or on use

    # ------------------------------------------------------------------ posterior use
    def posterior(self, state, splats) -> dict[str, Tensor]:
        self._refresh(state, splats)
        return {k: state[k] for k in ("m_n", "kappa_n", "nu_n", "S_n")}

    @torch.no_grad()
    def sample(self, *, splats, state, n, generator, params, info):
        return self.sampler(splats=splats, state=state)(n, generator, params)

    @torch.no_grad()
    def sampler(self, *, splats, state):
        """Posterior draws of the centre and (per ``cov_mode``) the rendered covariance; the posterior
        refresh and the Cholesky factors are computed once per sampler."""
        post = self.posterior(state, splats)
        prep = niwm.niw_sampler(post["m_n"], post["kappa_n"], post["nu_n"], post["S_n"])
        dtype = splats["means"].dtype
        if self.cov_mode == "relative":
            # W = E[Σ]^{-1/2} Σ E[Σ]^{-T/2} = c (A Aᵀ)^{-1}, c = ν_n - D - 1 (see draw_niw); rendered as
            # L W Lᵀ = YᵀY with Y = √c A^{-1} Lᵀ and L the rendered covariance's Cholesky factor
            sqrt_c = (post["nu_n"] - D - 1).clamp_min(niwm.EXPECTED_COV_DENOM_EPS).sqrt()[None, :, None, None]
            cov_r = covariance_3d(splats["quats"].detach(), splats["scales"].detach()).double()
            LrT = niwm.safe_cholesky(cov_r).transpose(-1, -2).unsqueeze(0)

        ext = self._sampling_extension(splats["means"].device)
        if ext is not None:
            mode = {"none": 0, "absolute": 1, "relative": 2}[self.cov_mode]
            empty = torch.zeros(0, dtype=torch.float64)
            args = (prep.m.contiguous(), prep.kappa.contiguous(), prep.nu.contiguous(), prep.L.contiguous(),
                    LrT[0].contiguous() if mode == 2 else empty, sqrt_c.reshape(-1).contiguous() if mode == 2 else empty)

        @torch.no_grad()
        def draw(n, generator, params):
            out = dict(params)
            if ext is not None:
                seed = int(torch.randint(0, 2**62, (1,), generator=generator))
                means, covs, floored = ext.niw_draw(*args, n, mode, niwm.BARTLETT_CHI2_FLOOR, seed,
                                                    dtype == torch.float64, torch.get_num_threads())
                guard("sample_niw.bartlett_chi2_floor", int(floored))
                out["means"] = means
                if mode:
                    out["covars"] = covs
                return out
            mu, X, A = niwm.draw_niw(prep, n, generator)
            out["means"] = mu.to(dtype)
            if self.cov_mode != "none":
                Y = X if self.cov_mode == "absolute" else niwm.tril_solve(A, LrT) * sqrt_c  # Σ = YᵀY
                out["covars"] = (Y.unsqueeze(-1) * Y.unsqueeze(-2)).sum(-3).to(dtype)  # symmetric by construction
            return out

        return draw

    def _sampling_extension(self, device: torch.device):
        """The C++ extension for ``sampler_backend`` cpu/auto on CPU tensors; auto uses the torch path on
        other devices, and falls back to it (with one warning naming the compiler error) if the build failed."""
        if self.sampler_backend == "torch" or (self.sampler_backend == "auto" and device.type != "cpu"):
            return None
        from b3dgs.render._ext import load_extension, warn_fallback

        try:
            return load_extension()
        except RuntimeError as e:
            if self.sampler_backend == "cpu":
                raise
            warn_fallback(e, "the NIW posterior sampler uses its float64 torch path")
            return None

    @torch.no_grad()
    def condition_on_view(self, *, splats, state, weight_sums):
        """The posterior after one more view's pseudo-observations (acquisition, issue 22): n_k = c·w_k
        observations at the current centre (x̄_k = μ_k, C_k = 0), the closed-form update of the paper's NIW
        appendix applied to the current posterior. The summaries already sit at μ_k with C = 0, and two such
        batches at one point combine into one of summed count (conjugacy), so this is N̂ ← N̂ + w on a copy of
        the state, refreshed."""
        st = dict(state)
        st["N"] = state["N"] + weight_sums.to(state["N"].dtype).to(state["N"].device).clamp_min(0.0)
        self._refresh(st, splats)
        return st

    @torch.no_grad()
    def posterior_mean(self, *, splats, state, params):
        out = dict(params)
        out["means"] = self.posterior(state, splats)["m_n"].to(splats["means"].dtype)
        return out

    def aleatoric_variance(self, *, state):
        if not self.plugin_noise or float(state["mse_n"]) <= 0:
            return None
        return float(state["mse"] / state["mse_n"])  # bias-corrected EMA of the residual MSE

    @torch.no_grad()
    def export(self, *, splats=None, state):
        if splats is not None:
            self._refresh(state, splats)
        var_mu = niwm.mean_variance(state["S_n"], state["nu_n"], state["kappa_n"])
        return {
            "niw_pos_var": (torch.diagonal(var_mu, dim1=-2, dim2=-1).sum(-1) / D).float(),
            "niw_kappa": state["kappa_n"].float(),
            "niw_nu": state["nu_n"].float(),
        }

    def summary(self, *, state):
        ex = self.export(splats=None, state=state)
        return {
            "mean_count": float(state["N"].mean()) if state["N"].numel() else 0.0,
            "median_pos_std": float(ex["niw_pos_var"].sqrt().median()) if state["N"].numel() else 0.0,
            "sigma2_plugin": self.aleatoric_variance(state=state),
        }
