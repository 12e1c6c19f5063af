"""NIW geometry posterior over each Gaussian's mean and covariance (paper Eq. 1-3): the pure batched math
(Murphy 2012, Sec. 4.6.3; tested against textbook formulas in tests/test_posterior_math.py) and the block
(:class:`NIWBlock`) that feeds it renderer-derived counts.

All functions are batched over K Gaussians with dimension D (D=3 in 3DGS), compute in float64 internally and
return the dtype of their main input. Numerical guards (floors, jitter) are counted in :mod:`b3dgs.numerics`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar, Optional, Tuple, Union

import torch
from torch import Tensor

from b3dgs.device import randn
from b3dgs.errors import B3dgsError, check_field, did_you_mean, field_default
from b3dgs.fisher import FisherAccumulator
from b3dgs.numerics import float_dtype as _out_dtype
from b3dgs.numerics import guard, guard_fill, safe_cholesky, sym as _sym, zero_invalid
from b3dgs.numerics import scalar_or_vector as _vec
from b3dgs.plugin import PosteriorBlock, ViewAccumulator
from b3dgs.render.projection import covariance_3d


Scalar = Union[float, int, torch.Tensor]

D = 3  # the dimension of a Gaussian's centre

#: Floor on nu_n - D - 1 in E[Sigma] = S_n / (nu_n - D - 1). With nu_n within 1e-3 of D+1 the
#: posterior mean of Sigma is (nearly) infinite; the floor caps E[Sigma] at 1e3 * S_n.
EXPECTED_COV_DENOM_EPS = 1e-3
#: Floor on kappa_n when dividing by it (kappa_n = kappa0 + N > 0 for a valid prior).
KAPPA_FLOOR = 1e-12
#: Floor on the Bartlett chi-square draws (only reachable for nu close to D-1).
BARTLETT_CHI2_FLOOR = 1e-30

_F64 = torch.float64


# ----------------------------------------------------------------------------- shape helpers
def _kd(name: str, x: torch.Tensor) -> Tuple[int, int]:
    if not isinstance(x, torch.Tensor) or x.ndim != 2:
        shape = tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
        raise B3dgsError(f"{name}: expected a (K, D) tensor, got {shape}",
                         fix=f"pass {name} as a torch tensor with one row per Gaussian: shape (K, D), e.g. (N, 3) "
                             "for centres")
    return int(x.shape[0]), int(x.shape[1])


def _vecD(name: str, x: torch.Tensor, K: int, D: int) -> torch.Tensor:
    if not isinstance(x, torch.Tensor) or tuple(x.shape) != (K, D):
        shape = tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
        raise B3dgsError(f"{name}: expected shape ({K}, {D}), got {shape}",
                         fix=f"pass {name} as a torch tensor of shape ({K}, {D}): one D-vector per Gaussian, rows "
                             "matching the other arguments")
    return x.to(_F64)


def _mat(name: str, x: torch.Tensor, K: int, D: int) -> torch.Tensor:
    if not isinstance(x, torch.Tensor) or tuple(x.shape) != (K, D, D):
        shape = tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
        raise B3dgsError(f"{name}: expected shape ({K}, {D}, {D}), got {shape}",
                         fix=f"pass {name} as a torch tensor of shape ({K}, {D}, {D}): one symmetric DxD matrix per "
                             "Gaussian")
    return x.to(_F64)


def _require_finite(name: str, x: torch.Tensor) -> None:
    if not bool(torch.isfinite(x).all()):
        raise B3dgsError(f"{name}: contains NaN/Inf",
                         fix=f"pass a finite {name}; if training produced it, the splats diverged: lower the "
                             "learning rates or rerun with b3dgs.debug=true to find the step")


# ----------------------------------------------------------------------------- conjugate update
def niw_update(m0: torch.Tensor, kappa0: Scalar, nu0: Scalar, S0: torch.Tensor, N: Scalar, xbar: torch.Tensor,
               C: Optional[torch.Tensor] = None) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Conjugate NIW update (Eq. 2-3) for effective count N >= 0, mean xbar and scatter C.

    Shapes: m0, xbar (K,D); kappa0, nu0, N (K,) or scalar; S0, C (K,D,D). C=None means C=0
    (the paper's online path). Computed as convex weights kappa0/kappa_n, N/kappa_n and
    kappa0*N/kappa_n = kappa0*(N/kappa_n), so N in {0, 1e-30, 1e30} is exact/cancellation-free.
    Entries with N == 0 ignore xbar and C. Negative/non-finite N are set to 0 (guard
    ``niw_update.invalid_count``). Returns (m_n (K,D), kappa_n (K,), nu_n (K,), S_n (K,D,D)).
    """
    K, D = _kd("m0", m0)
    dtype, dev = _out_dtype(m0), m0.device
    m0_ = m0.to(_F64)
    S0_ = _sym(_mat("S0", S0, K, D))
    xb = _vecD("xbar", xbar, K, D)
    C_ = torch.zeros_like(S0_) if C is None else _sym(_mat("C", C, K, D))
    k0 = _vec("kappa0", kappa0, K, dev)
    n0 = _vec("nu0", nu0, K, dev)
    N_ = _vec("N", N, K, dev)
    _require_finite("m0", m0_)
    _require_finite("S0", S0_)
    if not bool(((k0 > 0) & torch.isfinite(k0)).all()):
        raise B3dgsError("kappa0 must be finite and > 0",
                         fix="pass kappa0 > 0 for every Gaussian "
                             f"(posterior.niw.kappa0, default {field_default(NIWBlock, 'kappa0')})")
    if not bool(((n0 > D - 1) & torch.isfinite(n0)).all()):
        raise B3dgsError(f"nu0 must be finite and > D-1 = {D - 1} for a proper inverse-Wishart",
                         fix="pass nu0 > D - 1 for every Gaussian "
                             f"(posterior.niw.nu0, default {field_default(NIWBlock, 'nu0')})")
    N_ = zero_invalid("niw_update.invalid_count", N_)
    has = N_ > 0
    xb = torch.where(has[:, None], xb, m0_)
    C_ = torch.where(has[:, None, None], C_, torch.zeros_like(C_))
    _require_finite("xbar (entries with N > 0)", xb)
    _require_finite("C (entries with N > 0)", C_)

    kappa_n = k0 + N_
    w0 = k0 / kappa_n
    w1 = N_ / kappa_n
    m_n = w0[:, None] * m0_ + w1[:, None] * xb
    nu_n = n0 + N_
    d = xb - m0_
    coef = k0 * w1
    S_n = S0_ + C_ + coef[:, None, None] * (d[:, :, None] * d[:, None, :])
    S_n = _sym(S_n)
    return m_n.to(dtype), kappa_n.to(dtype), nu_n.to(dtype), S_n.to(dtype)


