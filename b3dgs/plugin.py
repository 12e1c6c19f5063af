"""Plugin base classes: one keyword hook signature shared by every plugin kind.

Every hook is called as ``hook(splats=, optimizers=, state=, step=, info=)``:
- ``splats``: the ``nn.ParameterDict`` of Gaussian parameters (means, quats, scales, opacities, sh0, shN);
- ``optimizers``: dict name -> torch optimizer;
- ``state``: the plugin's own dict from ``initialize_state``; the keys a plugin declares in
  ``per_gaussian_state`` hold (N, ...) tensors that the core's topology ops (clone, split, prune) re-index,
  so per-Gaussian state follows the Gaussians;
- ``step``: the training iteration (0-based);
- ``info``: everything else (render outputs, image size, scene extent, ``ops`` for topology changes, ...);
  ``info["per_gaussian"]`` holds this step's per-Gaussian render data as (S, N, ...) tensors (``radii``,
  ``means2d_grad``, ``weight_sum``, ``weight_sq_sum``), re-indexed by every topology change, so a plugin
  running after another one's prune still sees aligned values; ``info["loss_terms"]``: a list a plugin may
  append differentiable scalars to in ``step_pre_backward`` (added to the photometric loss before backward);
  with a training schedule (``schedule=dash``), ``info["resolution_scale"]`` (the step's view size over the
  full view's, so pixel sums convert to full-resolution units by / scale²) and ``info["budget_fraction"]``
  (see :meth:`Plugin.scheduled_cap`) and ``info["keep_fraction"]`` (trim to that share once, by usage; see
  ``AdaptiveDensityControl``); all absent under ``schedule=constant``.
New needs go into ``info``, never into new arguments, so the core never branches on a plugin's type.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, ClassVar, Optional

import torch
from torch import Tensor


@dataclass
class Plugin:
    """Base of every plugin kind (strategies, posterior blocks). All hooks are no-ops by default.

    What the core reads from a plugin is declared here: ``needs_weights`` says that the plugin reads the
    per-Gaussian compositing sums Σ_p w_kp and Σ_p w_kp² (``info["per_gaussian"]``), and :meth:`reads_pair_sums`
    on which steps (by default every step): the core asks the renderer for them only on a step where some plugin
    reads them;
    ``needs_residuals`` asks for ``info["sq_err_sum"]``, the step's summed squared residual (not computed otherwise);
    ``changes_training`` = False promises that the plugin only observes training (it never edits splats,
    optimizers, gradients or the topology), so a model with it trains bit for bit like one without it
    (``tests/test_rounds.py`` checks every plugin that promises it; the active-view study then shares
    such runs). State tensors must be created on the splats' device (``splats["means"].device``).
    """

    needs_weights: ClassVar[bool] = False
    needs_residuals: ClassVar[bool] = False
    changes_training: ClassVar[bool] = True
    #: the keys of ``state`` that hold per-Gaussian tensors (first dimension N): the topology ops re-index exactly
    #: these (a declared key whose first dimension is not N is an error; a key not created yet is skipped).
    #: ``None`` (plugins written before the declaration): every tensor of the state whose first dimension is N.
    per_gaussian_state: ClassVar[Optional[tuple[str, ...]]] = None

    def validate(self, **kwargs: Any) -> None:
        """Check this plugin's own field values (``kwargs``: ``max_steps``, the run's step budget, and ``sh_degree``, the
        model's SH degree, for posterior blocks; accept ``**kwargs`` for what later versions pass); raise
        :class:`~b3dgs.errors.B3dgsError` naming the bad field and the fix. The one validation method of every kind."""

    def initialize_state(self, *, splats, scene, info: dict) -> dict:
        return {}

    def periodic(self, step: int, info: dict) -> tuple[str, ...]:
        """The names of the periodic work this plugin does at ``step`` (e.g. ``("refresh",)``), decided from the step
        counter alone; ``()`` on an ordinary step. ``info``: the run's static info (``max_steps``, ...). Read by
        :class:`b3dgs.host_sync.HostSyncCallback` to tell ordinary steps, which must not synchronise, from the rest."""
        return ()

    def reads_pair_sums(self, step: int, info: dict) -> bool:
        """Whether this plugin reads the per-Gaussian pair sums (``info["per_gaussian"]["weight_sum"]`` and
        ``["weight_sq_sum"]``) at ``step``, decided from the step counter and the run's static info (``max_steps``)
        alone, like :meth:`periodic`. The core asks the renderer for the sums only on steps where some plugin
        returns True (on gsplat they are a second pass over the pixel-pair list, the largest per-step cost DPMM
        adds); on other steps they are absent from ``info``, and a plugin must not read sums that another
        plugin's cadence brought in on a step it does not declare. Default: ``needs_weights`` (every step)."""
        return self.needs_weights

    def step_pre_backward(self, *, splats, optimizers, state, step, info) -> None:
        pass

    def step_post_backward(self, *, splats, optimizers, state, step, info) -> None:
        pass

    @staticmethod
    def scheduled_cap(cap: Optional[int], n_init: int, info: dict) -> Optional[int]:
        """The Gaussian count a densifying strategy may reach at this step: its own ``cap`` when the training
        schedule sets no budget, else ``n_init + (cap - n_init) * info["budget_fraction"]`` (the primitive
        schedule of ``schedule=dash``, :mod:`b3dgs.schedule`); without a cap, the head-room is 5 x ``n_init``
        (DashGaussian's initial primitive momentum)."""
        f = info.get("budget_fraction")
        if f is None:
            return cap
        ref = int(cap) if cap is not None else 6 * int(n_init)
        return int(n_init + max(ref - int(n_init), 0) * min(max(float(f), 0.0), 1.0))

    def on_topology(self, *, splats, optimizers, state, step, info) -> None:
        """Called after clone/split/prune. ``info`` holds ``op``, ``index`` (N',) source rows,
        ``fresh`` (N',) bool rows that are new children, and ``parent_ids``."""


