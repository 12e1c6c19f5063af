"""Native posterior uncertainty: re-render posterior samples (paper Eq. 4). :class:`NativeRegime` is shared by
``uq=native`` (``plugins/uq/native.py``) and the calibrated regimes (``plugins/uq/native_calibrated.py``)."""
from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Optional

import torch
from omegaconf import DictConfig, OmegaConf

from b3dgs.errors import B3dgsError
from b3dgs.plugin import PosteriorBlock
from b3dgs.uq.regime import Predictive, UQRegime, render_params, sample_spread


def _sigma2(blocks) -> Optional[float]:
    """σ̂² of ``[(block, state)]``: the last block that gives one; a block whose σ̂² is a fallback
    (``aleatoric_fallback``, the SH pass residual) only when no other does, so ``posterior=[niw,sh]`` keeps NIW's
    plug-in σ̂² as ``uq=[native_plus_sh]`` (the SH block added at evaluation) does."""
    main = fallback = None
    for blk, st in blocks:
        v = blk.aleatoric_variance(state=st)
        if v is None:
            continue
        if blk.aleatoric_fallback:
            fallback = float(v)
        else:
            main = float(v)
    return main if main is not None else fallback


@dataclass
class NativeRegime(UQRegime):
    """Draws S parameter sets from the trained posterior blocks (each block replaces the attributes it
    models, in the configured order: geometry for NIW; activity, opacity and colour as well for DPMM),
    re-renders them in batched calls and returns var = u_p + σ̂², where σ̂² is the aleatoric variance
    of the last configured block that offers one (NIW's plug-in residual MSE, or the NoiseBlock's
    E[σ²]). The prediction is the point-estimate render.

    ``count_scale`` (None: the model's own) draws from the posterior with N̂ ← c·N̂ (Eq. 2-3) in every
    block that has that setting, on a copy of the block and of its state: the trained model and its
    training are untouched (``bench/uq_count_scale.py`` measures what c does).

    ``add``: posterior blocks drawn after the model's own, built for this evaluation from one pass over the training
    views (blocks whose posterior is a function of the trained Gaussians, e.g. ``posterior.sh``'s directional SH
    posterior); with ``add``, a standard model (no posterior blocks) has a native posterior too. σ̂² comes from the
    model's blocks, else from the added ones. A block the model already carries with the same settings is the model's
    own (``posterior=[niw,sh]`` under ``uq=[native_plus_sh]`` is ``uq=native``); with other settings it is an error."""

    count_scale: Optional[float] = None
    count: Optional[str] = None
    add: Optional[dict] = None  # {name: PosteriorBlock} (instantiated by Hydra from conf/uq/native_sh.yaml)
    model_blocks: bool = True  # draw from the model's own blocks (false: only from ``add``)

    def validate(self, **kwargs) -> None:
        super().validate(**kwargs)
        for name, blk in (self.add or {}).items():
            if not isinstance(self._block(name, blk), PosteriorBlock):
                raise B3dgsError(f"add.{name} must be a posterior block (a _target_ to a PosteriorBlock class such as "
                                 f"b3dgs_plugins.posterior.sh.SHPosteriorBlock), got {type(blk).__name__}",
                                 f"remove add.{name}, or give it a _target_")

    @staticmethod
    def _block(name, blk):
        """An added block as built by Hydra (a dataclass built inside a dict node is stored as a structured node)."""
        if isinstance(blk, DictConfig) and isinstance(OmegaConf.get_type(blk), type) \
                and issubclass(OmegaConf.get_type(blk), PosteriorBlock):
            blk = OmegaConf.to_object(blk)
        return blk

    def _blocks(self, m):
        """(name, block, state) to draw from: the model's own, or copies with ``count_scale`` / ``count`` applied
        (``count``: ``posterior.niw.count``, e.g. ``weight``, re-evaluated on the trained model without retraining)."""
        out, carried = [], []
        for name, blk in (m.posterior.items() if self.model_blocks else ()):
            st = m.states[name]
            names = {f.name for f in fields(blk)}
            if self.count_scale is not None and "count_scale" in names:
                blk, st = replace(blk, count_scale=float(self.count_scale)), dict(st)
            if self.count is not None and "count" in names and blk.count != self.count:
                blk, st = replace(blk, count=str(self.count)), dict(st)
                blk.validate()
            out.append((name, blk, st))
        for name, blk in (self.add or {}).items():
            blk = self._block(name, blk)  # a posterior block: validate() checked it
            if self.model_blocks and name in m.posterior:
                own = m.posterior[name]
                if own == blk:  # posterior=[niw,sh] under uq=[native_plus_sh]: the model's own block is the same one
                    carried.append(name)
                    continue
                diff = ", ".join(f"{f.name} {getattr(own, f.name)!r} vs {getattr(blk, f.name)!r}" for f in fields(own)
                                 if type(own) is type(blk) and getattr(own, f.name) != getattr(blk, f.name))
                raise B3dgsError(f"uq: add.{name} differs from the model's own {name} block ("
                                 f"{diff or f'{type(own).__name__} vs {type(blk).__name__}'})",
                                 f"score the model's own with uq=native, or give add.{name} the same settings")
            blk.validate()
            out.append((name, blk, blk.initialize_state(splats=m.splats, scene=None, info={})))
        if carried:  # added blocks the model already carries with the same settings (no key otherwise: archived uq.json)
            self.fit_info["add_carried"] = carried
        return out

    def fit(self, models, scene):
        super().fit(models, scene)
        m = self.models[0]
        if not self.add and (not m.posterior or not self.model_blocks):
            raise B3dgsError("uq=native needs a model trained with posterior blocks (model=niw or model=dpmm) or blocks "
                             "added at evaluation (uq=[native_sh])",
                             fix="use uq=proxy (or uq=[native_sh]) for a standard model, or train with model=niw")
        # one prepared draw function per block: posterior set-up once, not per chunk or view
        blocks = self._blocks(m)
        m.prepare_posterior(scene.train if scene is not None else None, blocks=blocks)  # counts from a view pass
        self._fitted = [(blk, st) for _, blk, st in blocks]
        self.reset_conditioning()
        self.base = render_params(m)
        n_own = len(m.posterior) if self.model_blocks else 0
        own = _sigma2([(blk, m.states[name]) for name, blk in (m.posterior.items() if self.model_blocks else ())])
        if own is None:  # only added blocks (a standard model, or model_blocks=false): their σ̂²
            own = _sigma2(self._fitted[n_own:])
        self.sigma2 = own if own is not None else 0.0
        self.fit_info["sigma2_plugin"] = self.sigma2

    def condition(self, weight_sums) -> bool:
        """Draw from now on from the posterior conditioned on the pseudo-observations of one more view without
        its image: ``weight_sums`` (N,) = Σ_p w_kp of its point-estimate render in training-resolution pixels,
        passed to every block's ``condition_on_view`` (on copies of the states). Returns whether any block
        changed; :meth:`reset_conditioning` goes back to the fitted posterior."""
        m = self.models[0]
        new = [(blk, blk.condition_on_view(splats=m.splats, state=st, weight_sums=weight_sums)) for blk, st in self._current]
        if all(st2 is None for _, st2 in new):
            return False
        self._current = [(blk, st if st2 is None else st2) for (blk, st), (_, st2) in zip(self._current, new)]
        self.samplers = [blk.sampler(splats=m.splats, state=st) for blk, st in self._current]
        return True

    @torch.no_grad()
    def gaussian_spread(self, samples: int = 4, seed: int = 0) -> torch.Tensor:
        """(N,) how far the current posterior's draws move each Gaussian, in units of its size: mean over
        ``samples`` draws of ‖μ⁽ˢ⁾ − μ‖ / √tr Σ, float64. The draws use a generator seeded with ``seed``, so two
        calls (e.g. before and after :meth:`condition`) share their random numbers. (On the test scene, weight
        sums · this spread predicted the conditioned / unconditioned native score within ~0.05, Spearman 0.68
        over candidates; a saturating 1 − exp(−‖Δμ‖² / tr Σ) ranked as well but predicted ratios near 1.)"""
        p = self._draw(int(samples), torch.Generator(device="cpu").manual_seed(int(seed)))
        d2 = (p["means"].double() - self.base["means"].double()).square().sum(-1)
        size2 = torch.exp(2.0 * self.base["scales"].double()).sum(-1).clamp_min(1e-30)
        return (d2 / size2).sqrt().mean(0)

    def reset_conditioning(self) -> None:
        m = self.models[0]
        self._current = list(self._fitted)
        self.samplers = [blk.sampler(splats=m.splats, state=st) for blk, st in self._current]

    def _draw(self, n: int, generator) -> dict:
        """The point-estimate parameters with ``n`` draws of the current posterior (every block in turn)."""
        p = dict(self.base)
        for sampler in self.samplers:
            p = sampler(n, generator, p)
        return p

    @torch.no_grad()
    def spread(self, camera, generator=None):
        """(point-estimate render (H, W, 3), u_p (H, W)) of one view: Eq. 4 over ``samples`` draws."""
        m = self.models[0]
        _, u = sample_spread(m, camera, lambda n: self._draw(n, generator), self.samples, self.chunk)
        return m.render_eval(camera), u

    @torch.no_grad()
    def predict(self, camera, generator=None):
        mean, u = self.spread(camera, generator)
        return Predictive(mean=mean, var=u + self.sigma2, epistemic=u, aleatoric=self.sigma2)