def niw_batch_stats(
    x: torch.Tensor, w: Optional[torch.Tensor] = None
) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Weighted sufficient statistics (N, xbar, C) of pseudo-observations for Eq. 2-3.

    x: (K,n,D); w: (K,n) non-negative weights (default 1). N = sum w, xbar = weighted mean
    (0 where N == 0), C = sum_i w_i (x_i - xbar)(x_i - xbar)^T (two-pass, centred).
    """
    if not isinstance(x, torch.Tensor) or x.ndim != 3:
        raise B3dgsError(f"x: expected a (K, n, D) tensor, got {getattr(x, 'shape', type(x).__name__)}",
                         fix="pass x as a float tensor of shape (K, n, D): n observations of a D-vector for each of "
                             "K Gaussians")
    K, n, D = x.shape
    dtype = _out_dtype(x)
    x_ = x.to(_F64)
    _require_finite("x", x_)
    if w is None:
        w_ = torch.ones(K, n, dtype=_F64, device=x.device)
    else:
        if not isinstance(w, torch.Tensor) or tuple(w.shape) != (K, n):
            raise B3dgsError(f"w: expected shape ({K}, {n}), got {getattr(w, 'shape', type(w).__name__)}",
                             fix="pass w of shape (K, n), one weight per observation in x, or w=None for unit "
                                 "weights")
        w_ = w.to(_F64)
        if not bool((torch.isfinite(w_) & (w_ >= 0)).all()):
            raise B3dgsError("w: weights must be finite and >= 0",
                             fix="pass finite weights >= 0 (e.g. compositing weights), or w=None for unit weights")
    N = w_.sum(1)
    has = N > 0
    Nsafe = torch.where(has, N, torch.ones_like(N))
    xbar = (w_[..., None] * x_).sum(1) / Nsafe[:, None]
    # one correction pass against rounding in the first mean (coordinates ~1e4)
    xbar = xbar + (w_[..., None] * (x_ - xbar[:, None, :])).sum(1) / Nsafe[:, None]
    xbar = torch.where(has[:, None], xbar, torch.zeros_like(xbar))
    dev = x_ - xbar[:, None, :]
    C = torch.einsum("kn,kni,knj->kij", w_, dev, dev)
    return N.to(dtype), xbar.to(dtype), _sym(C).to(dtype)


# ----------------------------------------------------------------------------- summaries
def prior_scale_for_expected_cov(Sigma: torch.Tensor, nu0: Scalar) -> torch.Tensor:
    """S0 = Sigma * (nu0 - D - 1), so that E[Sigma] under the NIW prior (Eq. 1) equals Sigma."""
    if not isinstance(Sigma, torch.Tensor) or Sigma.ndim != 3 or Sigma.shape[-1] != Sigma.shape[-2]:
        raise B3dgsError(f"Sigma: expected (K, D, D), got {getattr(Sigma, 'shape', type(Sigma).__name__)}",
                         fix="pass Sigma as a float tensor of shape (K, D, D), one square covariance per Gaussian")
    K, D = int(Sigma.shape[0]), int(Sigma.shape[-1])
    nu = _vec("nu0", nu0, K, Sigma.device)
    if not bool((nu > D + 1).all()):
        raise B3dgsError(f"nu0 must be > D+1 = {D + 1} for E[Sigma] to exist",
                         fix=f"pass nu0 > D + 1 (posterior.niw.nu0, default {field_default(NIWBlock, 'nu0')})")
    S0 = _sym(Sigma.to(_F64)) * (nu - D - 1)[:, None, None]
    return S0.to(_out_dtype(Sigma))


def expected_cov(S_n: torch.Tensor, nu_n: Scalar, eps: float = EXPECTED_COV_DENOM_EPS) -> torch.Tensor:
    """Posterior E[Sigma] = S_n / (nu_n - D - 1) (Sec. 2, after Eq. 3).

    The denominator is floored at ``eps`` (guard ``niw.expected_cov_denom_floor``).
    """
    if not isinstance(S_n, torch.Tensor) or S_n.ndim != 3 or S_n.shape[-1] != S_n.shape[-2]:
        raise B3dgsError(f"S_n: expected (K, D, D), got {getattr(S_n, 'shape', type(S_n).__name__)}",
                         fix="pass S_n as a float tensor of shape (K, D, D), one square scale matrix per Gaussian "
                             "(niw_update's S_n)")
    K, D = int(S_n.shape[0]), int(S_n.shape[-1])
    denom = _vec("nu_n", nu_n, K, S_n.device) - D - 1
    denom = guard_fill("niw.expected_cov_denom_floor", ~(denom >= eps), denom, eps)
    return (_sym(S_n.to(_F64)) / denom[:, None, None]).to(_out_dtype(S_n))


def mean_variance(
    S_n: torch.Tensor, nu_n: Scalar, kappa_n: Scalar, eps: float = EXPECTED_COV_DENOM_EPS
) -> torch.Tensor:
    """Var[mu] = E[Sigma] / kappa_n as a (K,D,D) covariance (Sec. 2, after Eq. 3)."""
    E = expected_cov(S_n, nu_n, eps).to(_F64)
    k = _vec("kappa_n", kappa_n, E.shape[0], E.device)
    k = guard_fill("niw.kappa_floor", ~(k >= KAPPA_FLOOR), k, KAPPA_FLOOR)
    return (E / k[:, None, None]).to(_out_dtype(S_n))


def position_variance(
    S_n: torch.Tensor, nu_n: Scalar, kappa_n: Scalar, eps: float = EXPECTED_COV_DENOM_EPS
) -> torch.Tensor:
    """Scalar position variance trace(Var[mu]) / D, shape (K,)."""
    V = mean_variance(S_n, nu_n, kappa_n, eps)
    return V.diagonal(dim1=-2, dim2=-1).sum(-1) / V.shape[-1]


def posterior_mean_params(
    m_n: torch.Tensor, kappa_n: Scalar, nu_n: Scalar, S_n: torch.Tensor
) -> Tuple[torch.Tensor, torch.Tensor]:
    """Posterior-mean geometry (E[mu] = m_n, E[Sigma]) of NIW(m_n, kappa_n, nu_n, S_n)."""
    K, D = _kd("m_n", m_n)
    _mat("S_n", S_n, K, D)
    _vec("kappa_n", kappa_n, K, m_n.device)
    return m_n, expected_cov(S_n, nu_n)


# ----------------------------------------------------------------------------- cholesky / sampling
def tril_solve(A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """A^{-1} B for lower-triangular A (..., D, D) and B (..., D, M), by forward substitution written
    elementwise (vectorised over the batch; batched LAPACK calls on 3x3 blocks are far slower)."""
    D = int(A.shape[-1])
    rows = []
    for i in range(D):
        r = B[..., i, :]
        for j in range(i):
            r = r - A[..., i, j, None] * rows[j]
        rows.append(r / A[..., i, i, None])
    return torch.stack(rows, dim=-2)


def bartlett_factor(nu: torch.Tensor, n_samples: int, D: int, generator: Optional[torch.Generator] = None) -> torch.Tensor:
    """Lower-triangular Bartlett factors A (S, K, D, D) for degrees of freedom nu (K,):
    A_ii = sqrt(chi2(nu - i + 1)), A_ij ~ N(0, 1) (i > j), so A A^T ~ Wishart(I, nu)."""
    K = int(nu.shape[0])
    df = nu[None, :, None] - torch.arange(D, dtype=_F64, device=nu.device)  # (1,K,D): nu - i + 1, i=1..D
    shape_g = (0.5 * df).expand(n_samples, K, D).contiguous()
    gdev = generator.device if generator is not None else nu.device  # draws on the generator's device
    chi2 = 2.0 * torch._standard_gamma(shape_g.to(gdev), generator=generator).to(nu.device)
    chi2 = guard_fill("sample_niw.bartlett_chi2_floor", ~(chi2 >= BARTLETT_CHI2_FLOOR), chi2, BARTLETT_CHI2_FLOOR)
    rows, cols = torch.tril_indices(D, D, offset=-1, device=nu.device)
    A = torch.diag_embed(torch.sqrt(chi2))
    # only the D(D-1)/2 strictly-lower entries are drawn
    A[..., rows, cols] = randn((n_samples, K, rows.numel()), generator=generator, dtype=_F64, device=nu.device)
    return A


@dataclass
class NIWSampler:
    """Validated, factorised NIW(m_n, kappa_n, nu_n, S_n) ready for repeated draws (:func:`draw_niw`):
    the set-up (checks, Cholesky of S_n, kappa floor) is done once. All float64."""

    m: torch.Tensor  # (K, D)
    kappa: torch.Tensor  # (K,) floored at KAPPA_FLOOR
    nu: torch.Tensor  # (K,)
    L: torch.Tensor  # (K, D, D) lower Cholesky factor of S_n


def niw_sampler(m_n: torch.Tensor, kappa_n: Scalar, nu_n: Scalar, S_n: torch.Tensor) -> NIWSampler:
    K, D = _kd("m_n", m_n)
    dev = m_n.device
    m = m_n.to(_F64)
    _require_finite("m_n", m)
    S = _mat("S_n", S_n, K, D)
    nu = _vec("nu_n", nu_n, K, dev)
    kap = _vec("kappa_n", kappa_n, K, dev)
    if not bool(((nu > D - 1) & torch.isfinite(nu)).all()):
        raise B3dgsError(f"nu_n must be finite and > D-1 = {D - 1}",
                         fix="pass nu_n > D - 1 for every Gaussian, as niw_update returns it from a prior with nu0 > "
                             "D + 1")
    kap = guard_fill("niw.kappa_floor", ~(kap >= KAPPA_FLOOR), kap, KAPPA_FLOOR)
    return NIWSampler(m, kap, nu, safe_cholesky(S))  # S is float64 here, so L is float64


def draw_niw(sampler: NIWSampler, n_samples: int, generator: Optional[torch.Generator] = None
             ) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """n draws as factors: mu (S,K,D), X (S,K,D,D) with Sigma = X^T X, and the Bartlett factor A.

    With S_n = L L^T and A A^T ~ W(I, nu): W = L^{-T} A A^T L^{-1} ~ W(S_n^{-1}, nu), hence
    Sigma = W^{-1} = X^T X with X = A^{-1} L^T (no inverses); mu = m_n + X^T z / sqrt(kappa_n), z ~ N(0, I),
    so Cov[mu | Sigma] = Sigma / kappa_n. The draw whitened by E[Sigma] = S_n / (nu - D - 1) is
    (nu - D - 1) (A A^T)^{-1}, a function of A alone.
    """
    if not isinstance(n_samples, int) or n_samples < 1:
        raise B3dgsError(f"n_samples must be a positive int, got {n_samples!r}",
                         fix="pass n_samples as an int >= 1 (e.g. uq.native.samples)")
    K, D = sampler.m.shape
    A = bartlett_factor(sampler.nu, n_samples, D, generator)
    X = tril_solve(A, sampler.L.transpose(-1, -2).unsqueeze(0))
    z = randn((n_samples, K, D), generator=generator, dtype=_F64, device=sampler.m.device)
    mu = sampler.m[None] + (X * z[..., :, None]).sum(-2) / torch.sqrt(sampler.kappa)[None, :, None]  # X^T z
    return mu, X, A


def sample_niw_factors(m_n: torch.Tensor, kappa_n: Scalar, nu_n: Scalar, S_n: torch.Tensor, n_samples: int,
                       generator: Optional[torch.Generator] = None) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`draw_niw` of :func:`niw_sampler` (one-off draws)."""
    return draw_niw(niw_sampler(m_n, kappa_n, nu_n, S_n), n_samples, generator)