@dataclass
class PosteriorBlock(Plugin):
    """A posterior block: closed-form or approximate posterior updates around the optimizer."""

    #: settings that change the method, with the value a run's label leaves unsaid (:mod:`b3dgs.labels`): any other
    #: value is written after the block's name, e.g. NIW's ``{"count": "paper"}`` labels ``count=fisher`` ``niw@fisher``
    label_settings: ClassVar[dict] = {}

    @staticmethod
    def stage_start(t: Optional[int], info: dict, divisor: int) -> int:
        """A stage threshold: ``t`` when configured, else max_steps // ``divisor`` (the canonical schedule).

        ``max_steps`` is the run's TOTAL step budget (``info["max_steps"]``), also when it is trained in rounds
        (the rounds continue the global step), so the thresholds never restart."""
        return int(t) if t is not None else int(info.get("max_steps", 0)) // divisor

    @staticmethod
    def strided_decay(ema: float, every: int) -> float:
        """The decay per update of an EMA meant to update every step with decay ``ema`` that updates only every
        ``every``-th step: ``ema ** every``, so that its memory in steps (~1 / (1 - ema)) is unchanged; ``ema`` itself
        (the same float) at ``every`` = 1."""
        return ema if every == 1 else ema ** every

    @staticmethod
    def train_views(state: dict, info: dict) -> float:
        """The number of views in the current training set: ``info["num_train_views"]`` (filled by the core
        every step, so it follows views acquired between training rounds), kept in ``state["n_views"]``
        (the value at initialisation until the first step, and for callers without the info key)."""
        n = info.get("num_train_views")
        if n is not None and "n_views" in state:
            state["n_views"].fill_(float(n))
        return float(n) if n is not None else float(state["n_views"])

    def sample(self, *, splats, state, n: int, generator: Optional[torch.Generator], params: dict, info: dict) -> dict:
        """Return ``params`` with the attributes this block samples replaced by (n, N, ...) draws."""
        return params

    def sampler(self, *, splats, state) -> Callable[[int, Optional[torch.Generator], dict], dict]:
        """A draw function ``draw(n, generator, params) -> params`` for repeated sampling from the current
        (fixed) posterior, with any set-up done once; by default every draw calls :meth:`sample`."""
        return lambda n, generator, params: self.sample(splats=splats, state=state, n=n, generator=generator,
                                                        params=params, info={})

    def posterior_mean(self, *, splats, state, params: dict) -> dict:
        """Return ``params`` with this block's attributes at their posterior mean."""
        return params

    def condition_on_view(self, *, splats, state, weight_sums: Optional[Tensor] = None, render=None,
                          camera=None) -> Optional[dict]:
        """A new state: the posterior after the pseudo-observations of one more view, without its image
        (acquisition's greedy_conditioned batch). ``weight_sums`` (N,) is Σ_p w_kp of the view's point-estimate
        render, in training-resolution pixels (the unit of the renderer-derived counts); ``render`` and ``camera``,
        when the caller passes them: that render at the resolution of the pass that made ``state`` (with weights)
        and its camera, for a block that needs more than Σ_p w (the SH posterior: Σ_p w² and the direction).
        ``state`` must not be modified. None (default): this block's posterior does not change with what is given."""
        return None

    def view_pass(self, *, state) -> Optional[list["ViewAccumulator"]]:
        """What this block sums over one pass of the training views before its posterior is used. None: no pass;
        a list (possibly empty) of :class:`ViewAccumulator`: a pass that feeds them, besides the renderer's own
        per-Gaussian sums (``weight_sum``, ``visible_views``). The core renders each view once for every accumulator
        of every block; the sums go to :meth:`absorb_view_sums`."""
        return None

    def absorb_view_sums(self, *, splats, state, sums: dict) -> None:
        """Update ``state`` from a view pass (``sums``: ``weight_sum``, ``visible_views`` and the ``result()`` of
        every accumulator of the pass)."""

    #: True: :meth:`aleatoric_variance` is a fallback, used only when no other block of the model gives σ̂² (the SH
    #: posterior's pass residual: NIW's plug-in σ̂² or the noise block's posterior comes first)
    aleatoric_fallback: ClassVar[bool] = False

    def aleatoric_variance(self, *, state) -> Optional[float]:
        """Per-pixel aleatoric variance this block provides (noise posterior), or None."""
        return None

    def export(self, *, splats, state) -> dict[str, Tensor]:
        """Per-Gaussian summaries (N,) or (N, d) for PLY export and reports."""
        return {}

    def summary(self, *, state) -> dict[str, Any]:
        """Scalar diagnostics for metrics.json."""
        return {}