def sample_niw(m_n: torch.Tensor, kappa_n: Scalar, nu_n: Scalar, S_n: torch.Tensor, n_samples: int,
               generator: Optional[torch.Generator] = None) -> Tuple[torch.Tensor, torch.Tensor]:
    """Draw (mu, Sigma) ~ NIW(m_n, kappa_n, nu_n, S_n) for all K at once (samples for Eq. 4), by
    Bartlett's decomposition (see :func:`sample_niw_factors`).
    Returns mu (S,K,D), Sigma (S,K,D,D); deterministic given ``generator``.
    Memory is O(S*K*D*D) float64: chunk over samples for very large K.
    """
    dtype = _out_dtype(m_n)
    mu, X, _ = sample_niw_factors(m_n, kappa_n, nu_n, S_n, n_samples, generator)
    Sigma = _sym((X.unsqueeze(-1) * X.unsqueeze(-2)).sum(-3))  # X^T X
    return mu.to(dtype), Sigma.to(dtype)


#: the counts ``posterior.niw.count`` offers (names kept stable for scripts outside the project)
COUNTS = ("paper", "weight", "fisher", "fisher3")
#: floor on the plug-in residual variance σ̂² that turns Fisher information into precision
COUNT_SIGMA2_FLOOR = 1e-8


def fisher_count(fisher_trace: Tensor, S0: Tensor, kappa0: float, nu0: float) -> Tensor:
    """(K,) the count N̂ whose NIW centre variance under Eq. 2-3 equals the Laplace variance of the centre.

    With the pseudo-observations at the centre (C = 0) and S_n ≈ S0, Eq. 2-3 give Var[μ] = E[Σ]/κ_n =
    S0 / ((ν0 + N̂ - D - 1)(κ0 + N̂)). Equating its mean per-axis precision, (κ0 + N̂)(ν0 - D - 1 + N̂) / s0 with
    s0 = tr S0 / D, to the Laplace one, p = tr(F) / D (F: the Fisher information of μ over the training pixels, over
    σ̂²), gives N̂² + (κ0 + a) N̂ + κ0 a - s0 p = 0 with a = ν0 - D - 1, whose non-negative root this returns (0 where
    the data add no precision beyond the prior's). Non-finite inputs give 0 (guard ``niw.count_nonfinite``)."""
    a = float(nu0) - D - 1
    s0 = torch.diagonal(S0.double(), dim1=-2, dim2=-1).sum(-1) / D
    p = fisher_trace.double() / D
    c = float(kappa0) * a - s0 * p
    b = float(kappa0) + a
    disc = (b * b - 4.0 * c).clamp_min(0.0)
    n = (0.5 * (torch.sqrt(disc) - b)).clamp_min(0.0)
    n = guard_fill("niw.count_nonfinite", ~torch.isfinite(n), n, 0.0)
    return n


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

    ``count`` (``posterior.niw.count``) chooses N̂_k: ``paper`` (the EMA above, bit for bit), ``weight``, ``fisher``
    (:func:`fisher_count`) or ``fisher3`` (a full 3×3 centre covariance), the last three from one pass over the
    training views when the posterior is used (:meth:`view_pass`); docs/counts.md defines them.
    ``count_scale`` (c, default 1 = the paper) uses c·N̂_k in Eq. 2-3 (``state["N"]`` unchanged), so a trained run's
    posterior can be re-evaluated at another c without retraining (docs/user-guide.md).
    """

    per_gaussian_state: ClassVar[tuple[str, ...]] = ("m0", "S0", "N", "ediag", "m_n", "kappa_n", "nu_n", "S_n",
                                                     "F", "mu_prec_chol")

    needs_residuals: ClassVar[bool] = True  # reads info["sq_err_sum"]
    changes_training: ClassVar[bool] = False  # it reads summaries; splats, optimizers, gradients untouched
    label_settings: ClassVar[dict] = {"count": "paper"}  # count=fisher runs are labelled niw@fisher

    kappa0: float = 0.01
    nu0: float = 5.0  # D + 2
    ema: float = 0.99  # EMA of the count summary N̂
    update_every: int = 100  # recompute Eq. 2-3 from the summaries every n steps (and whenever used)
    t_niw: Optional[int] = None  # None: 0 (active from the start)
    cov_mode: str = "relative"  # how a posterior sample replaces the rendered covariance: relative | absolute | none
    plugin_noise: bool = True  # the plug-in residual MSE as the aleatoric variance (NIW rows)
    mse_ema: float = 0.99  # EMA of that residual MSE
    sampler_backend: str = "auto"  # posterior draws (uq=native): "cpu" (C++, one pass), "torch" (reference) or "auto"
    count_scale: float = 1.0  # c in N̂ <- c·N̂ at the posterior refresh (Eq. 2-3); 1 = the paper, < 1 widens it
    count: str = "paper"  # N̂: paper (the EMA) | weight | fisher | fisher3 (see the class docstring)
    fisher_probes: int = 4  # Rademacher probes per training view for the Fisher counts (one backward pass each)

    def validate(self, max_steps: int = 0, **kw) -> None:
        check_field(self, "posterior.niw.kappa0", not self.kappa0 <= 0, "> 0")
        if self.nu0 <= D + 1:
            raise B3dgsError(f"posterior.niw.nu0 must be > D + 1 = {D + 1} for a proper prior with finite E[Σ]",
                             fix=f"pass posterior.niw.nu0 > 4, e.g. the default {field_default(self, 'nu0')} (D + 2)")
        check_field(self, "posterior.niw.ema", 0 <= self.ema < 1, "in [0, 1)", None, " (0 keeps only the latest count)")
        check_field(self, "posterior.niw.update_every", not self.update_every < 1, ">= 1", "as an integer >= 1")
        if self.cov_mode not in ("relative", "absolute", "none"):
            raise B3dgsError("posterior.niw.cov_mode must be relative | absolute | none",
                             fix="pass posterior.niw.cov_mode=relative, absolute or none")
        if self.sampler_backend not in ("auto", "cpu", "torch"):
            raise B3dgsError("posterior.niw.sampler_backend must be auto | cpu | torch",
                             fix="pass posterior.niw.sampler_backend=auto, cpu or torch")
        check_field(self, "posterior.niw.count_scale",
                    isinstance(self.count_scale, (int, float)) and 0 < float(self.count_scale) < float("inf"),
                    "a finite number > 0", "as a finite number > 0", " (< 1 widens the posterior)", got=True)
        if self.count not in COUNTS:
            raise B3dgsError(f"posterior.niw.count={self.count} is not a count{did_you_mean(str(self.count), COUNTS)}",
                             f"pass posterior.niw.count={'|'.join(COUNTS)}")
        p = self.fisher_probes
        check_field(self, "posterior.niw.fisher_probes", not isinstance(p, bool) and isinstance(p, int) and p >= 1,
                    "an integer >= 1", "as an integer >= 1", got=True)

    # ------------------------------------------------------------------ state
    def _prior_for(self, splats, rows: Optional[Tensor] = None):
        means = splats["means"].detach()
        cov = covariance_3d(splats["quats"].detach(), splats["scales"].detach())
        if rows is not None:
            means, cov = means[rows], cov[rows]
        nu0 = torch.full((means.shape[0],), float(self.nu0), dtype=torch.float64, device=means.device)
        return means.double(), prior_scale_for_expected_cov(cov.double(), nu0)

    def initialize_state(self, *, splats, scene, info):
        m0, S0 = self._prior_for(splats)
        n, dev = m0.shape[0], m0.device
        st = {"m0": m0, "S0": S0, "N": torch.zeros(n, dtype=torch.float64, device=dev),
              "ediag": torch.diagonal(S0, dim1=-2, dim2=-1) / (self.nu0 - D - 1),
              "mse": torch.tensor(0.0, dtype=torch.float64, device=dev),
              "mse_n": torch.tensor(0.0, dtype=torch.float64, device=dev),
              "n_views": torch.tensor(float(len(scene.train)) if scene is not None else 1.0, device=dev)}
        self._refresh(st, splats)
        return st

    # ------------------------------------------------------------------ updates
    @torch.no_grad()
    def step_post_backward(self, *, splats, optimizers, state, step, info):
        # tensor arithmetic only (no host synchronisation per step on a GPU)
        if self.plugin_noise or self.count != "paper":  # σ̂²: the aleatoric variance, and the Fisher counts' scale
            mse = info["sq_err_sum"].double() / max(int(info["num_values"]), 1)
            state["mse"] = self.mse_ema * state["mse"] + (1 - self.mse_ema) * mse
            state["mse_n"] = self.mse_ema * state["mse_n"] + (1 - self.mse_ema)
        if step < (self.t_niw or 0) or self.count != "paper":  # the other counts come from a view pass
            return
        vis = info["per_gaussian"]["radii"][0] > 0
        o = torch.sigmoid(splats["opacities"].detach()).double() * vis
        raw = o * torch.sqrt(torch.clamp(state["ediag"].prod(-1), min=0.0))
        total = raw.sum()
        eff_pixels = info["render"].alpha.detach().sum().double()
        rs = info.get("resolution_scale", 1.0)
        if rs != 1.0:  # a downsampled step (schedule=dash): the count in full-resolution pixels
            eff_pixels = eff_pixels / (rs * rs)
        ok = (total > 0) & (eff_pixels > 0)
        target = raw * torch.where(ok, eff_pixels * self.train_views(state, info) / torch.where(ok, total, 1.0), 0.0)
        keep = torch.where(vis.any(), self.ema, 1.0)  # no visible Gaussian: the counts stay as they are
        state["N"].mul_(keep).add_((1 - keep) * target)
        if "refresh" in self.periodic(step, info):
            self._refresh(state, splats)

    def periodic(self, step: int, info: dict) -> tuple[str, ...]:
        """``refresh`` (Eq. 2-3 from the running counts) every ``update_every`` steps from ``t_niw`` (paper count)."""
        if self.count == "paper" and step >= (self.t_niw or 0) and step % self.update_every == 0:
            return ("refresh",)
        return ()

    @torch.no_grad()
    def _refresh(self, state, splats) -> None:
        """Eq. 2-3 with N̂ ← count_scale·N̂, x̄ = current centre and C = 0."""
        xbar = splats["means"].detach().double()
        n = xbar.shape[0]
        m_n, k_n, nu_n, S_n = niw_update(state["m0"], float(self.kappa0), float(self.nu0), state["S0"],
                                         state["N"] * float(self.count_scale), xbar)  # C = 0
        state["m_n"], state["kappa_n"], state["nu_n"], state["S_n"] = m_n, k_n, nu_n, S_n
        state["ediag"] = torch.diagonal(expected_cov(S_n, nu_n), dim1=-2, dim2=-1).clone()
        if self.count == "fisher3" and "F" in state and state["F"].shape[0] == n:
            # centre precision: the NIW prior's, κ0 E0[Σ]⁻¹ with E0[Σ] = S0 / (ν0 - D - 1), plus c·F/σ̂²
            prior_cov = state["S0"] / (float(self.nu0) - D - 1)
            prec = float(self.kappa0) * torch.cholesky_inverse(safe_cholesky(prior_cov))
            state["mu_prec_chol"] = safe_cholesky(_sym(prec + float(self.count_scale) * state["F"]))

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
        if "F" in state and state["F"].shape[0] == state["N"].shape[0]:
            state["F"][rows] = 0.5 * state["F"][rows]  # the parent's information, shared like its count
        # the posterior (m_n, S_n, ...) of new rows is refreshed at the next scheduled update or on use

    # ------------------------------------------------------------------ counts from a pass over the views
    def view_pass(self, *, state) -> Optional[list[ViewAccumulator]]:
        """``weight``: the pass's weight sums only; ``fisher``/``fisher3``: also the centres' Fisher information."""
        if self.count == "paper":
            return None
        return [FisherAccumulator(int(self.fisher_probes))] if self.count.startswith("fisher") else []

    @torch.no_grad()
    def absorb_view_sums(self, *, splats, state, sums: dict) -> None:
        """Set N̂ (and F for ``fisher3``) from the pass's weight sums or :class:`FisherAccumulator` over the training views,
        then refresh the posterior (Eq. 2-3)."""
        n = splats["means"].shape[0]
        if self.count == "weight":
            count = sums["weight_sum"].double()
        else:
            F = sums["fisher"].double()
            if tuple(F.shape) != (n, D, D):
                raise B3dgsError(f"posterior.niw: the view pass gave a Fisher of shape {tuple(F.shape)}, expected ({n}, 3, 3)",
                                 fix="this is a bug in b3dgs (the NIW block's own Fisher accumulator): rerun with "
                                     "b3dgs.debug=true and report the traceback")
            s2 = float(state["mse"] / state["mse_n"]) if float(state["mse_n"]) > 0 else None  # plug-in σ̂²
            low = s2 is None or not s2 >= COUNT_SIGMA2_FLOOR
            if guard("niw.sigma2_floor", int(low)):
                s2 = COUNT_SIGMA2_FLOOR if s2 is None or not math.isfinite(s2) else max(s2, COUNT_SIGMA2_FLOOR)
            P = _sym(F) / float(s2)
            count = fisher_count(torch.diagonal(P, dim1=-2, dim2=-1).sum(-1), state["S0"], self.kappa0, self.nu0)
            if self.count == "fisher3":
                P = guard_fill("niw.count_nonfinite", ~torch.isfinite(P).all(-1).all(-1)[:, None, None], P, 0.0)
                state["F"] = P
        count = guard_fill("niw.count_nonfinite", ~(torch.isfinite(count) & (count >= 0)), count, 0.0)
        state["N"] = count.to(state["N"].dtype)
        self._refresh(state, splats)

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
        prep = niw_sampler(post["m_n"], post["kappa_n"], post["nu_n"], post["S_n"])
        dtype = splats["means"].dtype
        if self.cov_mode == "relative":
            # W = E[Σ]^{-1/2} Σ E[Σ]^{-T/2} = c (A Aᵀ)^{-1}, c = ν_n - D - 1 (see draw_niw); rendered as
            # L W Lᵀ = YᵀY with Y = √c A^{-1} Lᵀ and L the rendered covariance's Cholesky factor
            sqrt_c = (post["nu_n"] - D - 1).clamp_min(EXPECTED_COV_DENOM_EPS).sqrt()[None, :, None, None]
            cov_r = covariance_3d(splats["quats"].detach(), splats["scales"].detach()).double()
            LrT = safe_cholesky(cov_r).transpose(-1, -2).unsqueeze(0)

        ext = self._sampling_extension(splats["means"].device)
        if ext is not None:
            mode = {"none": 0, "absolute": 1, "relative": 2}[self.cov_mode]
            empty = torch.zeros(0, dtype=torch.float64)
            args = (prep.m.contiguous(), prep.kappa.contiguous(), prep.nu.contiguous(), prep.L.contiguous(),
                    LrT[0].contiguous() if mode == 2 else empty, sqrt_c.reshape(-1).contiguous() if mode == 2 else empty)

        chol = state.get("mu_prec_chol") if self.count == "fisher3" else None
        if chol is not None and chol.shape[0] != prep.m.shape[0]:
            chol = None

        def centre(out, n, generator):
            """fisher3: μ ~ N(m_n, (L Lᵀ)⁻¹) with L the Cholesky factor of the centre precision, as L⁻ᵀ ε."""
            if chol is not None:
                eps = randn((n,) + tuple(prep.m.shape), generator=generator, dtype=torch.float64, device=prep.m.device)
                x = torch.linalg.solve_triangular(chol.transpose(-1, -2).unsqueeze(0), eps.unsqueeze(-1), upper=True)
                out["means"] = (prep.m.unsqueeze(0) + x.squeeze(-1)).to(dtype)
            return out

        @torch.no_grad()
        def draw(n, generator, params):
            out = dict(params)
            if ext is not None:
                seed = int(torch.randint(0, 2**62, (1,), generator=generator))
                means, covs, floored = ext.niw_draw(*args, n, mode, BARTLETT_CHI2_FLOOR, seed,
                                                    dtype == torch.float64, torch.get_num_threads())
                guard("sample_niw.bartlett_chi2_floor", int(floored))
                out["means"] = means
                if mode:
                    out["covars"] = covs
                return centre(out, n, generator)
            mu, X, A = draw_niw(prep, n, generator)
            out["means"] = mu.to(dtype)
            if self.cov_mode != "none":
                Y = X if self.cov_mode == "absolute" else tril_solve(A, LrT) * sqrt_c  # Σ = YᵀY
                out["covars"] = (Y.unsqueeze(-1) * Y.unsqueeze(-2)).sum(-3).to(dtype)  # symmetric by construction
            return centre(out, n, generator)

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
    def condition_on_view(self, *, splats, state, weight_sums=None, render=None, camera=None):
        """The posterior after one more view's pseudo-observations (acquisition: greedy conditioned batches): n_k = c·w_k
        observations at the current centre (x̄_k = μ_k, C_k = 0), the closed-form update of the paper's NIW
        appendix applied to the current posterior. The summaries already sit at μ_k with C = 0, and two such
        batches at one point combine into one of summed count (conjugacy), so this is N̂ ← N̂ + w on a copy of
        the state, refreshed."""
        if self.count.startswith("fisher") or weight_sums is None:
            return None  # a view's Fisher needs its render's per-pixel gradients, not its weight sums
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
        var_mu = mean_variance(state["S_n"], state["nu_n"], state["kappa_n"])
        chol = state.get("mu_prec_chol") if self.count == "fisher3" else None
        if chol is not None and chol.shape[0] == var_mu.shape[0]:
            var_mu = torch.cholesky_inverse(chol)
        return {"niw_pos_var": (torch.diagonal(var_mu, dim1=-2, dim2=-1).sum(-1) / D).float(),
                "niw_kappa": state["kappa_n"].float(), "niw_nu": state["nu_n"].float()}

    def summary(self, *, state):
        ex = self.export(splats=None, state=state)
        return {"mean_count": float(state["N"].mean()) if state["N"].numel() else 0.0,
                "median_pos_std": float(ex["niw_pos_var"].sqrt().median()) if state["N"].numel() else 0.0,
                "sigma2_plugin": self.aleatoric_variance(state=state)}