class ViewAccumulator:
    """A per-Gaussian sum over one pass of views that a posterior block declares (:meth:`PosteriorBlock.view_pass`)
    and the core feeds (:meth:`b3dgs.module.SplatModule.view_sums`): ``start`` once, ``add`` per rendered view,
    ``result`` at the end. The core knows nothing of what is summed.

    ``key``: accumulators of one pass with equal keys run once, as ``a.merge(b)`` (e.g. the larger probe count);
    ``needs_means_grad``: the view is rendered with ``params["means"]`` requiring grad, so ``add`` may
    differentiate the render with respect to the centres (the render is then not under ``no_grad``)."""

    key: ClassVar[str] = ""
    needs_means_grad: ClassVar[bool] = False

    def start(self, *, params: dict, sh_degree: int, seed: int) -> None:
        """Allocate the sums for ``params`` (the Gaussians of the pass, detached) on their device."""

    def add(self, *, camera, render, params: dict, sh_degree: int) -> None:
        """Add one view: ``render`` is the renderer's output for ``camera`` (``rgb``, ``radii``, ``weight_sum``,
        ``weight_sq_sum``), rendered from ``params``."""
        raise NotImplementedError  # protocol: an abstract method (subclasses implement it)

    def result(self) -> dict[str, Tensor]:
        """The sums, by name (names must not clash with another accumulator's or the core's)."""
        raise NotImplementedError  # protocol: an abstract method (subclasses implement it)

    def merge(self, other: "ViewAccumulator") -> "ViewAccumulator":
        """The accumulator to run when two blocks ask for the same ``key`` (default: the first)."""
        return self


def validate_once(plugin, **run):
    """``plugin.validate(**run)`` unless it ran already, so that each plugin of a run is validated once (the config
    check builds and validates it, the model is built from it: :func:`b3dgs.validation.validate_config`); returns it."""
    if not getattr(plugin, "_validated", False):
        plugin.validate(**run)
        plugin._validated = True
    return plugin
